"""Paced delivery: a stream's own timestamps mapped onto the monotonic clock at ``speed`` times real time.

Every frame is due at a fixed point of one schedule set when the stream starts, so sleeping to the
schedule never accumulates drift, however the reads are batched.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Annotated, Any

from pydantic import BeforeValidator, Field


def _max_is_unpaced(value: Any) -> Any:
    return 0.0 if isinstance(value, str) and value.strip().lower() == "max" else value


#: The ``speed`` option of paced sources: x the stream's own rate; 0 or "max": unpaced.
Speed = Annotated[
    float,
    BeforeValidator(_max_is_unpaced),
    Field(ge=0, allow_inf_nan=False, description="x the stream's rate; 0 or 'max': unpaced"),
]


class Pacer:
    """Stream time (s) <-> monotonic clock at ``speed`` x real time; ``speed == 0`` means as fast as possible."""

    def __init__(
        self,
        speed: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not (math.isfinite(speed) and speed >= 0):
            raise ValueError(f"speed must be a finite number >= 0, got {speed}")
        self.speed = speed
        self._clock, self._sleep = clock, sleep
        self._wall0 = self._stream0 = 0.0

    def start(self, stream_time: float) -> None:
        """Make ``stream_time`` (s) due now; later times fall due ``1 / speed`` s of wall time per stream second."""
        self._wall0, self._stream0 = self._clock(), stream_time

    def now(self) -> float:
        """The stream time due now (s); infinite when unpaced."""
        if self.speed == 0:
            return math.inf
        return self._stream0 + (self._clock() - self._wall0) * self.speed

    def wait(self, stream_time: float, timeout: float) -> None:
        """Sleep until ``stream_time`` is due or ``timeout`` s have passed, whichever comes first."""
        if self.speed == 0:
            return
        delay = min(self._wall0 + (stream_time - self._stream0) / self.speed - self._clock(), timeout)
        if delay > 0:
            self._sleep(delay)
