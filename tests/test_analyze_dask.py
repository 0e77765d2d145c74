"""Window-level work on a Dask cluster: ``meniscope analyze --scheduler`` writes the REPORT the local process pool
writes, its fits run on the cluster's workers, and a scheduler that cannot be reached is one clear line."""

from __future__ import annotations

import json
import socket
import sys
from pathlib import Path

import pytest

from service.cli import main
from service.pipeline import windows

distributed = pytest.importorskip("distributed", reason="Dask distributed is not installed: pip install '.[scale]'")


@pytest.fixture(scope="module")
def cluster() -> distributed.LocalCluster:
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
    ) as local:
        yield local


def analyze(recording: Path, out: Path, *options: str) -> dict:
    assert main(["analyze", str(recording), "--out", str(out), "--quiet", *options]) == 0
    return json.loads(out.read_text())


def test_the_report_from_a_dask_cluster_is_the_local_one(
    demo_cine: Path, cluster: distributed.LocalCluster, tmp_path: Path
) -> None:
    local = analyze(demo_cine, tmp_path / "local.json", "--workers", "2")
    remote = analyze(demo_cine, tmp_path / "dask.json", "--scheduler", cluster.scheduler_address)
    assert remote == local and len(local["windows"]) >= 3
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        fitted_there = client.run(lambda: "service.analysis.fit" in sys.modules)
    assert any(fitted_there.values()), f"no fit ran on the cluster: {fitted_there}"


def test_an_unreachable_scheduler_is_one_line(
    demo_cine: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    monkeypatch.setattr(windows, "CONNECT_TIMEOUT_S", 1.0)
    assert main(["analyze", str(demo_cine), "--out", str(tmp_path / "r.json"), "--quiet", "--scheduler", address]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot reach the Dask scheduler" in err
    assert not (tmp_path / "r.json").exists()
