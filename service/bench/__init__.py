"""Benchmarks behind ``meniscope bench``: one module per benchmark, each exposing ``register(subparsers)``.

A benchmark measures one part of the pipeline (speed and quality, side by side in one run)
and writes its figures as JSON plus a Markdown table into the folder it is given.
"""

from service.errors import MeniscopeError


def parse_pairs(text: str, option: str, form: str) -> list[tuple[int, int]]:
    """ "2x4,1x1" -> [(2, 4), (1, 1)], each number at least 1; a one-line error naming ``option`` and the
    ``form`` expected (e.g. "SUPERSAMPLExSUN_SAMPLES like 2x4") for anything else."""
    out = []
    for item in text.split(","):
        try:
            a, b = (int(v) for v in item.strip().lower().split("x"))
        except ValueError:
            raise MeniscopeError(option, f"expected {form}, got {item!r}") from None
        if a < 1 or b < 1:
            raise MeniscopeError(option, f"both numbers must be at least 1, got {item!r}")
        out.append((a, b))
    return out
