"""The README's first command on Debian's own Python: `bash deploy/install.sh`, then `meniscope` works.

Debian 12's /usr/bin/python3 is "externally managed" (PEP 668): pip refuses to install into it. The
script makes a virtual environment from it and links the command into a folder on the PATH. Run on a
copy of this checkout (the files git knows), with the link put in a folder of the test's own
(MENISCOPE_BIN), so that the machine's /usr/local/bin is left alone. The runtime install only: the
wheels come from pip's cache (tests/run.sh filled it a moment before), so it takes a minute or two; the fit's
kernels are not compiled again (MENISCOPE_NO_WARM: the test command's own install ran that step).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests import cv2_owners
from tests.test_one_opencv import SERVICE_OPENCV

ROOT = Path(__file__).resolve().parents[1]
DEBIAN_PYTHON = Path("/usr/bin/python3")
INSTALL_TIMEOUT_S = 900

pytestmark = pytest.mark.slow


def checkout_copy(to: Path) -> Path:
    """The files git knows of this checkout (tracked, and untracked not ignored), copied to ``to``."""
    listed = (
        subprocess.run(
            ["git", "-C", str(ROOT), "ls-files", "-co", "--exclude-standard", "-z"], capture_output=True, check=True
        )
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():  # tracked files deleted in the work tree are skipped
            (to / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, to / name)
    return to


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A runtime install made by deploy/install.sh from Debian's Python: checkout, venv and command."""
    if not DEBIAN_PYTHON.is_file():
        pytest.skip(f"{DEBIAN_PYTHON} is absent: not a Debian machine")
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("the checkout is not a git work tree: its files cannot be listed")
    base = tmp_path_factory.mktemp("install")
    checkout = checkout_copy(base / "checkout")
    bin_dir, home = base / "bin", base / "home"
    home.mkdir()
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME") and not k.startswith("MENISCOPE_")
    }
    env.update(
        PYTHON=str(DEBIAN_PYTHON),
        MENISCOPE_BIN=str(bin_dir),
        HOME=str(home),
        PIP_CACHE_DIR=os.environ.get("PIP_CACHE_DIR", str(Path.home() / ".cache" / "pip")),
        MENISCOPE_NO_WARM="1",  # tests/run.sh's install compiled the fit's kernels; nothing here fits a window
    )
    done = subprocess.run(
        ["bash", "deploy/install.sh"], cwd=checkout, env=env, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return {
        "checkout": checkout,
        "venv": checkout / ".venv",
        "command": bin_dir / "meniscope",
        "stdout": done.stdout,
        "stderr": done.stderr,
    }


def run(command: Path, *args: str | Path) -> subprocess.CompletedProcess:
    """The installed command, as a shell would run it, with no checkout on PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(command), *map(str, args)], capture_output=True, text=True, timeout=300, env=env)


def test_the_environment_is_made_from_debians_python(installed: dict[str, Path]) -> None:
    stdlib = subprocess.run(
        [str(DEBIAN_PYTHON), "-c", "import sysconfig; print(sysconfig.get_path('stdlib'))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    if not (Path(stdlib) / "EXTERNALLY-MANAGED").is_file():
        pytest.skip(f"{DEBIAN_PYTHON} is not externally managed (PEP 668) here: the case this test is for")
    config = (installed["venv"] / "pyvenv.cfg").read_text()
    assert f"home = {DEBIAN_PYTHON.parent}" in config
    assert f"the command is {installed['command']}" in installed["stdout"]
    assert f"{installed['command'].parent} is not on your PATH" in installed["stderr"]  # and it says so


def test_the_linked_command_runs_the_installed_package(installed: dict[str, Path]) -> None:
    command = installed["command"]
    assert command.is_symlink() and command.resolve() == (installed["venv"] / "bin" / "meniscope").resolve()
    demo = installed["checkout"] / "service" / "demo" / "demo.avi"
    done = run(command, "info", demo)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["frames"] > 0


def test_the_installed_environment_holds_one_opencv(installed: dict[str, Path]) -> None:
    done = subprocess.run(
        [str(installed["venv"] / "bin" / "python"), cv2_owners.__file__], capture_output=True, text=True, check=True
    )
    assert json.loads(done.stdout) == [SERVICE_OPENCV]


def test_training_verbs_say_how_to_add_the_training_extra(installed: dict[str, Path], tmp_path: Path) -> None:
    done = run(installed["command"], "train", "--lab-video", tmp_path / "lab.cine", "--out", tmp_path / "models")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "'.[train]'" in done.stderr and "Traceback" not in done.stderr
