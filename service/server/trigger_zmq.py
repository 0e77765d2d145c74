"""The printer's trigger over ZeroMQ: a SUB socket connected to ``trigger_zmq``, each message one ejection.

A message is UTF-8 JSON ``{"frame": N}`` (the camera's frame index) or ``{"time_s": T}`` (seconds since the
stream's frame 0), as the last (or only) part of a multipart message, so a topic part may come first. A
message that is neither is logged and skipped: a printer's bad message must not stop the service.
"""

from __future__ import annotations

import json
import logging
import threading

import zmq

from service.pipeline.trigger import TriggerInbox

log = logging.getLogger(__name__)
POLL_MS = 100


class TriggerSubscriber:
    """A thread reading the printer's ejection events from ``endpoint`` into ``inbox`` until :meth:`close`."""

    def __init__(self, endpoint: str, inbox: TriggerInbox) -> None:
        self.endpoint, self.inbox = endpoint, inbox
        self._stop = threading.Event()
        self._socket = zmq.Context.instance().socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.SUBSCRIBE, b"")
        self._socket.connect(endpoint)
        self._thread = threading.Thread(target=self._run, name="meniscope-trigger", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if not self._socket.poll(POLL_MS):
                    continue
                body = self._socket.recv_multipart()[-1]
                try:
                    event = json.loads(body)
                    self.inbox.add(**{k: event[k] for k in ("frame", "time_s") if k in event})
                except (
                    ValueError,
                    TypeError,
                    KeyError,
                ) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
                    log.warning(
                        'trigger %s: skipped a message that is not {"frame": N} or {"time_s": T} (%s)',
                        self.endpoint,
                        exc,
                    )
        finally:
            self._socket.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
