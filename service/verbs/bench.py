"""``meniscope bench BENCHMARK``: measuring front door; every module of ``service.bench`` adds one benchmark."""
from __future__ import annotations

import argparse
import importlib
import pkgutil


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``bench`` and, under it, the benchmarks that ``service.bench`` modules register (as service.cli finds verbs)."""
    parser = subparsers.add_parser("bench", help="speed and quality benchmarks", description=__doc__)
    benchmarks = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    import service.bench as bench

    for info in sorted(pkgutil.iter_modules(bench.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{bench.__name__}.{info.name}")
        if hasattr(module, "register"):  # a benchmark, not a helper such as the results writer
            module.register(benchmarks)
