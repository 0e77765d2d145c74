"""A simulated monotonic clock for pacing tests: exact, and no test waits for real time to pass."""

from __future__ import annotations


class SimulatedClock:
    """A monotonic clock whose sleeps advance it, each overshooting by ``oversleep_s`` like a busy OS."""

    def __init__(self, oversleep_s: float = 0.0) -> None:
        self.now, self.oversleep_s, self.sleeps = 100.0, oversleep_s, []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds + self.oversleep_s
