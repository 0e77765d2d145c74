"""Camera adapters behind one interface: replay, V4L2, Aravis, ZeroMQ and simulated frame sources.

``open_source(uri, **options)`` picks the adapter by URI scheme and returns it open; every adapter
delivers :class:`FrameBatch` es through :class:`FrameSource` and passes tests/test_sources_conformance.py.
"""

from service.sources.aravis import AravisSource
from service.sources.base import (
    Frame,
    FrameBatch,
    FrameSource,
    SourceOptions,
    SourceStats,
    StreamFormat,
    open_source,
    probe_source,
)
from service.sources.replay import ReplaySource
from service.sources.simulated import SimulatedSource
from service.sources.v4l2 import V4l2Source
from service.sources.zmq_source import FrameSender, ZmqSource

__all__ = [
    "AravisSource",
    "Frame",
    "FrameBatch",
    "FrameSender",
    "FrameSource",
    "ReplaySource",
    "SimulatedSource",
    "SourceOptions",
    "SourceStats",
    "StreamFormat",
    "V4l2Source",
    "ZmqSource",
    "open_source",
    "probe_source",
]
