"""Prometheus metrics (names shared with deploy/'s alert rules and Grafana dashboard: keep them).

Frame counters and rates are read from the pipeline's :class:`PipelineStats` when scraped (one
source of truth, nothing counted twice); window histograms and counters are fed as results are
published. Base units in names, ``_total`` counters, histograms (they aggregate across printers),
no per-window labels. Each app has a registry of its own, so tests need no globals.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import get_args

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, disable_created_metrics
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from service.analysis.results import Status, WindowResult
from service.pipeline.runtime import PipelineStats
from service.pipeline.supervisor import SOURCE_SILENT_S, Health

STATUSES = get_args(Status)
#: Why the refinement lane skips a window (the ``reason`` label of ``meniscope_windows_refine_skipped_total``).
REFINE_SKIPPED = ("replaced", "incomplete", "failed", "rejected", "unmatched")

disable_created_metrics()  # no *_created series: nothing here reads them, and they double every counter


class _PipelineCollector(Collector):
    """Counters and gauges of the pipeline's statistics and health, as they are at scrape time."""

    def __init__(
        self,
        stats: Callable[[], PipelineStats],
        health: Callable[[], Health],
        websocket: Callable[[], tuple[int, int]],
        history: Callable[[], HistoryHealth] | None,
    ) -> None:
        self.stats, self.health, self.websocket = stats, health, websocket
        self.history = history or (lambda: HistoryHealth())

    def collect(self) -> Iterator[Metric]:
        s, health = self.stats(), self.health()
        ready = float(health.ready)
        flowing = float(
            health.state in ("running", "no_signal", "no_highlight", "degraded")
            and time.monotonic() - s.last_frame_at < SOURCE_SILENT_S
        )
        clients, skipped = self.websocket()
        history = self.history()
        for name, value, text in (
            ("frames_acquired", s.frames_acquired, "Frames read from the source."),
            ("frames_inferred", s.frames_inferred, "Frames run through the inverse model."),
            ("frames_dropped", s.frames_dropped, "Frames read but dropped because inference was behind."),
            ("frame_gaps", s.frame_gaps, "Jumps in the source's frame indices (frames lost before the service)."),
            ("frames_lost_upstream", s.frames_lost_upstream, "Frames missing inside those jumps."),
            (
                "windows_skipped",
                s.windows_skipped,
                "Windows closed while every fit worker was busy and as many windows waited (not fitted).",
            ),
            ("websocket_messages_skipped", skipped, "Messages lagging WebSocket clients did not get."),
            ("history_write_failures", history.failures, "Failed attempts to store windows in the history."),
            ("history_windows_lost", history.lost, "Windows sent but never stored (the history backlog overflowed)."),
        ):
            yield CounterMetricFamily(f"meniscope_{name}", text, value=value)
        trigger = s.trigger
        yield CounterMetricFamily(
            "meniscope_trigger_ejections",
            "Ejection events received from the printer's trigger.",
            value=trigger.received,
        )
        disagreements = CounterMetricFamily(
            "meniscope_trigger_disagreements",
            "Printer ejections the video did not show (side=printer_only) and "
            "video ejections the printer did not announce (side=video_only), within 2 frames.",
            labels=["side"],
        )
        disagreements.add_metric(["printer_only"], trigger.printer_only)
        disagreements.add_metric(["video_only"], trigger.video_only)
        yield disagreements
        for name, value, text in (
            ("source_up", flowing, f"1 while frames arrive from the source (within {SOURCE_SILENT_S:g} s), else 0."),
            ("ready", ready, "1 while the service is ready (model loaded, source running), else 0."),
            ("input_frames_per_second", s.fps_in, "Frames per second read from the source (last second)."),
            ("output_frames_per_second", s.fps_out, "Frames per second inferred (last second)."),
            ("websocket_clients", clients, "Connected WebSocket clients."),
            (
                "signal",
                float(flowing and health.state not in ("no_signal", "no_highlight")),
                "1 while the frames arriving show the meniscus' highlights, 0 while they are flat (dark, capped, "
                "saturated), show no highlight, or are absent.",
            ),
            ("history_up", float(history.error is None), "1 while windows are stored in the history, else 0."),
            ("history_backlog_windows", history.backlog, "Sent windows waiting to be stored in the history."),
        ):
            yield GaugeMetricFamily(f"meniscope_{name}", text, value=value)


@dataclass(frozen=True)
class HistoryHealth:
    """Whether windows are being stored: the error if not, failed writes, windows waiting and lost."""

    error: str | None = None
    failures: int = 0
    backlog: int = 0
    lost: int = 0


