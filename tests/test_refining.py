"""The refinement lane's parts (service/pipeline/refining.py): the newest-window slot, the frames kept for it, and
the history that takes its updates under the window's own id."""

from __future__ import annotations

import json
import multiprocessing
import os
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.analysis.results import WindowResult
from service.pipeline.refining import LANE_NICE, NewestSlot, RecentFrames, gather, idle_priority
from service.server.history import History
from service.sources import FrameBatch


@given(st.lists(st.one_of(st.integers(0, 10**6), st.none()), max_size=60))
def test_the_slot_hands_out_the_newest_item_and_every_other_is_skipped_once(steps: list[int | None]) -> None:
    """Offers (numbers) and takes (None) in any order: a take gets the newest item offered since the last take,
    every item offered is either taken or returned as replaced, exactly once."""
    slot: NewestSlot[int] = NewestSlot()
    taken, replaced, since_take = [], [], []
    for step in steps:
        if step is None:
            item = slot.take(timeout=0)
            assert item == (since_take[-1] if since_take else None)
            taken += [] if item is None else [item]
            since_take = []
        else:
            old = slot.offer(step)
            assert old == (since_take[-1] if since_take else None)
            replaced += [] if old is None else [old]
            since_take.append(step)
    left = slot.close()
    offered = [s for s in steps if s is not None]
    assert sorted(taken + replaced + ([] if left is None else [left])) == sorted(offered)
    assert slot.take(timeout=0) is None  # closed


def test_a_take_waits_for_an_offer_and_close_wakes_it() -> None:
    slot: NewestSlot[str] = NewestSlot()
    got: list[str | None] = []
    waiter = threading.Thread(target=lambda: got.append(slot.take()))
    waiter.start()
    slot.offer("w1")
    waiter.join(5)
    assert got == ["w1"]
    waiter = threading.Thread(target=lambda: got.append(slot.take()))
    waiter.start()
    slot.close()
    waiter.join(5)
    assert got == ["w1", None] and not waiter.is_alive()


def _reads(sizes: list[int], dtype: type = np.uint16) -> list[FrameBatch]:
    """Consecutive reads of the given sizes, each frame filled with its index."""
    out, first = [], 0
    for n in sizes:
        indices = np.arange(first, first + n)
        pixels = np.broadcast_to(indices[:, None, None], (n, 3, 2)).astype(dtype)
        out.append(FrameBatch(pixels, indices, indices / 1e3))
        first += n
    return out


@settings(max_examples=200)
@given(st.lists(st.integers(1, 64), min_size=1, max_size=40), st.integers(1, 300), st.data())
def test_recent_frames_keep_at_least_the_last_frames_asked_and_gather_any_span_of_them(
    sizes: list[int], keep: int, data: st.DataObject
) -> None:
    recent = RecentFrames(keep)
    for read in _reads(sizes):
        recent.add((read,))
    total = sum(sizes)
    first_kept = max(0, total - keep)
    start = data.draw(st.integers(first_kept, total - 1))
    end = data.draw(st.integers(start + 1, total))
    frames = gather(recent.covering(start, end), start, end)
    assert frames is not None and frames.dtype == np.uint16
    assert np.array_equal(frames[:, 0, 0], np.arange(start, end))
    kept = sum(len(r) for r in recent.covering(0, total))
    assert keep <= kept or kept == total  # never fewer than asked, ...
    assert kept - min(sizes) < keep + max(sizes)  # ... and no more than a read beyond it


def test_gather_says_none_where_a_frame_is_missing() -> None:
    a, _, c = _reads([10, 5, 10])  # the middle read dropped
    assert gather((a, c), 5, 20) is None
    assert gather((), 0, 3) is None
    assert np.array_equal(gather((a,), 2, 6)[:, 1, 1], [2, 3, 4, 5])  # type: ignore[index]


def _result(index: int, f: float) -> WindowResult:
    return WindowResult(
        index=index,
        start_frame=0,
        end_frame=100,
        status="settled",
        reason="test",
        samples=100,
        missing=0,
        starts_at_ejection=True,
        ends_at_ejection=True,
        offset_mm=f,
    )


