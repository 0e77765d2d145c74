"""The pipeline's sink in the service: every window result to ZeroMQ, WebSocket, history and metrics.

A fitted window is sent at once, on the thread that brings it (the fit pool's result thread): given its
id by the history, sent on ZeroMQ and handed to the WebSocket clients, a thread hop and an interpreter
lock hand-over sooner than through a queue. Storing it in SQLite and counting it, and the trace
snippets, go through a bounded queue to one publishing thread; if that thread ever fell a whole queue
behind, further items would be dropped and counted rather than pile up.

When the history cannot be written (data folder read-only, disk full), windows that were sent but not
stored wait in a bounded backlog and are written, oldest first, once the database takes writes again
(tried on every window and every second); the failure is counted, shown in readiness, and logged once
when it starts and once when it ends, not once per window.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict, deque
from typing import Protocol

from service.pipeline.refining import RefinedUpdate
from service.pipeline.runtime import FittedWindow, TraceSnippet
from service.server.history import History, StoredWindow
from service.server.messages import REFINED_TOPIC, trace_message, window_message
from service.server.metrics import Metrics
from service.server.zmq_publisher import ZmqPublisher

log = logging.getLogger(__name__)

#: Items (windows and trace snippets) waiting for the publishing thread, at most.
QUEUE_ITEMS = 1024
#: Sent windows kept for the history while it cannot be written (about 1 kB each: 15 min at 100 windows/s).
BACKLOG_WINDOWS = 100_000
#: Seconds between attempts to write the backlog when no window comes to trigger one.
RETRY_S = 1.0
#: Published windows whose ids a refined update can find (by pipeline run and window index): 10 minutes of windows
#: at 100 ejections/s, ~100 bytes each; a refinement later than that is skipped (``unmatched``).
IDS_KEPT = 60_000


class Fanout(Protocol):
    """Where WebSocket messages go: :class:`service.server.hub.Hub`, or the pipe to the web process."""

    @property
    def clients(self) -> int: ...

    def broadcast(self, message: str) -> None: ...


class Publishers:
    """Publishes what the pipeline makes; each window under the name of the source its frames came from."""

    def __init__(self, history: History, metrics: Metrics, zmq: ZmqPublisher | None, hub: Fanout) -> None:
        self.history, self.metrics, self.zmq, self.hub = history, metrics, zmq, hub
        self.dropped = 0
        self.history_error: str | None = None  # why the history is not being written, None while it is
        self.history_failures = 0  # failed attempts to write it
        self.history_lost = 0  # windows pushed out of a full backlog: sent, never stored
        self._backlog: deque[StoredWindow] = deque()
        self._closed = False  # set by stop(): a fit that comes back later is counted, not sent on closed sockets
        self._sending = threading.Lock()  # one window at a time gets its id and goes out (several fit workers)
        self._ids: OrderedDict[tuple[int, int], int] = OrderedDict()  # (run, window index) -> id, the newest last
        # for the publishing thread: a sent window with its publish latency (s), or a trace snippet
        self._queue: queue.Queue[tuple[StoredWindow, float] | TraceSnippet | None] = queue.Queue(QUEUE_ITEMS)
        self._thread = threading.Thread(target=self._run, name="meniscope-publish", daemon=True)

    def start(self) -> Publishers:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Publish what is queued, write what the history can take, and close ZeroMQ: call after the pipeline has
        stopped (a fit still out is then counted as unpublished, never sent on a closed socket)."""
        with self._sending:
            self._closed = True
        self._queue.put(None)
        self._thread.join(5.0)
        if self.zmq is not None:
            self.zmq.close()

    @property
    def backlog(self) -> int:
        """Sent windows waiting to be stored."""
        return len(self._backlog)

    # --- PipelineSink: hand over, never wait
    def on_window(self, fitted: FittedWindow) -> None:
        try:
            with self._sending:
                if self._closed:
                    self.dropped += 1
                    return
                stored, sent = self._send(fitted)
        except Exception:
            log.exception("publishing failed")
            return
        self._offer((stored, sent - fitted.closed_at))

    def on_trace(self, trace: TraceSnippet) -> None:
        if self.hub.clients:
            self._offer(trace)

    def on_inference(self, seconds: float, frames: int) -> None:
        self.metrics.inference_call(seconds)

    def on_refined(self, refined: RefinedUpdate) -> None:
        """Send a refined window as an update of the window published first (same id, revision 1), store it in that
        window's place and count it; skipped (``unmatched``) where that window is not known here."""
        try:
            with self._sending:
                window_id = self._ids.get((refined.run, refined.result.index))
                if self._closed or window_id is None:
                    self.metrics.refine_skipped.labels("unmatched").inc()
                    return
                stored = self._send_refined(refined, window_id)
        except Exception:
            log.exception("publishing a refined window failed")
            return
        self._offer((stored, stored.refine_latency_s))

    def on_refine_skipped(self, why: str) -> None:
        self.metrics.refine_skipped.labels(why).inc()

    def _offer(self, item: tuple[StoredWindow, float] | TraceSnippet) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _send(self, fitted: FittedWindow) -> tuple[StoredWindow, float]:
        """Give the window its id and send it to the printer (ZeroMQ) and the dashboards; the window as it will
        be stored and when (monotonic s) it was sent."""
        stored = StoredWindow(
            self.history.new_id(), time.time(), fitted.source, fitted.fps, fitted.result, fitted.method
        )
        if self.zmq is not None:
            self.zmq.send(window_message(stored))
        self.hub.broadcast(window_message(stored, fitted.values))
        sent = time.monotonic()
        self._ids[(fitted.run, fitted.result.index)] = stored.id
        if len(self._ids) > IDS_KEPT:
            self._ids.popitem(last=False)
        return stored, sent

    def _send_refined(self, refined: RefinedUpdate, window_id: int) -> StoredWindow:
        """Send the refined window under ``window_id`` to the printer (ZeroMQ, its own topic) and the dashboards;
        the window as it will be stored, its latency measured to now (what the messages say)."""
        latency = time.monotonic() - refined.closed_at
        stored = StoredWindow(
            window_id, time.time(), refined.source, refined.fps, refined.result, refined.method, 1, latency
        )
        if self.zmq is not None:
            self.zmq.send(window_message(stored), REFINED_TOPIC)
        self.hub.broadcast(window_message(stored, refined.values))
        return stored

    # --- the publishing thread
    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=RETRY_S)
            except queue.Empty:
                self._store()
                continue
            if item is None:
                break
            try:
                if isinstance(item, TraceSnippet):
                    self.hub.broadcast(trace_message(item))
                else:
                    stored, latency = item
                    if stored.revision:
                        self.metrics.refined.inc()
                        self.metrics.refine_latency.observe(latency)
                    else:
                        self.metrics.window(stored.result, latency)
                    self._backlog.append(stored)
                    if len(self._backlog) > BACKLOG_WINDOWS:
                        self._backlog.popleft()
                        self.history_lost += 1
                    self._store()
            except Exception:
                log.exception("publishing failed")
        self._store()

    def _store(self) -> None:
        """Write the backlog, oldest first, until it is empty or the history refuses a write."""
        while self._backlog:
            stored = self._backlog[0]
            try:
                self.history.add(
                    stored.result,
                    stored.source,
                    stored.fps,
                    stored.stored,
                    stored.id,
                    stored.method,
                    stored.revision,
                    stored.refine_latency_s,
                )
            except Exception as exc:
                self.history_failures += 1
                if self.history_error is None:
                    log.warning(
                        "history: cannot store windows (%s); keeping up to %d in memory until it can",
                        exc,
                        BACKLOG_WINDOWS,
                    )
                self.history_error = f"cannot store windows in the history: {exc}"
                return
            self._backlog.popleft()
        if self.history_error is not None:
            log.warning("history: storing windows again (%d sent windows lost while it failed)", self.history_lost)
            self.history_error = None
