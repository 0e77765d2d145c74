"""The content digest a report names its recording by: BLAKE3 (the ``blake3`` package, the reference Rust code).

A recording is hashed while its frames are analysed, on the same two cores: SHA-256 cost 15.6 us of CPU per
18 KiB frame here (SHA-NI), a third of the 52 us per frame that offline analysis at twice the camera's rate has on
two cores; BLAKE3 costs 5.9 and is as strong a fingerprint. ``b3sum REC.cine`` checks it.
"""

from __future__ import annotations

from pathlib import Path

from service.errors import MeniscopeError

#: Bytes per read: large enough that per-call overheads vanish, small enough to stay in the core's cache between the
#: read and the hash (4 MiB reads cost the hashing thread a sixth more CPU: docs/benchmarks.md).
BLOCK = 1 << 18


def blake3_file(path: Path) -> str:
    """Hex BLAKE3 of a file, read in :data:`BLOCK`-byte blocks into one buffer (the hash lets go of the interpreter
    lock: it runs beside the analysis' threads)."""
    from blake3 import blake3

    digest = blake3(max_threads=1)  # one thread: the other core is busy reading and inferring
    buffer = bytearray(BLOCK)
    view = memoryview(buffer)
    try:
        with Path(path).open("rb") as f:
            while size := f.readinto(buffer):
                digest.update(view[:size])
    except OSError as exc:
        raise MeniscopeError(path, f"cannot read: {exc.strerror or exc}") from None
    return digest.hexdigest()
