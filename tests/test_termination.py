"""SIGTERM (``kill``, a service manager's stop) ends a long verb the way Ctrl-C does: its scratch folders are removed,
its worker processes end with it, one line says so, and the exit status is 128 + SIGTERM. A training killed without
this left 25 GB in /tmp and its workers rendering on."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from service import cli
from tests.servicekit import MENISCOPE, checkout_env, meniscope, wait_for


def test_a_sigterm_that_lands_where_python_swallows_exceptions_is_delivered_again() -> None:
    """Python ignores an exception raised in a ``__del__`` or an at-fork callback (a pool forking met one): the verb
    must still stop, once that code has returned."""

    class SignalledWhileCollected:
        def __del__(self) -> None:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler runs here, where its exception is swallowed

    with pytest.raises(cli.Terminated), cli._terminable(True):
        SignalledWhileCollected()
        for _ in range(200):
            time.sleep(0.01)


def test_a_terminated_training_leaves_no_scratch_folder_behind(tmp_path: Path) -> None:
    pytest.importorskip("torch", reason="training needs the train extra (torch)")
    lab, scratch, models = tmp_path / "lab.cine", tmp_path / "scratch", tmp_path / "models"
    scratch.mkdir()
    done = meniscope("simulate", "--out", lab, "--windows", "3", "--seed", "1")
    assert done.returncode == 0, done.stderr
    err_path = tmp_path / "stderr.txt"
    with err_path.open("w") as err_file:  # a file, not a pipe: a killed verb's orphaned workers would hold a pipe open
        proc = subprocess.Popen(
            [*MENISCOPE, "train", "--lab-video", str(lab), "--out", str(models), "--quick"],
            stdout=subprocess.DEVNULL,
            stderr=err_file,
            env={**checkout_env(), "TMPDIR": str(scratch)},
        )
        try:
            wait_for(lambda: any(scratch.glob("meniscope-*")), 120, "the training's scratch folder")
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=120)
        finally:
            proc.kill()
    err = err_path.read_text()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "meniscope train: terminated" in err and "Traceback" not in err, err[-2000:]
    assert not list(scratch.glob("meniscope-*"))
    assert not _processes_reading(lab), "workers of the training outlived it"


def _processes_reading(path: Path) -> list[int]:
    """PIDs of the processes whose command line names ``path`` (Linux: /proc)."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if str(path).encode() in cmdline.read_bytes():
                pids.append(int(cmdline.parent.name))
        except OSError:  # gone meanwhile
            pass
    return pids
