"""Whatever bytes a .cine holds, opening it either works or raises MeniscopeError: no other exception, no hang.

When a damaged file opens, everything it claims must hold: every frame reads, ``info`` is strict JSON.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.errors import MeniscopeError
from service.recordings import open_recording, open_writer

_names = itertools.count()
#: cine_781.cine: the bytes before its first image (header, bitmap, SETUP, tagged blocks, image offsets).
REAL_HEADERS = 10_940
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def valid(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A small valid .cine: 16-bit words, 12 significant bits, time stamps, trigger at frame 1."""
    path = tmp_path_factory.mktemp("fuzz") / "valid.cine"
    frames = np.random.default_rng(0).integers(0, 4096, (4, 6, 8)).astype(np.uint16)
    with open_writer(path, 8, 6, 19000.0, bit_depth=12, trigger_frame=1) as writer:
        writer.write(frames)
    return path.read_bytes()


def open_and_use(folder: Path, data: bytes) -> bool:
    """Open ``data`` as a .cine and use all of it; True when it opened, False on MeniscopeError."""
    path = folder / f"fuzz{next(_names)}.cine"
    path.write_bytes(data)
    try:
        with open_recording(path) as rec:
            frames = rec.read(0, len(rec))
            assert frames.shape == (len(rec), rec.height, rec.width)
            assert rec.timestamps.shape == (len(rec),)
            json.dumps(rec.info(), allow_nan=False)
    except MeniscopeError as error:
        assert "\n" not in str(error)
        return False
    return True


def test_the_unbroken_file_opens(tmp_path: Path, valid: bytes) -> None:
    assert open_and_use(tmp_path, valid)


@FUZZ
@given(data=st.binary(max_size=4096), magic=st.booleans())
def test_random_bytes(tmp_path: Path, data: bytes, magic: bool) -> None:
    open_and_use(tmp_path, (b"CI" if magic else b"") + data)


@FUZZ
@given(cut=st.data())
def test_every_truncation_is_reported(tmp_path: Path, valid: bytes, cut: st.DataObject) -> None:
    length = cut.draw(st.integers(0, len(valid) - 1))
    assert not open_and_use(tmp_path, valid[:length])


@FUZZ
@given(flips=st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 7)), min_size=1, max_size=8))
def test_bit_flips(tmp_path: Path, valid: bytes, flips: list[tuple[int, int]]) -> None:
    data = bytearray(valid)
    for position, bit in flips:
        data[position % len(data)] ^= 1 << bit
    open_and_use(tmp_path, bytes(data))


@FUZZ
@given(flips=st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 7)), min_size=1, max_size=8))
def test_bit_flips_in_the_headers_of_a_real_file(
    tmp_path: Path, shared_dir: Path, flips: list[tuple[int, int]]
) -> None:
    path = shared_dir / "data" / "cine" / "cine_781.cine"
    if not path.is_file():
        pytest.skip(f"real Phantom file {path} is absent")
    data = bytearray(path.read_bytes())
    for position, bit in flips:
        data[position % REAL_HEADERS] ^= 1 << bit
    open_and_use(tmp_path, bytes(data))
