"""The content digest a report names its recording by: XXH3-128 (the ``xxhash`` package, the reference C code).

A recording is hashed while its frames are analysed, on the same two cores, where offline analysis at twice the
camera's rate has ~50 us of CPU per frame in all. The digest tells recordings apart (a copy in an archive, a file
changed since its report was written); it is not a seal against a file forged to match, which a plant analysing its
own camera's recordings has no use for. XXH3-128 costs 0.6 us of CPU per 18 KiB frame here, BLAKE3 4.0 and SHA-256
15.6 (the digests of earlier reports; docs/benchmarks.md). ``xxhsum -H2 REC.cine`` checks it.
"""

from __future__ import annotations

import mmap
from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import MeniscopeError

if TYPE_CHECKING:
    import numpy as np


def xxh3_file(path: Path, mapped: np.ndarray | None = None) -> str:
    """Hex XXH3-128 of a file, hashed from a memory map of it: no copy of its bytes into a buffer first (reading them
    cost the hashing thread as much CPU as the hash itself: docs/benchmarks.md). ``mapped``: the file's bytes as a
    reader of it already maps them (:attr:`service.recordings.base.Recording.mapped`), hashed there instead of
    mapping the file again, whose pages would each be mapped afresh. The hash lets go of the interpreter lock: it runs
    beside the analysis' threads."""
    from xxhash import xxh3_128

    if mapped is not None:
        return xxh3_128(mapped).hexdigest()
    try:
        with open(path, "rb") as file:
            if Path(path).stat().st_size == 0:  # an empty file cannot be mapped
                return xxh3_128(b"").hexdigest()
            with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as whole:
                return xxh3_128(whole).hexdigest()
    except OSError as exc:
        raise MeniscopeError(path, f"cannot read: {exc.strerror or exc}") from None
