"""The frame path of the service: supervisor, pipeline, fit pool, ZeroMQ publisher, history writer, metrics.

:class:`Engine` holds what makes and publishes window results, and nothing that answers HTTP: the pipeline
process (:mod:`service.server.pipeline_process`) runs one, so that no web request or WebSocket client can take
the interpreter from the frames. What the web side shows of it is a :class:`Report`, taken ten times a second.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

from prometheus_client import generate_latest

from service.pipeline.runtime import LatestFrame, PipelineStats
from service.pipeline.supervisor import Health, Supervisor
from service.pipeline.trigger import TriggerInbox
from service.server.history import History
from service.server.metrics import HistoryHealth, Metrics
from service.server.publishers import Fanout, Publishers
from service.server.settings import ServiceSettings
from service.server.trigger_zmq import TriggerSubscriber
from service.server.zmq_publisher import ZmqPublisher

#: The history database, in the data folder.
HISTORY_FILE = "history.sqlite"


@dataclass(frozen=True)
class Report:
    """The engine as the web side shows it: health, statistics (without the latest frame), history, counts."""

    health: Health
    stats: PipelineStats
    history: HistoryHealth
    unpublished: int  # windows made but never sent (the publishing queue was full, or the service stopping)
    latest: LatestFrame | None
    metrics: bytes  # the window metrics, Prometheus text format
    taken: float  # monotonic time (s) it was taken
    websocket_skipped: int = 0  # WebSocket messages the web process did not take in time


class Engine:
    """Opens the history, binds ZeroMQ and runs the supervisor for ``settings``, sending WebSocket messages to
    ``fanout``; :meth:`stop` stops them in order. The printer's ejection events arrive in :attr:`trigger`: from
    ``trigger_zmq`` (subscribed to here) and from the web process (:meth:`eject`)."""

    def __init__(self, settings: ServiceSettings, fanout: Fanout) -> None:
        s = self.settings = settings
        self.stats = PipelineStats()
        self.history = History(s.data_dir / HISTORY_FILE, s.retention_days, s.retention_windows)
        try:
            self.zmq = ZmqPublisher(s.zmq_publish) if s.zmq_publish else None
        except Exception:
            self.history.close()
            raise
        self.metrics = Metrics()
        self.publishers = Publishers(self.history, self.metrics, self.zmq, fanout)
        self.trigger = TriggerInbox(self.stats.trigger)
        self.supervisor = Supervisor(s, self.publishers, self.stats, self.trigger)
        self._trigger_zmq: TriggerSubscriber | None = None

    def start(self) -> Engine:
        self.publishers.start()
        self.supervisor.start()
        if self.settings.trigger_zmq:
            self._trigger_zmq = TriggerSubscriber(self.settings.trigger_zmq, self.trigger)
        return self

    def eject(self, frame: int | None, time_s: float | None) -> None:
        """One of the printer's ejection events, sent on by the web process (checked there already)."""
        self.trigger.add(frame, time_s)

    def stop(self) -> None:
        """In order: the trigger and the pipeline stop, the publishers drain and close ZeroMQ, the history closes."""
        if self._trigger_zmq is not None:
            self._trigger_zmq.close()
        self.supervisor.stop()
        self.publishers.stop()
        self.history.close()

    def reconfigure(self, settings: ServiceSettings) -> None:
        self.settings = settings
        self.supervisor.reconfigure(settings)

    def health(self) -> Health:
        """The pipeline's health, degraded while the history cannot be written."""
        error = self.publishers.history_error
        health = self.supervisor.health()
        return health if error is None else health.degraded(error)

    def history_health(self) -> HistoryHealth:
        p = self.publishers
        return HistoryHealth(p.history_error, p.history_failures, p.backlog, p.history_lost)

    def report(self) -> Report:
        return Report(
            self.health(),
            dataclasses.replace(self.stats, latest=None),
            self.history_health(),
            self.publishers.dropped,
            self.stats.latest,
            generate_latest(self.metrics.registry),
            time.monotonic(),
        )