def status_registry(
    stats: Callable[[], PipelineStats],
    health: Callable[[], Health],
    websocket: Callable[[], tuple[int, int]],
    history: Callable[[], HistoryHealth] | None = None,
) -> CollectorRegistry:
    """A registry of the pipeline's statistics and health, read through these callables at scrape time (the web
    process reads them from the pipeline process's latest report)."""
    registry = CollectorRegistry()
    registry.register(_PipelineCollector(stats, health, websocket, history))
    return registry


class Metrics:
    """What :meth:`window` and :meth:`inference` record as results are published, plus the pipeline's
    statistics and health when ``stats`` and ``health`` are given (in one process; the pipeline process
    records only what it publishes, and the web process adds the rest: :func:`status_registry`)."""

    def __init__(
        self,
        stats: PipelineStats | None = None,
        health: Callable[[], Health] | None = None,
        websocket: Callable[[], tuple[int, int]] = lambda: (0, 0),
        history: Callable[[], HistoryHealth] | None = None,
    ) -> None:
        self.registry = r = CollectorRegistry()
        if stats is not None and health is not None:
            r.register(_PipelineCollector(lambda: stats, health, websocket, history))
        self.windows = Counter("meniscope_windows", "Windows published, by fit status.", ["status"], registry=r)
        for status in STATUSES:
            self.windows.labels(status)
        self.unsettled = Counter(
            "meniscope_windows_unsettled", "Windows that ended at an ejection before the meniscus settled.", registry=r
        )
        self.settling = Histogram(
            "meniscope_settling_time_seconds",
            "Settling time of windows that settled.",
            buckets=(5e-4, 1e-3, 2e-3, 3e-3, 4e-3, 5e-3, 6e-3, 8e-3, 1e-2, 1.5e-2, 2e-2, 5e-2),
            registry=r,
        )
        self.frequency = Histogram(
            "meniscope_oscillation_frequency_hertz",
            "Dominant mode frequency per window.",
            buckets=(250, 500, 750, 1000, 1250, 1500, 1750, 2000, 2500, 3000, 4000, 6000),
            registry=r,
        )
        self.decay = Histogram(
            "meniscope_decay_rate_per_second",
            "Dominant mode decay rate per window.",
            buckets=(50, 100, 200, 300, 500, 750, 1000, 1500, 2000, 3000, 5000, 10000),
            registry=r,
        )
        self.inference = Histogram(
            "meniscope_inference_latency_seconds",
            "Time of one batched inference call.",
            buckets=(1e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 1.0),
            registry=r,
        )
        self.publish = Histogram(
            "meniscope_window_publish_latency_seconds",
            "From the frame that closed a window being read to its result being published.",
            buckets=(1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0),
            registry=r,
        )
        self.refined = Counter(
            "meniscope_windows_refined",
            "Windows refined by synthesis and published again as an update (serve --refine).",
            registry=r,
        )
        self.refine_skipped = Counter(
            "meniscope_windows_refine_skipped",
            "Windows the refinement lane did not refine: replaced by a newer window while waiting (reason=replaced), "
            "frames missing (incomplete), the refinement raised (failed), or its window no longer known (unmatched).",
            ["reason"],
            registry=r,
        )
        for reason in REFINE_SKIPPED:
            self.refine_skipped.labels(reason)
        self.refine_latency = Histogram(
            "meniscope_refine_latency_seconds",
            "From the frame that closed a window being read to its refined update being published.",
            buckets=(1.0, 2.5, 5.0, 10.0, 20.0, 30.0, 45.0, 60.0, 90.0, 120.0, 180.0, 300.0, 600.0),
            registry=r,
        )
        self.last_frequency = Gauge(
            "meniscope_last_frequency_hertz", "Dominant frequency of the last fitted window.", registry=r
        )
        self.last_settling = Gauge(
            "meniscope_last_settling_time_seconds", "Settling time of the last window that settled.", registry=r
        )

    def inference_call(self, seconds: float) -> None:
        self.inference.observe(seconds)

    def window(self, result: WindowResult, latency_s: float) -> None:
        """Record one published window and how long after it closed it went out."""
        self.windows.labels(result.status).inc()
        self.publish.observe(latency_s)
        if result.ends_at_ejection and result.status in ("ok", "unresolved") and not result.settled:
            self.unsettled.inc()
        if result.settling_time_s is not None:
            self.settling.observe(result.settling_time_s)
            self.last_settling.set(result.settling_time_s)
        if result.status == "ok" and result.modes:
            dominant = result.modes[0]
            self.frequency.observe(dominant.frequency_hz)
            self.decay.observe(dominant.decay_rate_per_s)
            self.last_frequency.set(dominant.frequency_hz)
