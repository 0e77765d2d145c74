"""The report's recording digest: XXH3-128 of the file's bytes, whatever their size, as ``xxhsum -H2`` prints it,
and a one-line error naming a file it cannot read."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from xxhash import xxh3_128

from service.errors import MeniscopeError
from service.recordings.digest import xxh3_file


@settings(max_examples=25, deadline=None)
@given(
    size=st.sampled_from(
        [0, 1, 16, 17, 128, 129, 240, 241, 1023, 1024, 4095, 4096, 4097, 65536 * 3 + 7, (1 << 20) + 1]
    ),
    seed=st.integers(0, 2**32 - 1),
)
def test_digest_is_xxh3_128_of_the_bytes(tmp_path_factory: pytest.TempPathFactory, size: int, seed: int) -> None:
    """Empty, one byte, either side of XXH3's short-input branches (16, 128, 240 bytes), of a stripe block and of a
    page, and over a MiB: the reference digest, from the file or from a reader's mapping of it."""
    import numpy as np

    data = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    path = tmp_path_factory.mktemp("digest") / "rec.cine"
    path.write_bytes(data)
    assert xxh3_file(path) == xxh3_128(data).hexdigest()
    mapped = np.memmap(path, np.uint8, mode="r") if size else np.empty(0, np.uint8)  # as a reader maps it
    assert xxh3_file(path, mapped) == xxh3_128(data).hexdigest()


@pytest.mark.skipif(shutil.which("xxhsum") is None, reason="xxhsum (Debian package xxhash) is not installed")
def test_xxhsum_checks_the_digest(demo_cine: Path) -> None:
    """What the report says a user checks with ``xxhsum -H2 REC.cine``."""
    printed = subprocess.run(["xxhsum", "-H2", str(demo_cine)], capture_output=True, text=True, check=True).stdout
    assert printed.split()[0] == xxh3_file(demo_cine)


@pytest.mark.parametrize("name", ["missing.cine", "."])
def test_unreadable_file_is_named(tmp_path: Path, name: str) -> None:
    """A missing file or a folder: a MeniscopeError naming the path."""
    path = tmp_path / name
    with pytest.raises(MeniscopeError, match="cannot read") as caught:
        xxh3_file(path)
    assert str(path) in str(caught.value)
