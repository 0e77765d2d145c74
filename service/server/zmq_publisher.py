"""Window results on a ZeroMQ PUB socket, for the printer's controller (docs/service.md).

Each message has two parts: the topic ``meniscope.window`` and the window message of
:mod:`service.server.messages` (UTF-8 JSON). PUB never blocks: a subscriber that does not keep up
loses messages beyond the high-water mark, and so does one that connects late.
"""

from __future__ import annotations

import zmq

from service.errors import MeniscopeError
from service.server.messages import WINDOW_TOPIC

#: Window messages queued per subscriber before PUB drops (about 10 s of windows at 100 ejections/s).
HWM = 1000


class ZmqPublisher:
    """A PUB socket bound to ``endpoint`` (``tcp://127.0.0.1:*`` picks a free port: see :attr:`endpoint`)."""

    def __init__(self, endpoint: str) -> None:
        self._socket = zmq.Context.instance().socket(zmq.PUB)
        self._socket.setsockopt(zmq.SNDHWM, HWM)
        self._socket.setsockopt(zmq.LINGER, 0)
        try:
            self._socket.bind(endpoint)
        except zmq.ZMQError as exc:
            self._socket.close()
            raise MeniscopeError(endpoint, f"cannot bind the ZeroMQ publisher: {exc}") from None
        self.endpoint = self._socket.getsockopt_string(zmq.LAST_ENDPOINT)

    def send(self, message: str, topic: bytes = WINDOW_TOPIC) -> None:
        self._socket.send_multipart([topic, message.encode()], flags=zmq.NOBLOCK)

    def close(self) -> None:
        self._socket.close()
