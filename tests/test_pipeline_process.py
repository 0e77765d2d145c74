"""The frame path runs in a process of its own (service.server.pipeline_process): nothing the web side does, or
fails to do, stalls it, and when it dies the service says so and starts it again (issue 18)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest
from websockets.sync.client import connect

from service.bench.live import subscribe
from service.errors import MeniscopeError
from service.server.hub import Hub
from service.server.pipeline_process import PipelineProcess
from tests.servicekit import (
    free_port,
    request,
    running_service,
    service_settings,
    wait_for,
)
from tests.test_serve_cli import serve
from tests.test_serve_hardening import demo


def _window_ids(port: int, stop: threading.Event) -> list[tuple[float, int]]:
    """(arrival time, id) of each window the ZeroMQ publisher on ``port`` sends, in a thread, until ``stop``."""
    got: list[tuple[float, int]] = []
    threading.Thread(
        target=subscribe,
        args=(port, stop, lambda parts: got.append((time.monotonic(), json.loads(parts[1])["id"]))),
        daemon=True,
    ).start()
    return got


def test_a_stopped_web_process_does_not_stall_the_frame_path(tmp_path: Path, demo_cine: Path) -> None:
    """SIGSTOP the web process (what a flood of requests does to it, at the extreme) with a WebSocket client that
    reads nothing: windows go on being made, published on ZeroMQ and stored, as fast as before."""
    port = free_port()
    proc = serve(tmp_path, "--port", str(port), "--source", demo(demo_cine, speed=0.5))
    base, stop = f"http://127.0.0.1:{port}", threading.Event()
    try:
        wait_for(lambda: proc.poll() is None and _ready(base), 120, "readiness")
        status = request("GET", base + "/api/v1/status").json()
        assert status["pipeline_process"]["pid"] not in (None, proc.pid)
        ids = _window_ids(int(status["zmq_publish"].rsplit(":", 1)[1]), stop)
        with connect(f"ws://127.0.0.1:{port}/ws"):  # a client that never reads
            wait_for(lambda: len(ids) >= 2, 60, "windows on ZeroMQ")
            time.sleep(3.0)
            os.kill(proc.pid, signal.SIGSTOP)
            stopped_at = time.monotonic()
            time.sleep(3.0)
            os.kill(proc.pid, signal.SIGCONT)
            resumed_at = time.monotonic()
            wait_for(lambda: _ready(base), 30, "readiness after SIGCONT")
        before = [i for t, i in ids if stopped_at - 3.0 <= t < stopped_at]
        during = [i for t, i in ids if stopped_at <= t < resumed_at]
        stored = (
            {
                w["id"]
                for w in request("GET", base + f"/api/v1/windows?since={during[0] - 1}&limit=1000").json()["windows"]
            }
            if during
            else set()
        )
    finally:
        stop.set()
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert len(during) >= max(1, len(before) // 2), (before, during)  # in-process, SIGSTOP stopped them all
    assert during == list(range(during[0], during[0] + len(during)))  # none lost on the way
    assert set(during) <= stored, sorted(set(during) - stored)  # and every one of them stored
    assert "Traceback" not in err, err[-2000:]


def test_a_killed_pipeline_process_is_noticed_and_started_again(tmp_path: Path, demo_cine: Path) -> None:
    with running_service(service_settings(tmp_path / "data", demo_cine.parent, demo(demo_cine))) as url:
        wait_for(lambda: _ready(url), 60, "readiness")
        status = request("GET", url + "/api/v1/status").json()
        os.kill(status["pipeline_process"]["pid"], signal.SIGKILL)
        reply = wait_for(lambda: (r := request("GET", url + "/readyz")).status == 503 and r, 5, "not ready")
        assert reply.json()["state"] == "retrying" and "pipeline process ended" in reply.json()["reason"]
        assert "meniscope_ready 0.0" in request("GET", url + "/metrics").body.decode()
        wait_for(lambda: _ready(url), 60, "readiness once it runs again")
        again = request("GET", url + "/api/v1/status").json()
    assert again["pipeline_process"]["restarts"] == 1
    assert again["pipeline_process"]["pid"] != status["pipeline_process"]["pid"]
    assert again["zmq_publish"] == status["zmq_publish"]  # the printer's controller stays connected


def _ready(base: str) -> bool:
    try:
        return request("GET", base + "/readyz").status == 200
    except OSError:
        return False


def test_a_pipeline_process_that_cannot_start_is_one_clear_error(tmp_path: Path) -> None:
    """A ZeroMQ endpoint that cannot be bound stops the service at start, naming it, as before the split."""
    settings = service_settings(tmp_path / "data", tmp_path, None).model_copy(
        update={"zmq_publish": "tcp://256.1.1.1:5"}
    )
    loop = asyncio.new_event_loop()
    try:
        with pytest.raises(MeniscopeError, match="cannot bind the ZeroMQ publisher"):
            PipelineProcess(settings, Hub(loop, 1)).start()
    finally:
        loop.close()
