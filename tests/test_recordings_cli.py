"""``meniscope info`` and ``meniscope frames`` (shared/spec/cli.md): one JSON object; frames as stored, to .npy."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from service.recordings import open_writer
from service.verbs import recordings as verbs
from tests.servicekit import CLI_TIMEOUT_S, checkout_env

FRAMES = np.random.default_rng(3).integers(0, 4096, (12, 6, 10)).astype(np.uint16)


@pytest.fixture
def cine(tmp_path: Path) -> Path:
    path = tmp_path / "rec.cine"
    with open_writer(path, 10, 6, 19000.0, bit_depth=12, trigger_frame=4) as writer:
        writer.write(FRAMES)
    return path


def test_info_prints_one_json_object(cine: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info", str(cine)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {k: info[k] for k in ("frames", "fps", "width", "height", "bit_depth", "trigger_frame")} == dict(
        frames=12, fps=19000.0, width=10, height=6, bit_depth=12, trigger_frame=4
    )
    assert info["timestamps"]["source"] == "file" and info["timestamps"]["first_s"] == pytest.approx(-4 / 19000)


def test_info_on_a_real_file_says_what_the_camera_wrote(shared_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_dir / "data" / "cine" / "cine_781.cine"
    if not path.is_file():
        pytest.skip(f"real Phantom file {path} is absent")
    assert main(["info", str(path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["frames"], info["bit_depth"], info["acquisition_fps"], info["decimation"], info["fps"]) == (
        15,
        12,
        90000.0,
        10.0,
        9000.0,
    )
    assert info["camera_model"] == "Phantom v2012"


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ([], FRAMES),
        (["--start", "3", "--count", "5"], FRAMES[3:8]),
        (["--start", "11"], FRAMES[11:]),
        (["--start", "12"], FRAMES[12:]),
    ],
)
def test_frames_saves_the_stored_words(cine: Path, tmp_path: Path, extra: list[str], expected: np.ndarray) -> None:
    out = tmp_path / "frames.npy"
    assert main(["frames", str(cine), *extra, "--out", str(out)]) == 0
    saved = np.load(out)
    assert saved.dtype == np.uint16 and saved.shape == expected.shape
    np.testing.assert_array_equal(saved, expected)


def test_frames_are_copied_a_chunk_at_a_time(cine: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(verbs, "CHUNK_BYTES", 3 * FRAMES[0].nbytes)
    out = tmp_path / "frames.npy"
    assert main(["frames", str(cine), "--start", "1", "--out", str(out)]) == 0
    np.testing.assert_array_equal(np.load(out), FRAMES[1:])


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["info", "{missing}"], "no such file"),
        (["info", "{empty}"], "the file is empty"),
        (["info", "{text}"], "unsupported recording type '.txt'"),
        (["frames", "{cine}", "--start", "10", "--count", "3", "--out", "{out}"], "the recording has frames 0..11"),
        (["frames", "{cine}", "--count", "-1", "--out", "{out}"], "cannot read -1 frame"),
        (["frames", "{cine}", "--out", "{nowhere}"], "does not exist"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    cine: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], problem: str
) -> None:
    (tmp_path / "empty.cine").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("not video")
    names = dict(
        cine=cine,
        missing=tmp_path / "missing.cine",
        empty=tmp_path / "empty.cine",
        text=tmp_path / "notes.txt",
        out=tmp_path / "out.npy",
        nowhere=tmp_path / "no" / "out.npy",
    )
    assert main([a.format(**names) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert problem in err and "\n" not in err and err.startswith(f"meniscope {argv[0]}: error: ")
    assert not (tmp_path / "out.npy").exists()


def test_the_installed_command_runs(cine: Path) -> None:
    """The console script the install puts beside this Python (pyproject's [project.scripts]), not ``-m``."""
    script = shutil.which("meniscope", path=str(Path(sys.executable).parent))
    assert script, f"no meniscope script beside {sys.executable}: is the project installed (deploy/install.sh)?"
    done = subprocess.run(
        [script, "info", str(cine)], capture_output=True, text=True, timeout=CLI_TIMEOUT_S, env=checkout_env()
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["frames"] == 12
