"""The container and docker-compose.yml: what can be checked without a Docker engine. The compose file
passes `docker compose config` (or docker-compose's); the Dockerfile's structure keeps its promises
(two stages, no torch, non-root, health check, default models, the serve command); the build context
holds what the Dockerfile copies."""

from __future__ import annotations

import fnmatch
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
COMPOSE = ROOT / "docker-compose.yml"


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(
        r"\\\n", " ", "\n".join(l for l in DOCKERFILE.read_text().splitlines() if not l.lstrip().startswith("#"))
    )
    return [(line.split(None, 1)[0].upper(), line.split(None, 1)[1]) for line in text.splitlines() if line.strip()]


def _stages() -> list[list[tuple[str, str]]]:
    stages: list[list[tuple[str, str]]] = []
    for op, args in _instructions():
        if op == "FROM":
            stages.append([])
        if stages:
            stages[-1].append((op, args))
    return stages


def _compose_command() -> list[str]:
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True, timeout=30).returncode == 0:
        return [docker, "compose"]
    if shutil.which("docker-compose"):
        return [shutil.which("docker-compose")]
    pytest.skip("neither `docker compose` nor docker-compose is installed (Debian package docker-compose)")


def test_compose_config_accepts_the_file_and_passes_the_source_through() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MENISCOPE_")} | {"MENISCOPE_SOURCE": "v4l2://0"}
    result = subprocess.run(
        [*_compose_command(), "-f", str(COMPOSE), "config"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stderr
    config = yaml.safe_load(result.stdout)
    assert set(config["services"]) == {"meniscope", "prometheus", "grafana"}
    meniscope = config["services"]["meniscope"]
    assert meniscope["build"]["dockerfile"] == "deploy/Dockerfile"
    assert meniscope["environment"]["MENISCOPE_SOURCE"] == "v4l2://0"
    assert {int(p["target"]) if isinstance(p, dict) else int(p.split(":")[-1]) for p in meniscope["ports"]} == {
        8000,
        5556,
    }


def test_compose_mounts_what_prometheus_reads() -> None:
    prometheus = yaml.safe_load(COMPOSE.read_text())["services"]["prometheus"]
    mounts = dict(v.split(":")[:2][::-1] for v in prometheus["volumes"])
    config_file = next(a.split("=", 1)[1] for a in prometheus["command"] if a.startswith("--config.file="))
    host_dir = ROOT / mounts["/etc/prometheus"]
    assert (host_dir / Path(config_file).relative_to("/etc/prometheus")).is_file()
    scrape = yaml.safe_load((host_dir / "prometheus.yml").read_text())["scrape_configs"]
    assert any("meniscope:8000" in c["static_configs"][0]["targets"] for c in scrape)


def test_the_image_builds_in_two_stages_and_runs_without_root() -> None:
    build, runtime = _stages()[0], _stages()[-1]
    assert len(_stages()) >= 2
    installs = " ".join(a for op, a in build if op == "RUN")
    assert (
        "pip install" in installs and "[train" not in installs and "torch" not in installs.replace("import torch", "")
    )
    users = [a for op, a in runtime if op == "USER"]
    assert users and users[-1].split(":")[0] not in {"root", "0"}
    assert not any(op == "RUN" and "pip install" in a for op, a in runtime), "the runtime stage installs nothing"


def test_the_image_compiles_the_window_fit_as_the_user_that_runs_it() -> None:
    """numba's cache is written at build time, by the runtime's user into its NUMBA_CACHE_DIR, so that the
    container's fit workers load the compiled fit instead of compiling it at the first window."""
    runtime = _stages()[-1]
    user = max(i for i, (op, _) in enumerate(runtime) if op == "USER")
    warms = [i for i, (op, a) in enumerate(runtime) if op == "RUN" and "warm()" in a]
    assert warms and warms[-1] > user
    assert "NUMBA_CACHE_DIR=" in " ".join(a for op, a in runtime if op == "ENV")


def test_the_image_checks_health_bakes_models_and_serves() -> None:
    runtime = _stages()[-1]
    [health] = [a for op, a in runtime if op == "HEALTHCHECK"]
    assert "127.0.0.1" in health and "/healthz" in health and "8000" in health
    assert any(op == "COPY" and a.split()[0] == "models" for op, a in runtime)
    entry = next(a for op, a in reversed(runtime) if op == "ENTRYPOINT")
    cmd = next(a for op, a in reversed(runtime) if op == "CMD")
    assert re.findall(r'"([^"]*)"', entry) + re.findall(r'"([^"]*)"', cmd) == [
        "meniscope",
        "serve",
        "--host",
        "0.0.0.0",
    ]
    env = " ".join(a for op, a in runtime if op == "ENV")
    assert "MENISCOPE_DATA_DIR=" in env and "MENISCOPE_SOURCE" not in env, "unset, the service picks its own default"


def test_the_build_context_holds_what_the_dockerfile_copies() -> None:
    """Every COPY source exists and .dockerignore (an allow-list) lets it in."""
    rules = [
        l.strip() for l in (ROOT / ".dockerignore").read_text().splitlines() if l.strip() and not l.startswith("#")
    ]

    def included(path: str) -> bool:
        keep = True
        for rule in rules:
            pattern = rule.lstrip("!").rstrip("/")
            if fnmatch.fnmatch(path, pattern) or path.startswith(pattern + "/"):
                keep = rule.startswith("!")
        return keep

    for op, args in _instructions():
        if op == "COPY" and "--from" not in args:
            for source in args.split()[:-1]:
                assert (ROOT / source).exists(), source
                assert included(source), f"{source} is excluded by .dockerignore"
    assert not included("tests") and not included(".git")


def test_the_runtime_install_has_no_torch() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    # onnx (the graph reader, not torch's exporter) is a runtime dependency: the network's input pooling is cut out
    # of its graph at load (service.inverse.pooling)
    assert not [d for d in project["dependencies"] if re.match(r"torch\b", d)]
    assert any(d.startswith("torch") for d in project["optional-dependencies"]["train"])


def test_the_images_settings_bind_zeromq_where_compose_publishes_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The image's environment loaded as the service loads it: ZeroMQ on all interfaces like HTTP (bound to
    127.0.0.1 inside the container, compose's published 5556 reached nothing), on a port compose publishes."""
    from urllib.parse import urlsplit

    from service.server.settings import load_settings
    from service.server.zmq_publisher import ZmqPublisher

    env = dict(re.findall(r"(MENISCOPE_\w+)=(\S+)", " ".join(a for op, a in _stages()[-1] if op == "ENV")))
    for name in [k for k in os.environ if k.startswith("MENISCOPE_")]:
        monkeypatch.delenv(name)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    settings = load_settings(None, host="0.0.0.0")
    zmq = urlsplit(settings.zmq_publish or "")
    assert zmq.hostname == settings.host == "0.0.0.0"
    published = yaml.safe_load(COMPOSE.read_text())["services"]["meniscope"]["ports"]
    assert f"{zmq.port}:{zmq.port}" in published
    publisher = ZmqPublisher(settings.zmq_publish.replace(f":{zmq.port}", ":*"))  # the bind itself, on a free port
    try:
        assert publisher.endpoint.startswith("tcp://0.0.0.0:")
    finally:
        publisher.close()
