"""Running the real service and CLI in tests: uvicorn on a free port in a thread, `meniscope` as a process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import uvicorn
from fastapi import FastAPI

from service.bench.live import free_port  # noqa: F401 - the tests' free port is the benchmark's
from service.server.app import create_app
from service.server.settings import ServiceSettings

#: The checkout these tests belong to, whose code every `meniscope` process they start must run.
ROOT = Path(__file__).resolve().parents[1]
#: `meniscope` as a command; -P keeps the working folder (where a stray `service` folder may lie) off the path.
MENISCOPE = [sys.executable, "-P", "-m", "service.cli"]
#: Seconds a `meniscope` command may take before it counts as hung (pytest's own limit is 600 per test).
CLI_TIMEOUT_S = 600


def checkout_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's) with :data:`ROOT` first on PYTHONPATH, so that a `meniscope`
    process runs the code under test, not an installed copy or another checkout's."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env


def meniscope(*args: str | Path) -> subprocess.CompletedProcess:
    """Run ``meniscope ARGS`` as its own process on this checkout's code; its output is captured as text."""
    return subprocess.run(
        [*MENISCOPE, *map(str, args)], capture_output=True, text=True, timeout=CLI_TIMEOUT_S, env=checkout_env()
    )


@contextmanager
def running_service(settings: ServiceSettings) -> Iterator[str]:
    """Serve ``settings`` on 127.0.0.1 (a free port); yields the base URL, e.g. ``http://127.0.0.1:41234``."""
    with running_app(create_app(settings)) as base:
        yield base


@contextmanager
def running_app(app: FastAPI) -> Iterator[str]:
    """Serve ``app`` (from :func:`create_app`: the test may reach into ``app.state.service``) as
    :func:`running_service` does."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", ws="websockets-sansio"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the service did not start")
        time.sleep(0.05)
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(20)


def wait_for(predicate, timeout: float, what: str, interval: float = 0.1):  # type: ignore[no-untyped-def]
    """Poll ``predicate()`` until it returns something truthy (returned), or fail saying ``what``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


@dataclass(frozen=True)
class Reply:
    status: int
    body: bytes
    headers: dict[str, str]

    def json(self) -> Any:
        return json.loads(self.body)


def request(method: str, url: str, body: Any = None, headers: dict[str, str] | None = None) -> Reply:
    """One HTTP request with the standard library; any status is returned, not raised."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json", **(headers or {})}
    )
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return Reply(resp.status, resp.read(), dict(resp.headers))
    except urllib.error.HTTPError as err:
        return Reply(err.code, err.read(), dict(err.headers))


def service_settings(data_dir: Path, recordings: Path, source: str | None, **overrides) -> ServiceSettings:  # type: ignore[no-untyped-def]
    """Settings for a test service: its own data folder, a ZeroMQ port the system picks."""
    return ServiceSettings(
        data_dir=data_dir, recordings_dir=recordings, source=source, zmq_publish="tcp://127.0.0.1:*", **overrides
    )
