"""The pipeline's sink in the service: every window result to history, ZeroMQ, WebSocket and metrics.

The pipeline hands results and trace snippets over through a bounded queue and goes on; one
publishing thread stores each window (which gives it its id), then sends it on. If that thread ever
fell a whole queue behind, further items would be dropped and counted rather than pile up.
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
        self._queue: queue.Queue[FittedWindow | TraceSnippet | None] = queue.Queue(QUEUE_ITEMS)
        self._thread = threading.Thread(target=self._run, name="meniscope-publish", daemon=True)

    def start(self) -> "Publishers":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._queue.put(None)
        self._thread.join(5.0)

    # --- PipelineSink: hand over, never wait
    def on_window(self, fitted: FittedWindow) -> None:
        self._offer(fitted)

    def on_trace(self, trace: TraceSnippet) -> None:
        if self.hub.clients:
            self._offer(trace)

    def on_inference(self, seconds: float, frames: int) -> None:
        self.metrics.inference_call(seconds)

    def _offer(self, item: FittedWindow | TraceSnippet) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    # --- the publishing thread
    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            try:
                if isinstance(item, FittedWindow):
                    self._window(item)
                else:
                    self.hub.broadcast(trace_message(item))
            except Exception:  # noqa: BLE001 - one bad item must not stop publishing
                log.exception("publishing failed")

    def _window(self, fitted: FittedWindow) -> None:
        result, stored_at = fitted.result, time.time()
        window_id = self.history.add(result, fitted.source, fitted.fps, stored_at)
        stored = StoredWindow(window_id, stored_at, fitted.source, fitted.fps, result)
        if self.zmq is not None:
            self.zmq.send(window_message(stored))
        self.hub.broadcast(window_message(stored, fitted.values))
        self.metrics.window(result, time.monotonic() - fitted.closed_at)
