"""The report's recording digest: BLAKE3 of the file's bytes, whatever their size, and a one-line error naming
a file it cannot read."""

from __future__ import annotations

from pathlib import Path

import pytest
from blake3 import blake3
from hypothesis import given, settings
from hypothesis import strategies as st

from service.errors import MeniscopeError
from service.recordings.digest import blake3_file


@settings(max_examples=25, deadline=None)
@given(
    size=st.sampled_from([0, 1, 1023, 1024, 1025, 4095, 4096, 4097, 65536 * 3 + 7, (1 << 20) + 1]),
    seed=st.integers(0, 2**32 - 1),
)
def test_digest_is_blake3_of_the_bytes(tmp_path_factory: pytest.TempPathFactory, size: int, seed: int) -> None:
    """Empty, one byte, either side of BLAKE3's 1 KiB chunk and of a page, and over a MiB: the reference digest."""
    import numpy as np

    data = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    path = tmp_path_factory.mktemp("digest") / "rec.cine"
    path.write_bytes(data)
    assert blake3_file(path) == blake3(data).hexdigest()
    mapped = np.memmap(path, np.uint8, mode="r") if size else np.empty(0, np.uint8)  # as a reader maps it
    assert blake3_file(path, mapped) == blake3(data).hexdigest()


@pytest.mark.parametrize("name", ["missing.cine", "."])
def test_unreadable_file_is_named(tmp_path: Path, name: str) -> None:
    """A missing file or a folder: a MeniscopeError naming the path."""
    path = tmp_path / name
    with pytest.raises(MeniscopeError, match="cannot read") as caught:
        blake3_file(path)
    assert str(path) in str(caught.value)
