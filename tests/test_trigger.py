"""The printer's trigger live: events over HTTP and ZeroMQ, windows cut at them, the video detector checking them."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zmq

from service.pipeline.ejections import EjectionDetector
from service.pipeline.runtime import segmenter_for
from service.pipeline.segmenter import StreamingSegmenter
from service.pipeline.trigger import TriggerCheck, TriggerInbox
from service.server.settings import ServiceSettings
from service.server.trigger_zmq import TriggerSubscriber
from tests.servicekit import request, running_service, service_settings, wait_for
from tests.test_live_segmentation import FPS, bursts, segment

TOKEN = {"Authorization": "Bearer s3cret"}


def triggered(printer: list[int], video: list[int], n: int = 1200) -> tuple[list, TriggerInbox]:
    """Windows of a stream whose video shows ejections at ``video`` while the printer announces ``printer``."""
    inbox = TriggerInbox()
    for frame in printer:
        inbox.add(frame=frame)
    seg = StreamingSegmenter(10_000, EjectionDetector(FPS), trigger=TriggerCheck(inbox, FPS, wait_frames=38))
    closed = segment(seg, np.arange(n), np.zeros(n), bursts(video, n, np.random.default_rng(0)), 50)
    return closed + seg.finish(0.0), inbox


def test_windows_are_cut_at_the_printers_ejections_and_agreement_is_counted() -> None:
    closed, inbox = triggered([200, 401, 600, 800], [200, 400, 600, 801])  # within 2 frames: agreement
    assert [c.window.start for c in closed] == [0, 200, 401, 600, 800]
    assert (inbox.counts.received, inbox.counts.agreed, inbox.counts.printer_only, inbox.counts.video_only) == (
        4,
        4,
        0,
        0,
    )


def test_a_trigger_the_video_does_not_show_and_an_ejection_the_printer_did_not_announce_are_disagreements() -> None:
    closed, inbox = triggered([200, 400, 600, 1000], [200, 400, 605, 800])
    assert [c.window.start for c in closed] == [0, 200, 400, 600, 1000]  # the printer's, not the video's
    assert (inbox.counts.agreed, inbox.counts.printer_only, inbox.counts.video_only) == (2, 2, 2)


def test_late_events_within_the_wait_still_cut_and_times_become_frames() -> None:
    inbox = TriggerInbox()
    seg = StreamingSegmenter(10_000, EjectionDetector(FPS), trigger=TriggerCheck(inbox, FPS, wait_frames=38))
    change = bursts([300], 600, np.random.default_rng(1))
    closed = segment(seg, np.arange(320), np.zeros(600), change, 20)  # the frames arrive before the event
    inbox.add(time_s=300 / FPS)
    closed += segment(seg, np.arange(320, 600), np.zeros(600)[320:], change[320:], 20)
    assert [c.window.end for c in closed] == [300]  # cut at the printer's time, whatever the video's detector holds
    seg.finish(0.0)
    assert inbox.counts.agreed == 1


@pytest.mark.parametrize("event", [{}, {"frame": 1, "time_s": 0.1}, {"frame": -1}, {"time_s": float("nan")}])
def test_an_event_with_neither_or_both_or_a_bad_number_is_refused(event: dict) -> None:
    with pytest.raises(ValueError):
        TriggerInbox().add(**event)


def test_zeromq_events_reach_the_inbox_and_a_bad_message_is_skipped() -> None:
    pub = zmq.Context.instance().socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    inbox = TriggerInbox()
    subscriber = TriggerSubscriber(f"tcp://127.0.0.1:{port}", inbox)
    try:
        deadline = time.monotonic() + 10
        while inbox.counts.received == 0 and time.monotonic() < deadline:  # a SUB joins a PUB after a moment
            pub.send_multipart([b"ejection", b"not json"])
            pub.send_multipart([b"ejection", json.dumps({"frame": 7}).encode()])
            time.sleep(0.05)
        pub.send_string(json.dumps({"time_s": 0.01}))
        wait_for(lambda: 190 in inbox.take(FPS), 10, "the time_s event")
    finally:
        subscriber.close()
        pub.close()


def test_the_live_segmenter_takes_the_printers_events_only_when_asked() -> None:
    inbox = TriggerInbox()
    assert segmenter_for(ServiceSettings(trigger="printer"), FPS, inbox).trigger.inbox is inbox
    assert segmenter_for(ServiceSettings(), FPS, inbox).trigger is None


@pytest.fixture(scope="module")
def printer() -> Iterator[tuple[zmq.Socket, str]]:
    """The printer's ZeroMQ PUB socket and its endpoint."""
    pub = zmq.Context.instance().socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    yield pub, f"tcp://127.0.0.1:{port}"
    pub.close()


@pytest.fixture(scope="module")
def printer_service(
    tmp_path_factory: pytest.TempPathFactory, demo_cine: Path, printer: tuple[zmq.Socket, str]
) -> Iterator[str]:
    settings = service_settings(
        tmp_path_factory.mktemp("trigger"),
        demo_cine.parent,
        f"file://{demo_cine}?speed=0.25&loop=1",
        token="s3cret",
        trigger="printer",
        trigger_zmq=printer[1],
    )
    with running_service(settings) as url:  # the trigger's route answers whether or not the pipeline is ready yet
        yield url


def received(url: str) -> float:
    """meniscope_trigger_ejections_total as the service's /metrics says (the pipeline process's count)."""
    metrics = request("GET", url + "/metrics").body.decode()
    assert 'meniscope_trigger_disagreements_total{side="printer_only"}' in metrics
    return next(float(line.split()[-1]) for line in metrics.splitlines() if line.startswith("meniscope_trigger_ej"))


def test_the_http_trigger_needs_the_token_and_reaches_the_pipeline_process(printer_service: str) -> None:
    url = printer_service + "/api/v1/ejections"
    assert request("POST", url, {"frame": 10}).status == 401
    assert request("POST", url, {"frame": 10, "time_s": 0.1}, TOKEN).status == 422
    assert request("POST", url, {"frame": -3}, TOKEN).status == 422
    before = received(printer_service)
    reply = request("POST", url, {"frame": 10}, TOKEN)
    assert reply.status == 202 and reply.json() == {"received": 1}
    # counted where the segmenter runs, the pipeline process, and reported back to the web process's /metrics
    wait_for(lambda: received(printer_service) == before + 1, 10, "the HTTP event in the pipeline process")


def test_zeromq_trigger_events_reach_the_running_services_pipeline_process(
    printer_service: str, printer: tuple[zmq.Socket, str]
) -> None:
    pub, _ = printer

    def sent_and_counted() -> bool:  # a SUB joins a PUB after a moment: send until one arrives
        before = received(printer_service)
        pub.send_string(json.dumps({"frame": 20}))
        time.sleep(0.3)
        return received(printer_service) > before

    wait_for(sent_and_counted, 30, "a ZeroMQ event in the pipeline process")
