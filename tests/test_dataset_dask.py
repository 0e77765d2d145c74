"""Scale-out: a dataset rendered on a Dask cluster (two worker processes) is byte for byte the one this
process renders alone for the same seed, and a scheduler that cannot be reached is one clear line."""

from __future__ import annotations

import argparse
import socket
import sys
from pathlib import Path

import pytest

from service.errors import MeniscopeError
from service.scene import Scene
from training import engine
from training.dataset import FILES, DatasetConfig, generate, open_dataset
from training.verbs import register

distributed = pytest.importorskip("distributed", reason="Dask distributed is not installed: pip install '.[scale]'")


@pytest.fixture(scope="module")
def config(scene: Scene) -> DatasetConfig:
    """Three chunks of 16 x 16 renders, the last one short."""
    data = scene.model_dump()
    data["camera"].update(width_px=16, height_px=16, fov_deg=scene.camera.fov_deg * 16 / scene.camera.width_px)
    return DatasetConfig(scene=Scene.from_dict(data), samples=40, seed=3, chunk_size=16, supersample=1)


@pytest.fixture(scope="module")
def cluster() -> distributed.LocalCluster:
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
    ) as local:
        yield local


def test_a_two_worker_cluster_writes_the_same_files_as_one_process(
    config: DatasetConfig, cluster: distributed.LocalCluster, tmp_path: Path
) -> None:
    generate(config, tmp_path / "alone", workers=1)
    manifest = generate(config, tmp_path / "dask", scheduler=cluster.scheduler_address)
    for name in FILES:
        assert (tmp_path / "alone" / name).read_bytes() == (tmp_path / "dask" / name).read_bytes(), name
    assert manifest["chunks"] == 3 and len(open_dataset(tmp_path / "dask", verify=True)) == 40
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        ran_there = client.run(lambda: "training.dataset" in sys.modules)
    assert len(ran_there) == 2 and all(ran_there.values()), f"chunks did not run on both workers: {ran_there}"


def test_an_unreachable_scheduler_is_one_line_and_leaves_no_folder(
    config: DatasetConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(MeniscopeError, match="cannot reach the Dask scheduler"):
        generate(config, tmp_path / "set", scheduler=address)
    assert not (tmp_path / "set").exists()


def test_the_dataset_verb_takes_a_scheduler(
    config: DatasetConfig, cluster: distributed.LocalCluster, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="verb"))
    scene_file = tmp_path / "scene.json"
    scene_file.write_text(config.scene.to_json())
    args = parser.parse_args(
        [
            "dataset",
            "--scene",
            str(scene_file),
            "--out",
            str(tmp_path / "set"),
            "--samples",
            "5",
            "--scheduler",
            cluster.scheduler_address,
        ]
    )
    assert args.func(args) == 0
    assert "5 frames uint8 16x16" in capsys.readouterr().out
