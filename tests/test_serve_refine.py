"""`meniscope serve --refine` end to end: the real service on the demo recording, each refined window published as an
update of the same window id on WebSocket, ZeroMQ, REST and Prometheus, and equal to that window in `meniscope analyze
--refine`'s report of the same recording (the same function refines both)."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest
import zmq
from websockets.sync.client import connect

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.offline import analyse_recording
from service.analysis.results import FitSettings
from service.scene import Scene
from service.server.messages import REFINED_TOPIC, WINDOW_TOPIC
from tests.servicekit import request, running_service, service_settings, wait_for
from tests.test_serve_end_to_end import PERIOD, complete

WANTED = 1  # refined updates each client must receive (tens of seconds of CPU each)
#: A refinement costs ~40 s of CPU on the demo, and analyze --refine of its 4 windows ~170 s (docs/benchmarks.md).
pytestmark = pytest.mark.timeout(2400)


@pytest.fixture(scope="module")
def session(demo_cine: Path, offline: dict[int, dict], tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """The service with ``refine`` on the demo (a twentieth of the camera's rate: no frame dropped on a busy machine,
    so that the windows are whole), a WebSocket client and a ZeroMQ subscriber to both topics, collecting until each
    has ``WANTED`` refined updates. The lane at the test's own niceness, not the lowest: on a CI machine shared with
    other jobs nice 19 may get no CPU at all. Started once ``offline`` is done: its lane refines without a pause while
    it runs, and would take a core from the offline analysis."""
    settings = service_settings(
        tmp_path_factory.mktemp("service"),
        demo_cine.parent,
        f"file://{demo_cine}?speed=0.05&loop=1",
        refine=True,
        refine_nice=0,
    )
    with running_service(settings) as base:
        endpoint = request("GET", base + "/api/v1/status").json()["zmq_publish"]
        sub = zmq.Context.instance().socket(zmq.SUB)
        for topic in (WINDOW_TOPIC, REFINED_TOPIC):
            sub.setsockopt(zmq.SUBSCRIBE, topic)
        sub.connect(endpoint)
        got: dict[str, list] = {"ws": [], "zmq": []}

        def updates(channel: str) -> int:
            return sum(m["type"] == "window_update" for _, m in got[channel])

        def listen_ws() -> None:
            with connect(base.replace("http", "ws") + "/ws", open_timeout=10) as ws:
                while updates("ws") < WANTED:
                    message = json.loads(ws.recv(timeout=600))
                    if message["type"] != "trace":
                        got["ws"].append((None, message))

        def listen_zmq() -> None:
            while updates("zmq") < WANTED and sub.poll(600_000):
                topic, body = sub.recv_multipart()
                got["zmq"].append((topic, json.loads(body)))

        listeners = [threading.Thread(target=f, daemon=True) for f in (listen_ws, listen_zmq)]
        for t in listeners:
            t.start()
        for t in listeners:
            t.join(1800)
        sub.close()
        yield base, got


@pytest.fixture(scope="module")
def offline(demo_cine: Path) -> dict[int, dict]:
    """``analyze --refine``'s windows of the demo (its CLI's fit settings, the service's: the default method's window,
    which a rejected refinement reports, takes its poles from the frames), by start frame."""
    analysis = analyse_recording(
        demo_cine,
        Scene.load(DEFAULT_SCENE),
        "network",
        DEFAULT_MODELS,
        settings=FitSettings(),
        progress=False,
        refine=True,
    )
    assert analysis.report.method == "network+synthesis"
    return {w.start_frame: w.model_dump(mode="json") for w in analysis.report.windows}


def test_refined_updates_carry_the_id_of_the_window_published_first(session) -> None:  # type: ignore[no-untyped-def]
    _, got = session
    for channel in ("ws", "zmq"):
        first = {m["id"]: m for _, m in got[channel] if m["type"] == "window"}
        refined = [(topic, m) for topic, m in got[channel] if m["type"] == "window_update"]
        assert len(refined) >= WANTED, channel
        for topic, m in refined:
            assert topic in (None, REFINED_TOPIC)
            assert m["method"] == "network+synthesis" and m["revision"] == 1 and m["refined"] is True
            assert m["refine_latency_s"] > 0
            if m["id"] in first:  # published first on this channel (a client may connect after it)
                before = first[m["id"]]
                assert before["revision"] == 0 and before["refined"] is False and before["method"] == "network"
                assert before["window"]["start_frame"] == m["window"]["start_frame"]
        assert all(topic in (None, WINDOW_TOPIC) for topic, m in got[channel] if m["type"] == "window")


def test_rest_and_metrics_show_the_refined_window(session) -> None:  # type: ignore[no-untyped-def]
    base, got = session
    m = next(m for _, m in got["zmq"] if m["type"] == "window_update")
    stored = wait_for(
        lambda: (r := request("GET", f"{base}/api/v1/windows/{m['id']}").json())["revision"] == 1 and r,
        30,
        "the refined window stored",
    )
    assert stored["window"] == m["window"] and stored["method"] == "network+synthesis" and stored["refined"]
    page = request("GET", f"{base}/api/v1/windows?since={m['id'] - 1}&limit=1").json()
    assert page["windows"][0]["refined"] and page["windows"][0]["window"] == m["window"]

    def scraped() -> dict[str, float]:
        text = request("GET", base + "/metrics").body.decode()
        return {line.split(" ")[0]: float(line.split(" ")[1]) for line in text.splitlines() if line and line[0] != "#"}

    # the metrics reach the web process on their own path: a scrape may come before the last refinement's count
    values = wait_for(
        lambda: (v := scraped()).get("meniscope_windows_refined_total", 0) >= WANTED and v, 30, "the refined count"
    )
    assert values["meniscope_refine_latency_seconds_count"] == values["meniscope_windows_refined_total"]
    assert values['meniscope_windows_refine_skipped_total{reason="replaced"}'] > 0  # thousands of times slower


def test_a_window_refined_live_equals_the_same_window_in_analyze_refine(session, offline) -> None:  # type: ignore[no-untyped-def]
    _, got = session
    live = [m["window"] for _, m in got["ws"] + got["zmq"] if m["type"] == "window_update" and complete(m["window"])]
    assert live, "no refined window between two of the file's ejections came"
    for window in live:
        expected = offline[window["start_frame"] % PERIOD]
        placed = {"index", "start_frame", "end_frame"}  # the stream's, not the file's
        if expected["end_frame"] == PERIOD:  # the file's last window: the looped stream's next ejection ends it live
            placed.add("ends_at_ejection")
        assert {k: v for k, v in window.items() if k not in placed} == {
            k: v for k, v in expected.items() if k not in placed
        }
