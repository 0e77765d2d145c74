"""`meniscope serve` against hostile or unlucky clients, files and disks (issue 18): each defect as found, fixed.

One demo service serves the request-only checks; the checks that change the service or its data run
their own.
"""

from __future__ import annotations

import asyncio
import logging
import re
import signal
import socket
import sqlite3
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from prometheus_client import generate_latest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from service.analysis.results import WindowResult
from service.pipeline.runtime import FittedWindow
from service.recordings import open_writer
from service.server.engine import Engine
from service.server.guard import default_hosts, host_name
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import Metrics, status_registry
from service.server.publishers import Publishers
from service.server.zmq_publisher import ZmqPublisher
from tests.servicekit import MENISCOPE, checkout_env, free_port, request, running_service, service_settings, wait_for
from tests.test_serve_cli import _answers, serve

TOKEN = {"Authorization": "Bearer s3cret"}


def demo(demo_cine: Path, speed: float = 0.25) -> str:
    return f"file://{demo_cine}?speed={speed}&loop=1"


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory, demo_cine: Path) -> Iterator[str]:
    """A running demo service with a token, ready."""
    settings = service_settings(tmp_path_factory.mktemp("hardening"), demo_cine.parent, demo(demo_cine), token="s3cret")
    with running_service(settings) as url:
        wait_for(lambda: request("GET", url + "/readyz").status == 200, 60, "readiness")
        yield url


@pytest.mark.parametrize(
    "path",
    [
        "/api/v1/windows?since=9223372036854775808",
        "/api/v1/windows/9223372036854775808",
        "/api/v1/windows?limit=10000",
        "/api/v1/windows/-1",
    ],
)
def test_out_of_range_numbers_are_422_with_the_schemas_list(base: str, path: str) -> None:
    reply = request("GET", base + path)
    assert reply.status == 422 and isinstance(reply.json()["detail"], list)


@pytest.mark.parametrize(
    "source", ["gopher://printer/1", "", "x" * 100_000, "missing.cine", "zmq+tcp://127.0.0.1:5555?colour=blue"]
)
def test_a_source_that_cannot_open_is_refused_and_the_running_one_kept(base: str, source: str) -> None:
    before = request("GET", base + "/api/v1/config").json()["source"]
    reply = request("PUT", base + "/api/v1/config", {"source": source}, TOKEN)
    assert reply.status in (413, 422), reply.body[:200]
    if reply.status == 422:
        assert isinstance(reply.json()["detail"], list) and reply.json()["detail"][0]["loc"][:2] == ["body", "source"]
    assert request("GET", base + "/api/v1/config").json()["source"] == before
    assert request("GET", base + "/readyz").status == 200


def test_a_foreign_host_header_is_refused(base: str) -> None:
    """DNS rebinding: a page of evil.example reaching 127.0.0.1 under its own name."""
    reply = request("PUT", base + "/api/v1/config", {"method": "network"}, {**TOKEN, "Host": "evil.example"})
    assert reply.status == 400 and "allowed_hosts" in reply.json()["detail"]
    assert request("GET", base + "/healthz", headers={"Host": "localhost:1234"}).status == 200


def test_the_token_is_needed_whenever_one_is_set(base: str) -> None:
    assert request("PUT", base + "/api/v1/config", {"method": "network"}).status == 401


def test_a_websocket_from_another_origin_is_refused_and_the_services_own_accepted(base: str) -> None:
    ws_url = base.replace("http", "ws") + "/ws"
    with pytest.raises(InvalidStatus) as refused:
        connect(ws_url, origin="http://evil.example")  # type: ignore[arg-type]
    assert refused.value.response.status_code == 403
    with connect(ws_url, origin=base) as ws:  # type: ignore[arg-type]
        assert ws.recv(timeout=10)


def test_docs_load_nothing_from_another_site(base: str) -> None:
    page = request("GET", base + "/docs").body.decode()
    urls = re.findall(r"""(?:src|href)=['"]([^'"]+)""", page) + re.findall(r"""url:\s*['"]([^'"]+)""", page)
    assert urls and all(u.startswith("/") for u in urls), urls
    for url in urls:
        assert request("GET", base + url).status == 200, url


def test_errors_are_documented(base: str) -> None:
    paths = request("GET", base + "/openapi.json").json()["paths"]
    assert {"401", "403", "422"} <= set(paths["/api/v1/config"]["put"]["responses"])
    assert "404" in paths["/api/v1/windows/{window_id}"]["get"]["responses"]
    assert "503" in paths["/readyz"]["get"]["responses"]


