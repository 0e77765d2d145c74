"""Replay pacing: frames fall due on one drift-free schedule at ``speed`` x the recorded rate.

The schedule itself is checked on a simulated clock (exact, no waiting); one short real-time run
checks, with loose bounds, that a paced replay neither runs flat out nor stalls.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from service.recordings import open_writer
from service.sources import FrameBatch, open_source
from service.sources.pacing import Pacer
from tests.clocks import SimulatedClock

FPS, FRAMES = 19000.0, 2000


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2,000 frames of 16 x 16 px at 19,000 frames/s: 105 ms as recorded."""
    path = tmp_path_factory.mktemp("pacing") / "rec.cine"
    with open_writer(path, 16, 16, FPS, bit_depth=8) as writer:
        writer.write(np.zeros((FRAMES, 16, 16), np.uint8))
    return path


class TestPacer:
    def test_late_wakeups_do_not_accumulate_into_drift(self) -> None:
        clock = SimulatedClock(oversleep_s=0.002)
        pacer = Pacer(0.5, clock, clock.sleep)
        pacer.start(3.0)
        for k in range(1, 2001):
            due = 3.0 + k * 0.001
            pacer.wait(due, timeout=1.0)
            lag = pacer.now() - due  # stream seconds behind schedule: one oversleep at most, however many waits
            assert -1e-12 <= lag <= 0.002 * 0.5 + 1e-12

    def test_one_stream_second_takes_one_over_speed_wall_seconds(self) -> None:
        clock = SimulatedClock()
        pacer = Pacer(0.1, clock, clock.sleep)
        pacer.start(0.0)
        pacer.wait(0.5, timeout=60.0)
        assert clock.sleeps == [pytest.approx(5.0)]

    def test_a_wait_never_outlasts_its_timeout(self) -> None:
        clock = SimulatedClock()
        pacer = Pacer(1.0, clock, clock.sleep)
        pacer.start(0.0)
        pacer.wait(10.0, timeout=0.1)
        pacer.wait(-1.0, timeout=0.1)  # already due: no sleep at all
        assert clock.sleeps == [pytest.approx(0.1)]

    def test_speed_zero_never_waits(self) -> None:
        clock = SimulatedClock()
        pacer = Pacer(0.0, clock, clock.sleep)
        pacer.start(0.0)
        pacer.wait(1e9, timeout=10.0)
        assert clock.sleeps == [] and pacer.now() == float("inf")

    @pytest.mark.parametrize("speed", [-1.0, float("nan"), float("inf")])
    def test_refuses_a_speed_that_is_not_a_finite_non_negative_number(self, speed: float) -> None:
        with pytest.raises(ValueError, match="speed"):
            Pacer(speed)


class TestReplaySpeed:
    def test_paced_replay_neither_runs_flat_out_nor_stalls(self, recording: Path) -> None:
        speed, run_s = 0.05, 0.6  # 950 frames/s of wall time: about 570 frames in the run
        delivered = 0
        with open_source(str(recording), speed=speed, timeout=0.02) as source:
            start = time.monotonic()
            while (elapsed := time.monotonic() - start) < run_s:
                delivered += len(source.read(64))  # type: ignore[arg-type]
        expected = elapsed * FPS * speed
        assert 0.5 * expected < delivered < 1.5 * expected, (
            f"{delivered} frames in {elapsed:.2f} s, expected ~{expected:.0f}"
        )

    def test_unpaced_replay_fills_every_batch_without_waiting(self, recording: Path) -> None:
        with open_source(str(recording), speed="max", timeout=1e-6) as source:
            sizes = []
            while (batch := source.read(300)) is not None:
                sizes.append(len(batch))
        assert sizes == [300] * 6 + [200]

    def test_a_read_returns_at_its_timeout_with_the_frames_due(self, recording: Path) -> None:
        with open_source(str(recording), speed=0.001, timeout=0.05) as source:  # 19 frames/s
            batch = source.read(64)
        assert batch is not None and 1 <= len(batch) < 64

    def test_a_consumer_that_falls_behind_catches_up_without_losing_frames(self, recording: Path) -> None:
        with open_source(str(recording), speed=1.0) as source:
            time.sleep(0.2)  # the whole recording (105 ms) falls due meanwhile
            batches = []
            while (batch := source.read(500)) is not None:
                batches.append(batch)
            frames = FrameBatch.concatenate(batches)
        assert [len(b) for b in batches] == [500] * 4
        np.testing.assert_array_equal(frames.indices, np.arange(FRAMES))
        assert source.stats.gaps == 0
