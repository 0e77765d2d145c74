"""`meniscope serve` over HTTP: readiness that tells why, recovery, guarded configuration, slow clients."""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import threading
from contextlib import closing
from pathlib import Path

from websockets.sync.client import ClientConnection, connect

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.sources import FrameSender, open_source
from tests.servicekit import request, running_service, service_settings, wait_for


def demo(demo_cine: Path, speed: float = 0.25) -> str:
    return f"file://{demo_cine}?speed={speed}&loop=1"


def ready(base: str) -> bool:
    return request("GET", base + "/readyz").status == 200


def test_a_missing_model_is_reported_and_the_service_recovers_once_it_is_there(tmp_path: Path, demo_cine: Path) -> None:
    models = tmp_path / "models"
    settings = service_settings(tmp_path / "data", demo_cine.parent, demo(demo_cine), models=models)
    with running_service(settings) as base:
        assert request("GET", base + "/healthz").json() == {"status": "ok"}
        reply = wait_for(
            lambda: (r := request("GET", base + "/readyz")).json()["state"] == "retrying" and r, 10, "a retry"
        )
        assert reply.status == 503 and "not a model folder" in reply.json()["reason"]
        assert "/api/v1/windows" in request("GET", base + "/openapi.json").json()["paths"]
        shutil.copytree(DEFAULT_MODELS, models)
        wait_for(lambda: ready(base), 20, "readiness after the model appeared")


def test_an_unreadable_source_is_a_clear_reason_not_a_crash(tmp_path: Path, demo_cine: Path) -> None:
    (tmp_path / "recordings").mkdir()
    (tmp_path / "recordings" / "broken.cine").write_bytes(b"not a cine file at all" * 100)
    settings = service_settings(tmp_path / "data", tmp_path / "recordings", "broken.cine")
    with running_service(settings) as base:
        status = wait_for(
            lambda: (s := request("GET", base + "/api/v1/status").json())["state"] == "retrying" and s, 10, "a retry"
        )
        assert "broken.cine" in status["reason"] and not status["ready"]
        assert request("GET", base + "/api/v1/windows").json() == {"windows": [], "last_id": None}


def test_a_simulated_camera_renders_the_service_scene_and_its_windows_are_published(tmp_path: Path) -> None:
    scene = tmp_path / "nozzle.json"  # the embedded scene under another name: the shipped models fit it
    shutil.copy(DEFAULT_SCENE, scene)
    settings = service_settings(tmp_path / "data", tmp_path, "sim://?seed=4", scene=scene)
    with running_service(settings) as base:
        status = wait_for(
            lambda: (s := request("GET", base + "/api/v1/status").json())["state"] == "running" and s,
            60,
            "the simulated camera running",
        )
        assert status["source"]["kind"] == "simulated" and status["source"]["scene"] == str(scene)
        stored = wait_for(lambda: request("GET", base + "/api/v1/windows").json()["windows"], 60, "a window")
        assert stored[0]["source"] == "sim://?seed=4" and stored[0]["fps"] == 19000.0


def test_configuration_changes_need_the_token_and_stay_in_the_recordings_folder(
    tmp_path: Path, demo_cine: Path
) -> None:
    settings = service_settings(tmp_path / "data", demo_cine.parent, demo(demo_cine), token="s3cret")
    with running_service(settings) as base:
        url = base + "/api/v1/config"
        assert request("GET", url).json()["token_set"] is True
        assert request("PUT", url, {"method": "direct"}).status == 401
        assert request("PUT", url, {"method": "direct"}, {"Authorization": "Bearer wrong"}).status == 401
        auth = {"Authorization": "Bearer s3cret"}
        for bad in ({"source": "../../etc/passwd"}, {"method": "fastest"}, {"port": 1}):
            assert request("PUT", url, bad, auth).status == 422, bad
        reply = request("PUT", url, {"method": "direct"}, auth)
        assert reply.status == 200 and reply.json()["method"] == "direct"
        assert request("GET", base + "/api/v1/status").json()["model"]["method"] == "direct"
        wait_for(lambda: ready(base), 20, "the pipeline to restart with the new method")


def test_without_a_token_only_a_loopback_service_can_be_reconfigured(tmp_path: Path, demo_cine: Path) -> None:
    settings = service_settings(tmp_path / "data", demo_cine.parent, demo(demo_cine), host="0.0.0.0")
    with running_service(settings) as base:
        reply = request("PUT", base + "/api/v1/config", {"method": "direct"})
        assert reply.status == 403 and "MENISCOPE_TOKEN" in reply.json()["detail"]


