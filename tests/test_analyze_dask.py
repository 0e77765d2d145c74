"""Window-level work on a Dask cluster: ``meniscope analyze --scheduler`` writes the REPORT the local process pool
writes, its fits run on the cluster's workers, and a scheduler that cannot be reached is one clear line."""

from __future__ import annotations

import json
import socket
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service import DEFAULT_SCENE, blas
from service.analysis.offline import refine_task
from service.analysis.results import FitSettings
from service.camera_effects import CameraEffects
from service.cli import main
from service.physics import WindowMotion
from service.pipeline import windows
from service.render.renderer import Renderer
from service.scene import Scene

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


def test_a_window_refined_on_a_dask_worker_is_the_bits_the_local_pool_gives(
    cluster: distributed.LocalCluster,
) -> None:
    """``analyze --refine`` sends each window's refinement to the runner's processes, whose threads differ (a local
    pool of one process renders on every core and its BLAS has a thread per core; a Dask worker thread has one of
    each): the refined coefficients, motion and the pixel fit's covariance, which the REPORT is made of, are the same bits
    from both (a short window seen by a half-size camera: seconds)."""
    default = Scene.load(DEFAULT_SCENE)
    camera = default.camera.model_copy(update={"width_px": 48, "height_px": 48, "fov_deg": default.camera.fov_deg / 2})
    scene = default.model_copy(update={"camera": camera})
    t = np.arange(30) / camera.fps
    truth = WindowMotion(
        d=0.01, p=-0.08, A1=0.018, g1=400.0, f1=1400.0, phi1=1.0, A2=0.007, g2=900.0, f2=3200.0, phi2=4.0
    )
    frames = CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0).apply(
        Renderer(scene).render(truth.coefficients(t).to_array()), np.random.default_rng(0)
    )
    start = replace(truth, A1=0.012, g1=600.0)
    found = []
    for runner in (
        windows.JobRunner(FitSettings(), workers=1),
        windows.JobRunner(FitSettings(), cluster.scheduler_address),
    ):
        with runner:
            coefficients, motion, covariance, clusters = runner.call(
                refine_task, scene, frames, t, start, runner.threads
            ).result()
        found.append((coefficients.tobytes(), motion, covariance.tobytes(), clusters))
    assert found[0] == found[1]


def test_a_task_s_threads_are_its_share_of_the_cores() -> None:
    """A local pool's processes share the machine's cores between them (one each at the default of one process per
    core, never none); a Dask worker thread is one core, the cluster's workers being how it grows."""
    cores = blas.usable_cores()
    for workers, threads in ((1, cores), (cores, 1), (2 * cores, 1)):
        with windows.JobRunner(FitSettings(), workers=workers) as runner:
            assert runner.threads == threads