class FailingWrites:
    """The history's writer, refusing every write while ``failing`` (a read-only data folder, a full disk)."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self.conn, self.failing = conn, threading.Event()

    def execute(self, sql: str, *args: Any) -> sqlite3.Cursor:
        if self.failing.is_set() and not sql.lstrip().upper().startswith("SELECT"):
            raise sqlite3.OperationalError("attempt to write a readonly database")
        return self.conn.execute(sql, *args)

    def close(self) -> None:
        self.conn.close()


def test_windows_sent_while_the_history_fails_are_counted_and_stored_when_it_returns(
    tmp_path: Path, demo_cine: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The engine the pipeline process runs, in this process, so that its history writer can be made to fail."""
    engine = Engine(
        service_settings(tmp_path / "data", demo_cine.parent, demo(demo_cine)), Hub(asyncio.new_event_loop(), 1)
    )

    def text() -> str:
        return generate_latest(
            status_registry(lambda: engine.stats, engine.health, lambda: (0, 0), engine.history_health)
        ).decode()

    try:
        engine.start()
        wait_for(lambda: engine.health().ready, 60, "readiness")
        writes = engine.history._writer = FailingWrites(engine.history._writer)
        writes.failing.set()
        history = wait_for(
            lambda: (h := engine.history_health()).backlog >= 5 and h, 30, "windows waiting for the history"
        )
        health = engine.health()
        assert health.state == "degraded" and not health.ready and "readonly" in health.reason
        assert history.failures >= 5 and history.error
        assert "meniscope_history_up 0.0" in text() and "meniscope_ready 0.0" in text()
        writes.failing.clear()
        wait_for(lambda: engine.health().ready, 30, "readiness once the history takes writes")
        history = engine.history_health()
        ids = [w.id for w in engine.history.since(0, 100_000)]
    finally:
        engine.stop()
    assert history.lost == 0
    assert ids == list(range(ids[0], ids[0] + len(ids))) and len(ids) >= 5  # every window sent is stored, no gap
    logged = [r for r in caplog.records if r.name == "service.server.publishers"]
    assert len(logged) == 2, [r.getMessage() for r in logged]  # once when it failed, once when it came back


def test_a_dark_camera_is_no_signal_not_a_healthy_meniscus(tmp_path: Path) -> None:
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    with open_writer(recordings / "dark.cine", 96, 96, 19000.0, bit_depth=8) as writer:
        writer.write(np.zeros((2000, 96, 96), np.uint8))
    with running_service(service_settings(tmp_path / "data", recordings, demo(recordings / "dark.cine"))) as url:
        reply = wait_for(
            lambda: (r := request("GET", url + "/readyz")).json()["state"] == "no_signal" and r, 60, "no signal"
        )
        assert reply.status == 503 and "flat" in reply.json()["reason"]
        assert "meniscope_signal 0.0" in request("GET", url + "/metrics").body.decode()


