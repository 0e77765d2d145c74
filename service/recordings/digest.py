"""The content digest a report names its recording by: BLAKE3 (the ``blake3`` package, the reference Rust code).

A recording is hashed while its frames are analysed, on the same two cores: SHA-256 cost 15.6 us of CPU per
18 KiB frame here (SHA-NI), a third of the 52 us per frame that offline analysis at twice the camera's rate has on
two cores; BLAKE3 costs less than a third of that and is as strong a fingerprint. ``b3sum REC.cine`` checks it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import MeniscopeError

if TYPE_CHECKING:
    import numpy as np


def blake3_file(path: Path, mapped: np.ndarray | None = None) -> str:
    """Hex BLAKE3 of a file, hashed from a memory map of it: no copy of its bytes into a buffer first (reading them
    cost the hashing thread as much CPU as the hash itself: docs/benchmarks.md). ``mapped``: the file's bytes as a
    reader of it already maps them (:attr:`service.recordings.base.Recording.mapped`), hashed there instead of
    mapping the file again, whose pages would each be mapped afresh. The hash lets go of the interpreter lock: it runs
    beside the analysis' threads."""
    from blake3 import blake3

    digest = blake3(max_threads=1)  # one thread: the other core is busy reading and inferring
    if mapped is not None:
        digest.update(mapped)
        return digest.hexdigest()
    try:
        digest.update_mmap(Path(path))
    except OSError as exc:
        raise MeniscopeError(path, f"cannot read: {exc.strerror or exc}") from None
    return digest.hexdigest()
