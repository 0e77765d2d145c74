"""The meniscope command: one dispatcher over the verbs listed below (README.md, "Command line").

Each module of ``service.verbs`` exposes ``register(subparsers)`` and is found by itself; ``training`` adds its verbs
through the ``meniscope.verbs`` entry-point group, so the runtime never imports it.
"""

from __future__ import annotations

import _thread
import argparse
import importlib
import os
import pkgutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
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
        with _terminable(not getattr(args, "own_signals", False)):
            return int(args.func(args) or 0)
    except MeniscopeError as exc:
        print(f"meniscope {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"meniscope {args.verb}: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print(f"meniscope {args.verb}: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM


class Terminated(Exception):
    """SIGTERM (``kill``, a service manager's stop) in a verb's process: raised where the verb is, so that it unwinds
    as an interrupt does and its scratch folders go with it (a training's are tens of GB: killed ones filled a disk)."""


@contextmanager
def _terminable(enabled: bool) -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` in this process while the block runs (from the main thread; ``enabled``
    False for a verb that handles its signals itself, ``serve``). Where it lands in code whose exceptions Python
    swallows (an at-fork or ``__del__`` callback: a test run met one as a pool forked), it is delivered again once that
    code has returned. A worker forked meanwhile inherits the handler and is ended by the signal as it would have been
    without it."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    pid = os.getpid()

    def terminate(signum: int, frame: object) -> None:
        if os.getpid() != pid:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise Terminated

    def again(unraisable: sys.UnraisableHookArgs) -> None:
        if isinstance(unraisable.exc_value, Terminated):  # again from another thread, once this code has returned
            threading.Timer(0.01, _thread.interrupt_main, (signal.SIGTERM,)).start()
        else:
            hook(unraisable)

    previous, hook = signal.signal(signal.SIGTERM, terminate), sys.unraisablehook
    sys.unraisablehook = again
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        sys.unraisablehook = hook


if __name__ == "__main__":
    sys.exit(main())
