"""The meniscope command: one dispatcher over the verbs listed below (README.md, "Command line").

Each module of ``service.verbs`` exposes ``register(subparsers)`` and is found by itself; ``training`` adds its verbs
through the ``meniscope.verbs`` entry-point group, so the runtime never imports it.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points

from service.errors import MeniscopeError


def build_parser() -> argparse.ArgumentParser:
    """The full parser: built-in verbs plus those that installed plugins register."""
    parser = argparse.ArgumentParser(prog="meniscope", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    import service.verbs as verbs

    for info in sorted(pkgutil.iter_modules(verbs.__path__), key=lambda m: m.name):
        importlib.import_module(f"{verbs.__name__}.{info.name}").register(sub)
    for ep in entry_points(group="meniscope.verbs"):
        try:
            register: Callable[[argparse._SubParsersAction], None] = ep.load()
        except ImportError as exc:  # a plugin whose package or extras are missing
            print(f"meniscope: verbs of {ep.value} unavailable: {exc}", file=sys.stderr)
            continue
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: run one verb; user errors print one line and exit 2."""
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if rest:  # a verb that parses its own options (``bench``) takes them; for any other, argparse's usual error
        if not hasattr(args, "options"):
            parser.parse_args(argv)
        args.options = [*rest, *args.options]
    try:
        return int(args.func(args) or 0)
    except MeniscopeError as exc:
        print(f"meniscope {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"meniscope {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
