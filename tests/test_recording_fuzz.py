"""A seeded mutation fuzzer over .cine and .avi headers and truncations: 40,000 damaged files, each either
refused with one :class:`MeniscopeError` line or read with exactly the frame count and size of the file
it was made from (every frame decoded, ``info`` strict JSON). No other exception, no wrong count or size.

Mutations: bit flips and whole fields set to boundary values (0, 1, 2**31 - 1, 2**32 - 1, -1, 1e9, the
neighbours of the true value, absurd doubles) at the header's bytes and the stream's chunk headers;
truncations anywhere; truncations followed by garbage. Hypothesis drives the smaller property tests of
test_cine_fuzz.py; a plain seeded loop is used here because 40,000 cases through Hypothesis would cost
minutes of CPU time.
"""

from __future__ import annotations

import json
import struct
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service.errors import MeniscopeError
from service.recordings import open_recording, open_writer

#: Mutated files per format: together the issue's 40,000.
CASES = {".cine": 30_000, ".avi": 10_000}
INTS = np.array([0, 1, 2, 3, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 2**31 - 1, 2**31, 2**32 - 1, 10**9], np.uint64)
DOUBLES = [0.0, -1.0, 5e-324, 1e-9, 1e308, float("inf"), float("nan"), 1e12]


@pytest.fixture
def scratch(tmp_path: Path) -> Iterator[Path]:
    """A folder in memory where the system has one (a file rewritten on disk 40,000 times costs minutes of I/O)."""
    shm = Path("/dev/shm")
    if not shm.is_dir():
        yield tmp_path
        return
    with tempfile.TemporaryDirectory(dir=shm, prefix="meniscope-fuzz-") as folder:
        yield Path(folder)


def valid_file(folder: Path, suffix: str) -> bytes:
    """A small valid recording: 5 frames of 16 x 12 px (12-bit words with time stamps in .cine, FFV1 in .avi)."""
    path = folder / f"valid{suffix}"
    depth = 12 if suffix == ".cine" else 8
    frames = np.random.default_rng(0).integers(0, 2**depth, (5, 12, 16))
    with open_writer(path, 16, 12, 19000.0, bit_depth=depth, trigger_frame=1 if suffix == ".cine" else 0) as w:
        w.write(frames)
    return path.read_bytes()


def header_positions(data: bytes, suffix: str) -> np.ndarray:
    """Byte positions worth mutating: everything before the first image (.cine) or the first video chunk
    (.avi), and each chunk header of the AVI's stream and index."""
    if suffix == ".cine":
        first_image = struct.unpack_from("<Q", data, struct.unpack_from("<I", data, 32)[0])[0]
        return np.arange(first_image + 8)  # the first image's annotation too
    movi = data.index(b"movi") + 4
    chunks = [
        i for i in range(movi, len(data) - 8) if data[i : i + 2] == b"00" and data[i + 2 : i + 4] in (b"dc", b"db")
    ]
    chunks += [data.index(b"idx1")]
    return np.concatenate([np.arange(movi + 8)] + [np.arange(c, c + 8) for c in chunks])


def mutate(rng: np.random.Generator, data: bytes, positions: np.ndarray) -> bytes:
    """One damaged copy of ``data``."""
    kind = rng.integers(6)
    out = bytearray(data)
    if kind == 0:  # a few bit flips in the headers
        for p in rng.choice(positions, rng.integers(1, 5)):
            out[p] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # an aligned 32-bit field set to a boundary value
        p = int(rng.choice(positions)) & ~3
        struct.pack_into("<I", out, min(p, len(out) - 4), int(rng.choice(INTS)))
    elif kind == 2:  # a 32-bit field nudged by one either way
        p = min(int(rng.choice(positions)) & ~1, len(out) - 4)
        value = struct.unpack_from("<I", out, p)[0]
        struct.pack_into("<I", out, p, (value + int(rng.choice([-1, 1]))) % 2**32)
    elif kind == 3:  # a double set to an absurd value (.cine's frame rate, exposure, ...)
        p = min(int(rng.choice(positions)) & ~3, len(out) - 8)
        struct.pack_into("<d", out, p, DOUBLES[int(rng.integers(len(DOUBLES)))])
    elif kind == 4:  # truncated
        return bytes(out[: int(rng.integers(len(out)))])
    else:  # truncated, then garbage
        cut = int(rng.integers(len(out)))
        return bytes(out[:cut]) + rng.bytes(int(rng.integers(1, 64)))
    return bytes(out)


def outcome(path: Path, data: bytes, expected: tuple[int, int, int]) -> str:
    """'refused', 'read' (all frames, the right count and size) or 'WRONG ...'; anything else raises."""
    path.write_bytes(data)
    try:
        with open_recording(path) as rec:
            frames = rec.read(0, len(rec))
            json.dumps(rec.info(), allow_nan=False)
    except MeniscopeError as error:
        assert "\n" not in str(error)
        return "refused"
    got = frames.shape
    return "read" if got == expected and rec.timestamps.shape == (got[0],) else f"WRONG {got} for {expected}"


@pytest.mark.parametrize("suffix", sorted(CASES))
def test_damaged_headers_and_truncations(scratch: Path, suffix: str) -> None:
    data = valid_file(scratch, suffix)
    with open_recording(scratch / f"valid{suffix}") as rec:
        expected = (len(rec), rec.height, rec.width)
    positions = header_positions(data, suffix)
    rng = np.random.default_rng(18)
    tally: Counter[str] = Counter()
    wrong: list[str] = []
    for case in range(CASES[suffix]):
        mutated = mutate(rng, data, positions)
        result = outcome(scratch / f"case{suffix}", mutated, expected)
        tally[result.split()[0]] += 1
        if result.startswith("WRONG"):
            wrong.append(f"case {case}: {result}")
    assert not wrong, f"{len(wrong)} damaged files read with a wrong count or size, e.g. {wrong[:5]} ({tally})"
    assert tally["refused"] > CASES[suffix] // 4 and tally["read"] > 0  # the fuzzer reaches both sides
