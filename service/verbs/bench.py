"""``meniscope bench BENCHMARK``: measuring front door; every module of ``service.bench`` with a ``register``
function adds one benchmark, imported only when it is the one asked for (so that help stays fast)."""

from __future__ import annotations

import argparse
import ast
import importlib
import pkgutil
from functools import partial
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``bench`` and, under it, one entry per benchmark module (its summary read from its source, unimported)."""
    parser = subparsers.add_parser("bench", help="speed and quality benchmarks", description=__doc__)
    benchmarks = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    import service.bench as bench

    for info in sorted(pkgutil.iter_modules(bench.__path__), key=lambda m: m.name):
        summary = _summary(Path(bench.__path__[0]) / f"{info.name}.py")
        if summary is None:  # a helper such as the results writer, not a benchmark
            continue
        p = benchmarks.add_parser(info.name, help=summary, add_help=False)
        p.add_argument("options", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        p.set_defaults(func=partial(_run, info.name))


def _summary(path: Path) -> str | None:
    """The first line of a benchmark module's docstring, or None for a module that registers no benchmark."""
    try:
        tree = ast.parse(path.read_text())
    except (OSError, SyntaxError):
        return None
    if not any(isinstance(node, ast.FunctionDef) and node.name == "register" for node in tree.body):
        return None
    first = " ".join((ast.get_docstring(tree) or "").split("\n\n")[0].split())  # the first paragraph, one line
    return first.split("``: ", 1)[-1]  # without the "``meniscope bench NAME``: " it starts with


def _run(name: str, args: argparse.Namespace) -> int:
    """Import the benchmark ``name``, parse its own options and run it."""
    parser = argparse.ArgumentParser(prog="meniscope bench")
    module = importlib.import_module(f"service.bench.{name}")
    module.register(parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK"))
    parsed = parser.parse_args([name, *args.options])
    return int(parsed.func(parsed) or 0)