def test_a_refined_window_replaces_its_row_under_the_same_id(tmp_path) -> None:  # type: ignore[no-untyped-def]
    history = History(tmp_path / "h.sqlite", 7, 1000)
    first = history.add(_result(0, 0.1), "demo", 19000.0, method="network")
    other = history.add(_result(1, 0.2), "demo", 19000.0, method="network")
    history.add(_result(0, 0.15), "demo", 19000.0, window_id=first, method="network+synthesis", revision=1,
                refine_latency_s=12.5)  # fmt: skip
    rows = {w.id: w for w in history.since(0)}
    assert list(rows) == [first, other]
    assert rows[first].revision == 1 and rows[first].method == "network+synthesis"
    assert rows[first].refine_latency_s == 12.5 and rows[first].result.offset_mm == 0.15
    assert rows[other].revision == 0 and rows[other].refine_latency_s is None
    page = json.loads(history.page_json(0, 10))
    assert page["windows"] == [rows[first].to_json(), rows[other].to_json()]
    history.close()


def test_an_older_history_gains_the_columns_and_keeps_its_windows(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as conn:
        conn.executescript(
            "CREATE TABLE windows (id INTEGER PRIMARY KEY AUTOINCREMENT, stored REAL NOT NULL, source TEXT NOT NULL,"
            " fps REAL NOT NULL, result TEXT NOT NULL);"
        )
        conn.execute(
            "INSERT INTO windows (stored, source, fps, result) VALUES (1e9, 'old', 19000, ?)",
            (_result(0, 0.1).model_dump_json(),),
        )
    conn.close()
    history = History(path, 1e6, 1000)
    (old,) = history.since(0)
    assert old.method is None and old.revision == 0 and old.to_json()["refined"] is False
    history.close()


def test_the_search_starts_on_every_demo_window(demo_cine) -> None:  # type: ignore[no-untyped-def]
    """``analyze --refine``'s start (one-mode fits of each coefficient's series) on each window of the demo: window 0's
    fit of one series was polished into an unresolved fit that gave no reason, which raised (analyze --refine of the
    demo failed); an unresolved fit says why."""
    from service import DEFAULT_MODELS, DEFAULT_SCENE
    from service.analysis.fit import fit_window
    from service.analysis.results import FitSettings
    from service.inverse import synthesis
    from service.inverse.network import NetworkMethod
    from service.pipeline.demo import DEMO_TRUTH
    from service.recordings import open_recording
    from service.recordings.roi import roi_frames
    from service.scene import Scene

    truth, scene = json.loads(DEMO_TRUTH.read_text()), Scene.load(DEFAULT_SCENE)
    with open_recording(demo_cine) as rec:
        coefficients = NetworkMethod(DEFAULT_MODELS, scene).infer(roi_frames(rec, scene, 0, len(rec))).coefficients
    fps = truth["recording"]["fps"]
    skip = FitSettings().transient_frames(fps)
    for w in truth["windows"]:
        lo, end = w["start_frame"] + skip, w["end_frame"]
        t = (np.arange(lo, end) - w["start_frame"]) / fps
        assert synthesis.start_motion(coefficients[lo:end], t, fps).f1 > 0
        for column in coefficients[lo:end].T:
            result = fit_window(column, fps, FitSettings(max_modes=1))
            assert result.status == "ok" or result.reason


class _Clients:
    """A WebSocket fan-out that keeps what it is given."""

    clients = 1

    def __init__(self) -> None:
        self.messages: list[dict] = []

    def broadcast(self, message: str) -> None:
        self.messages.append(json.loads(message))


def test_publishers_send_a_refined_window_under_the_id_of_its_first_publication(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from service.pipeline.refining import RefinedUpdate
    from service.pipeline.runtime import FittedWindow
    from service.server.metrics import Metrics
    from service.server.publishers import Publishers

    history, metrics, hub = History(tmp_path / "h.sqlite", 7, 1000), Metrics(), _Clients()
    publishers = Publishers(history, metrics, None, hub).start()
    values = np.array([0.1, np.nan, 0.2])
    for index in (4, 5):
        publishers.on_window(FittedWindow(_result(index, 0.1), "demo", values, 19000.0, *[0.0] * 5, 7, "network"))

    def refined(run: int, index: int) -> RefinedUpdate:
        return RefinedUpdate(run, _result(index, 0.3), "network+synthesis", "demo", values, 19000.0, 0.0, 1, 2, 3)

    publishers.on_refined(refined(7, 4))
    publishers.on_refined(refined(8, 4))  # another run's window 4: never published here
    publishers.on_refine_skipped("replaced")
    publishers.stop()
    first, _, update = hub.messages
    assert update["type"] == "window_update" and update["id"] == first["id"] and first["type"] == "window"
    assert (first["revision"], first["refined"], first["method"]) == (0, False, "network")
    assert (update["revision"], update["refined"], update["method"]) == (1, True, "network+synthesis")
    assert update["refine_latency_s"] > 0 and update["window"]["offset_mm"] == 0.3
    assert update["values"] == [0.1, None, 0.2]
    stored = history.get(first["id"])
    assert stored is not None and stored.revision == 1 and stored.result.offset_mm == 0.3
    sample = metrics.registry.get_sample_value
    assert sample("meniscope_windows_refined_total") == 1
    assert sample("meniscope_refine_latency_seconds_count") == 1
    assert sample("meniscope_windows_total", {"status": "settled"}) == 2  # the updates are not counted as windows
    assert sample("meniscope_windows_refine_skipped_total", {"reason": "unmatched"}) == 1
    assert sample("meniscope_windows_refine_skipped_total", {"reason": "replaced"}) == 1
    history.close()


def _priority_after(nice: int) -> tuple[int, int, int]:
    """In a fresh process: (scheduling policy, niceness, a new thread's policy) after ``idle_priority(nice)``."""
    idle_priority(nice)
    seen: list[int] = []
    thread = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
    thread.start()
    thread.join()
    return os.sched_getscheduler(0), os.nice(0), seen[0]


def test_the_lane_runs_in_the_idle_class_at_the_lowest_niceness_and_its_threads_inherit_it() -> None:
    """At nice 19 (the lane's default) the process and every thread it starts run only where no other wants a core;
    at a lower niceness (an operator's choice: refined windows sooner) it stays in the normal class."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        idle = pool.apply(_priority_after, (LANE_NICE,))
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        normal = pool.apply(_priority_after, (5,))
    assert idle == (os.SCHED_IDLE, 19, os.SCHED_IDLE)
    assert normal == (os.SCHED_OTHER, min(19, os.nice(0) + 5), os.SCHED_OTHER)  # niceness adds to this process's


def _window_of(motion):  # type: ignore[no-untyped-def]
    """A 190-frame window (19,000 frames/s, the default scene) whose per-frame records are ``motion``'s, with a
    highlight in every frame, and what refining it takes: (scene, window, records, fps, refined settings)."""
    from service import DEFAULT_SCENE
    from service.analysis import offline
    from service.analysis.results import FitSettings
    from service.analysis.segment import Window
    from service.physics import centre_displacement
    from service.pipeline.records import COEFFICIENTS, FRAME
    from service.scene import Scene

    scene, fps, n = Scene.load(DEFAULT_SCENE), 19000.0, 190
    records = np.zeros(n, FRAME)
    for name, column in zip(COEFFICIENTS, motion.coefficients(np.arange(n) / fps).to_array().T):
        records[name] = column
    records["centre"] = centre_displacement(*(records[name] for name in COEFFICIENTS), scene.nozzle.radius_mm)
    records["highlight"] = 0.5  # a highlight in every frame: the meniscus is seen
    return scene, Window(0, 0, n, True, True), records, fps, offline.refined_settings(FitSettings())


def _searching_to(monkeypatch, motion):  # type: ignore[no-untyped-def]
    """The search stood in for by one that ends at ``motion``."""
    from service.analysis import offline

    def search(scene, frames, t, start, threads=1, fitted=None):  # type: ignore[no-untyped-def]
        return motion.coefficients(t).to_array(), motion, np.eye(10), 20

    monkeypatch.setattr(offline, "refine_task", search)


_TRUTH = dict(d=0.01, p=0.05, A1=0.02, g1=300.0, f1=1500.0, phi1=0.3, A2=0.004, g2=700.0, f2=3600.0, phi2=1.0)


@pytest.mark.parametrize("with_first", [True, False])
def test_a_refinement_that_leaves_the_coefficient_ranges_reports_the_unrefined_window(monkeypatch, with_first) -> None:  # type: ignore[no-untyped-def]
    """A search that ends at a motion no meniscus makes (a Blender recording analysed through an uncalibrated scene:
    its tilt p far outside the ranges, the offset reported 42 mm off) is not reported as refined: the window keeps its
    records and its first fit (else the fit of its records) and says why; inside the ranges the refined motion is
    what the window reports."""
    from service.analysis import offline
    from service.analysis.fit import fit_window
    from service.inverse.synthesis import within_ranges
    from service.physics import WindowMotion

    truth = WindowMotion(**_TRUTH)
    scene, window, records, fps, settings = _window_of(truth)
    n, radius = len(records), scene.nozzle.radius_mm
    first = fit_window(records["centre"], fps, settings) if with_first else None
    astray = WindowMotion(**{**truth.__dict__, "p": 160.0})  # D(0, t) 40 mm from the truth's
    for motion, refined in ((astray, False), (truth, True)):
        assert within_ranges(motion, np.arange(n) / fps) == refined
        _searching_to(monkeypatch, motion)
        out = offline.refine_window(scene, window, records, np.zeros((n, 96, 96), np.uint16), fps, settings, first)
        offset = out.result.offset_mm
        assert offset is not None and abs(offset - (truth.d + truth.p * radius)) < 0.005
        assert (offline.UNREFINED in (out.result.reason or "")) != refined
        if not refined:
            assert out.records.tobytes() == records.tobytes()
            if first is not None:
                assert out.result.modes == first.modes


@pytest.mark.parametrize("off", [0.0, 0.005, 0.03, 1.3])
def test_a_refinement_off_the_frames_frequency_reports_the_default_methods_window(monkeypatch, off) -> None:  # type: ignore[no-untyped-def]
    """Where the default method's window is given (its poles from the frames' brightness), a refinement whose mode 1
    lies over ASTRAY_FREQUENCY from its frequency (it settled on mode 2, or on the frames' noise) is not reported:
    the default method's window is, records, fit and series as they were, saying why; nearer, the refined motion is
    reported (its fit's own frequency, with the pixel fit's intervals)."""
    from service.analysis import offline
    from service.analysis.fit import fit_window
    from service.physics import WindowMotion

    truth = WindowMotion(**_TRUTH)
    scene, window, records, fps, settings = _window_of(truth)
    n = len(records)
    default = fit_window(records["centre"], fps, settings)
    unrefined = offline.RefinedWindow(window, records.copy(), default, records["centre"].copy())
    refined_motion = WindowMotion(**{**_TRUTH, "f1": truth.f1 * (1 + off), "f2": truth.f2 * (1 + off)})
    _searching_to(monkeypatch, refined_motion)
    out = offline.refine_window(
        scene, window, records, np.zeros((n, 96, 96), np.uint16), fps, settings, default, 1, unrefined
    )
    kept = off > offline.ASTRAY_FREQUENCY
    assert ("the unrefined window is reported" in (out.result.reason or "")) == kept
    if kept:
        assert out.records.tobytes() == records.tobytes()
        assert out.result.modes == default.modes
        assert np.array_equal(out.series, unrefined.series)
    else:
        assert abs(out.result.modes[0].frequency_hz / refined_motion.f1 - 1) < 1e-3
        assert out.result.intervals == "pixels"


def test_the_lane_publishes_a_refinement_it_keeps_and_counts_one_it_rejects_as_skipped(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """In `serve --refine` a window whose refinement is rejected (here: mode 1 ended 30 % off the window's own
    frequency) was published already, with the default method's numbers: the lane publishes no update of it, and
    counts it skipped (``rejected``); a refinement it keeps is published."""
    import time
    from types import SimpleNamespace

    from service import DEFAULT_MODELS, DEFAULT_SCENE
    from service.analysis.results import FitSettings
    from service.physics import WindowMotion
    from service.pipeline import refining

    truth = WindowMotion(**_TRUTH)
    _, window, records, fps, _ = _window_of(truth)
    frames = FrameBatch(
        np.zeros((len(records), 96, 96), np.uint16), np.arange(len(records)), np.arange(len(records)) / fps
    )
    offered = refining.Offered(0, window, records, (frames,), fps, time.monotonic())
    # the lane's process forked from this one, so that the search stood in for reaches it
    forked = multiprocessing.get_context("fork")
    monkeypatch.setattr(refining, "multiprocessing", SimpleNamespace(get_context=lambda _: forked))
    fit = FitSettings(poles="series", series_model="steady")  # the series' own poles: the truth's frequency
    astray = WindowMotion(**{**_TRUTH, "f1": 1.3 * truth.f1})
    for motion, kept in ((astray, False), (truth, True)):
        _searching_to(monkeypatch, motion)  # before the lane's process is forked
        published, skipped = [], []
        config = refining.LaneConfig(Path(DEFAULT_SCENE), DEFAULT_MODELS, "network", fit)
        lane = refining.RefineLane(config, published.append, skipped.append, nice=0)
        try:
            lane.offer(offered, "test")
            deadline = time.monotonic() + 120
            while not published + skipped and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            lane.close()
        if kept:
            assert len(published) == 1 and not skipped
            assert abs(published[0].result.modes[0].frequency_hz / truth.f1 - 1) < 1e-3
        else:
            assert (published, skipped) == ([], ["rejected"])
