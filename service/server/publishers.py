"""The pipeline's sink in the service: every window result to ZeroMQ, WebSocket, history and metrics.

A fitted window is sent at once, on the thread that brings it (the fit pool's result thread): given its
id by the history, sent on ZeroMQ and handed to the WebSocket clients, a thread hop and an interpreter
lock hand-over sooner than through a queue. Storing it in SQLite and counting it, and the trace
snippets, go through a bounded queue to one publishing thread; if that thread ever fell a whole queue
behind, further items would be dropped and counted rather than pile up.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from service.pipeline.runtime import FittedWindow, TraceSnippet
from service.server.history import History, StoredWindow
from service.server.hub import Hub
from service.server.messages import trace_message, window_message
from service.server.metrics import Metrics
from service.server.zmq_publisher import ZmqPublisher

log = logging.getLogger(__name__)

#: Items (windows and trace snippets) waiting for the publishing thread, at most.
QUEUE_ITEMS = 1024


class Publishers:
    """Publishes what the pipeline makes; each window under the name of the source its frames came from."""

    def __init__(self, history: History, metrics: Metrics, zmq: ZmqPublisher | None, hub: Hub) -> None:
        self.history, self.metrics, self.zmq, self.hub = history, metrics, zmq, hub
        self.dropped = 0
        self._sending = threading.Lock()  # one window at a time gets its id and goes out (several fit workers)
        # for the publishing thread: a sent window with its publish latency (s), or a trace snippet
        self._queue: queue.Queue[tuple[StoredWindow, float] | TraceSnippet | None] = queue.Queue(QUEUE_ITEMS)
        self._thread = threading.Thread(target=self._run, name="meniscope-publish", daemon=True)

    def start(self) -> "Publishers":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._queue.put(None)
        self._thread.join(5.0)

    # --- PipelineSink: hand over, never wait
    def on_window(self, fitted: FittedWindow) -> None:
        try:
            with self._sending:
                stored, sent = self._send(fitted)
        except Exception:  # noqa: BLE001 - one bad window must not stop the fit results
            log.exception("publishing failed")
            return
        self._offer((stored, sent - fitted.closed_at))

    def on_trace(self, trace: TraceSnippet) -> None:
        if self.hub.clients:
            self._offer(trace)

    def on_inference(self, seconds: float, frames: int) -> None:
        self.metrics.inference_call(seconds)

    def _offer(self, item: tuple[StoredWindow, float] | TraceSnippet) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _send(self, fitted: FittedWindow) -> tuple[StoredWindow, float]:
        """Give the window its id and send it to the printer (ZeroMQ) and the dashboards; the window as it will
        be stored and when (monotonic s) it was sent."""
        stored = StoredWindow(self.history.new_id(), time.time(), fitted.source, fitted.fps, fitted.result)
        if self.zmq is not None:
            self.zmq.send(window_message(stored))
        self.hub.broadcast(window_message(stored, fitted.values))
        return stored, time.monotonic()

    # --- the publishing thread
    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            try:
                if isinstance(item, TraceSnippet):
                    self.hub.broadcast(trace_message(item))
                else:
                    stored, latency = item
                    self.history.add(stored.result, stored.source, stored.fps, stored.stored, stored.id)
                    self.metrics.window(stored.result, latency)
            except Exception:  # noqa: BLE001 - one bad item must not stop publishing
                log.exception("publishing failed")