def test_a_websocket_client_that_stops_reading_slows_neither_the_pipeline_nor_other_clients(
    tmp_path: Path, demo_cine: Path
) -> None:
    # large, frequent trace messages fill a stalled client's small socket buffers within a second or two
    settings = service_settings(
        tmp_path / "data",
        demo_cine.parent,
        demo(demo_cine),
        trace_hz=100.0,
        trace_frames=8192,
        client_queue=4,
        read_frames=16,
    )
    with running_service(settings) as base:
        wait_for(lambda: ready(base), 20, "readiness")
        ws_url = base.replace("http", "ws") + "/ws"
        with closing(stalled_websocket(base)), connect(ws_url) as reader:
            # the reader reads on while the stalled client's buffers fill, until it loses messages
            wait_for(
                lambda: skipped_while_reading(base, reader),
                60,
                "the stalled client's buffers to fill, so that it loses messages",
            )
            before, lost = request("GET", base + "/api/v1/status").json(), websocket(base)
            # frames read from now on reach the reader only if neither the pipeline nor the reader waits on it
            wait_for(
                lambda: covers(next_message(reader), before["source"]["position"]),
                60,
                "the reading client to get a trace of frames read after the stalled client fell behind",
            )
            after, still = request("GET", base + "/api/v1/status").json(), websocket(base)
        assert still["clients"] == 2 and still["skipped"] > lost["skipped"]  # connected and stalled throughout
        assert after["windows"]["unpublished"] == before["windows"]["unpublished"] == 0  # publishing kept up


def stalled_websocket(base: str) -> socket.socket:
    """A WebSocket client that completes the handshake on a tiny receive buffer and then reads nothing."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    host, port = base.removeprefix("http://").split(":")
    sock.connect((host, int(port)))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


def next_message(ws: ClientConnection) -> dict | None:
    """The next message on ``ws``, or None when none came within a second (the caller waits on)."""
    try:
        return json.loads(ws.recv(timeout=1))
    except TimeoutError:
        return None


def skipped_while_reading(base: str, reader: ClientConnection) -> bool:
    """Whether any message was skipped yet, once ``reader`` took its next one (if any) so that it never lags."""
    next_message(reader)
    return websocket(base)["skipped"] > 0


def covers(message: dict | None, index: int) -> bool:
    """Whether ``message`` is a trace whose frames reach past frame ``index``."""
    return (
        message is not None and message["type"] == "trace" and message["first_index"] + len(message["values"]) > index
    )


def websocket(base: str) -> dict[str, float]:
    """The WebSocket metrics /metrics shows: connected ``clients`` and messages ``skipped`` for lagging ones."""
    metrics = dict(
        line.split()
        for line in request("GET", base + "/metrics").body.decode().splitlines()
        if line.startswith(("meniscope_websocket_clients ", "meniscope_websocket_messages_skipped_total "))
    )
    return {
        "clients": float(metrics["meniscope_websocket_clients"]),
        "skipped": float(metrics["meniscope_websocket_messages_skipped_total"]),
    }


class Camera:
    """A stand-in network camera: the demo recording sent as ZeroMQ frames while ``on``."""

    def __init__(self, recording: Path, endpoint: str = "tcp://127.0.0.1:*") -> None:
        self.source = open_source(str(recording), speed=0.25, loop=True)
        self.sender = FrameSender(endpoint, self.source.format)
        self.endpoint = self.sender.endpoint
        self.on = True
        self.thread = threading.Thread(target=self._send, daemon=True)
        self.thread.start()

    def _send(self) -> None:
        while self.on:
            self.sender.send(self.source.read(64))

    def unplug(self) -> None:
        self.on = False
        self.thread.join()
        self.sender.close()
        self.source.close()


def test_a_camera_that_disappears_is_reported_and_followed_again_when_it_returns(
    tmp_path: Path, demo_cine: Path
) -> None:
    camera = Camera(demo_cine)
    uri = camera.endpoint.replace("tcp://", "zmq+tcp://") + "?open_timeout=1"
    with running_service(service_settings(tmp_path / "data", tmp_path, uri)) as base:
        wait_for(lambda: ready(base), 20, "readiness on the camera's frames")
        camera.unplug()
        reply = wait_for(lambda: (r := request("GET", base + "/readyz")).status == 503 and r, 10, "not ready")
        assert camera.endpoint.split(":")[-1] in reply.json()["reason"]
        camera = Camera(demo_cine, camera.endpoint)  # plugged in again, same address
        try:
            wait_for(lambda: ready(base), 20, "readiness after the camera came back")
        finally:
            camera.unplug()