def test_a_fit_that_comes_back_after_shutdown_is_counted_not_sent_on_a_closed_socket(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """What SIGTERM met: the fit workers finish the fit they are on after the pipeline stopped; its result came
    back after ZeroMQ had closed (`publishing failed ... ZMQError: Socket operation on non-socket`)."""
    loop = asyncio.new_event_loop()
    try:
        history = History(tmp_path / "history.sqlite", 1.0, 100)
        publishers = Publishers(history, Metrics(), ZmqPublisher("tcp://127.0.0.1:*"), Hub(loop, 1)).start()
        publishers.stop()
        result = WindowResult(index=0, start_frame=0, end_frame=10, status="failed", reason="late")
        publishers.on_window(FittedWindow(result, "demo", np.zeros(10), 19000.0, *[0.0] * 5))
        history.close()
    finally:
        loop.close()
    assert publishers.dropped == 1
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text


def test_sigterm_stops_in_order_without_an_error(tmp_path: Path) -> None:
    """The pipeline stops, the publishers drain, then ZeroMQ closes: no `publishing failed ... Socket operation on
    non-socket` from a fit that came back after the socket closed."""
    port = free_port()
    proc = serve(tmp_path, "--port", str(port))
    try:
        wait_for(lambda: _answers(proc, f"http://127.0.0.1:{port}/api/v1/windows?limit=1"), 120, "a window")
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    # uvicorn shuts down gracefully, then re-raises the signal: the status says SIGTERM ended it
    assert proc.returncode in (0, -signal.SIGTERM) and "Traceback" not in err and "failed" not in err, err[-2000:]


def test_a_zeromq_sender_that_dies_makes_the_service_unready_until_frames_flow_again(
    tmp_path: Path, demo_cine: Path
) -> None:
    """A sender killed with SIGKILL sends no end message: only the silence tells that it is dead (the service
    stayed ready for as long as anyone watched)."""
    port = free_port()
    sender_command = [
        *MENISCOPE,
        "publish-frames",
        str(demo_cine),
        "--bind",
        f"tcp://127.0.0.1:{port}",
        "--speed",
        "0.25",
        "--loop",
    ]
    sender = subprocess.Popen(sender_command, env=checkout_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with running_service(service_settings(tmp_path / "data", tmp_path, f"zmq+tcp://127.0.0.1:{port}")) as url:
            wait_for(lambda: request("GET", url + "/readyz").status == 200, 60, "readiness on the sender's frames")
            sender.kill()
            reply = wait_for(lambda: (r := request("GET", url + "/readyz")).status == 503 and r, 10, "not ready")
            assert reply.json()["state"] == "stalled" and str(port) in reply.json()["reason"]
            sender.wait()
            sender = subprocess.Popen(
                sender_command, env=checkout_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
            )
            wait_for(lambda: request("GET", url + "/readyz").status == 200, 60, "readiness once frames flow again")
    finally:
        sender.kill()
        sender.wait()


@pytest.mark.parametrize(
    "bind, host, allowed",
    [
        ("127.0.0.1", "127.0.0.1:8000", True),
        ("127.0.0.1", "localhost", True),
        ("127.0.0.1", "[::1]:8000", True),
        ("127.0.0.1", "evil.example", False),
        ("127.0.0.1", "127.0.0.1.evil.example:8000", False),
        ("192.168.3.7", "192.168.3.7:8000", True),
        ("192.168.3.7", "evil.example", False),
        ("0.0.0.0", "printer-7.factory.lan:8000", True),
    ],
)
def test_the_hosts_a_service_answers_to_follow_its_bind_address(bind: str, host: str, allowed: bool) -> None:
    hosts = default_hosts(bind)
    assert ("*" in hosts or host_name(host) in hosts) == allowed


def test_a_body_over_64_kb_is_refused_before_it_is_read_whole(base: str) -> None:
    """1 MB and 50 MB sources used to be taken in and kept. Refused on the declared length before the body is
    read (raw sockets: a client still sending meets the closed connection), and a chunked body (no length
    given) is read only up to the limit."""
    host, port = base.removeprefix("http://").split(":")
    head = (
        f"PUT /api/v1/config HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer s3cret\r\n"
        "Content-Type: application/json\r\n"
    )
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(f"{head}Content-Length: 1000000\r\n\r\n".encode())
        assert s.recv(100).startswith(b"HTTP/1.1 413")
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(f"{head}Transfer-Encoding: chunked\r\n\r\n".encode())
        chunk = b'{"source": "' + b"x" * 66_000 + b'"}'  # just over the limit
        s.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n0\r\n\r\n")
        assert s.recv(100).startswith(b"HTTP/1.1 413")


def test_a_lit_camera_without_a_highlight_is_its_own_state(tmp_path: Path) -> None:
    """Frames that carry a picture (grey with noise: not flat) but no highlight (the brightest pixel ~4 % of full
    scale above the mean): the meniscus is not seen, so the service is not ready (the window-level rule is
    test_pipeline.py's)."""
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    grey = 90 + np.random.default_rng(3).normal(0, 2, (2000, 96, 96))
    with open_writer(recordings / "unlit.cine", 96, 96, 19000.0, bit_depth=8) as writer:
        writer.write(np.clip(grey, 0, 255).astype(np.uint8))
    with running_service(service_settings(tmp_path / "data", recordings, demo(recordings / "unlit.cine"))) as url:
        reply = wait_for(
            lambda: (r := request("GET", url + "/readyz")).json()["state"] == "no_highlight" and r, 60, "no highlight"
        )
        assert reply.status == 503 and "no highlight" in reply.json()["reason"]
        assert "meniscope_signal 0.0" in request("GET", url + "/metrics").body.decode()
