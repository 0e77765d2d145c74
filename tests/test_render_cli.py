"""``meniscope render`` and ``meniscope sheet`` as a user runs them: real files, the installed command."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from service.render import Renderer
from service.scene import Scene
from tests.servicekit import meniscope


def test_render_writes_the_renderers_frames_for_each_csv_row(tmp_path: Path, scene: Scene) -> None:
    coeffs = np.array([[0.01, 0.1, 0.02, -0.01], [0.0, 0.0, 0.0, 0.0], [-0.04, -0.2, 0.03, 0.015]])
    csv = tmp_path / "coeffs.csv"
    csv.write_text("b,a,p,d,note\n" + "".join(f"{b},{a},{p},{d},x\n" for d, p, a, b in coeffs))  # any column order
    out = tmp_path / "frames.npy"
    done = meniscope("render", "--coefficients", str(csv), "--out", str(out), "--supersample", "1")
    assert done.returncode == 0, done.stderr
    frames = np.load(out)
    assert frames.dtype == np.float32 and frames.shape == (3, scene.camera.height_px, scene.camera.width_px)
    np.testing.assert_array_equal(frames, Renderer(scene, supersample=1).render(coeffs))


@pytest.mark.parametrize(
    "content, problem",
    [
        ("d,p,a\n1,2,3\n", "missing b"),
        ("d,p,a,b\n0,0,zero,0\n", "line 2: column a is not a number"),
        ("d,p,a,b\n0,0,,0\n", "line 2: empty cell in column a"),
        ("d,p,a,b\n0,nan,0,0\n", "line 2: column p is not finite"),
        ("", "missing d, p, a, b"),
    ],
)
def test_a_bad_coefficients_file_is_a_one_line_error_naming_it(tmp_path: Path, content: str, problem: str) -> None:
    csv = tmp_path / "coeffs.csv"
    csv.write_text(content)
    out = tmp_path / "frames.npy"
    done = meniscope("render", "--coefficients", str(csv), "--out", str(out))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and str(csv) in done.stderr and problem in done.stderr
    assert not out.exists()


def test_a_missing_coefficients_file_or_output_folder_is_named(tmp_path: Path) -> None:
    done = meniscope("render", "--coefficients", str(tmp_path / "none.csv"), "--out", str(tmp_path / "f.npy"))
    assert done.returncode == 2 and "none.csv: no such file" in done.stderr
    (tmp_path / "c.csv").write_text("d,p,a,b\n0,0,0,0\n")
    done = meniscope("render", "--coefficients", str(tmp_path / "c.csv"), "--out", str(tmp_path / "no" / "f.npy"))
    assert done.returncode == 2 and "does not exist" in done.stderr


def test_sheet_writes_a_png_of_sweeps_and_profiles(tmp_path: Path) -> None:
    out = tmp_path / "sheet.png"
    done = meniscope("sheet", "--out", str(out), "--supersample", "1", "--sun-samples", "1")
    assert done.returncode == 0, done.stderr
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 800 and image.shape[1] > 600
