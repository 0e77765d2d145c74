"""Frames over ZeroMQ, for acquisition in another process or machine: the receiving source and the sender.

PUB/SUB rather than PUSH/PULL: a PUB socket drops messages once a subscriber's queue reaches the
high-water mark instead of blocking, so a slow or stalled monitor never holds up acquisition, and a
small high-water mark keeps what it receives fresh; what it missed shows as a gap in the frame
indices. The sender is an XPUB socket (a PUB that also sees subscriptions), so a replay can wait for
its first subscriber. Wire format: :mod:`service.sources.zmq_format`, docs/zmq-frames.md.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any
from urllib.parse import SplitResult

import numpy as np
import zmq
from pydantic import Field

from service.errors import MeniscopeError
from service.sources import zmq_format
from service.sources.base import FrameBatch, FrameSource, SourceOptions, StreamFormat, parse_options

#: Messages queued per peer before PUB drops (sender) or the receiver stops taking more.
DEFAULT_HWM = 4


class ZmqOptions(SourceOptions):
    open_timeout: float = Field(10.0, gt=0, allow_inf_nan=False, description="longest wait for the first frames, s")
    hwm: int = Field(DEFAULT_HWM, ge=1, description="receive high-water mark, messages")


class ZmqSource(FrameSource):
    """Subscribes to a frame publisher (``zmq+tcp://host:port``); the first message fixes the stream's format.

    The stream ends at the sender's end message, or when indices start again from below the last one
    (the sender restarted; open the source again to follow the new stream).
    """

    kind = "zmq"

    def __init__(
        self,
        endpoint: str,
        *,
        timeout: float = 0.1,
        open_timeout: float = 10.0,
        hwm: int = DEFAULT_HWM,
        uri: str | None = None,
    ) -> None:
        super().__init__(uri or endpoint, timeout)
        self.endpoint, self.open_timeout, self.hwm = endpoint, open_timeout, hwm
        self._socket: zmq.Socket | None = None
        self._pending: FrameBatch | None = None
        self._ended = False
        self._sequence = self._last_received = 0
        self._lost_messages = 0

    @classmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> ZmqSource:
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None or parts.path not in ("", "/"):
            raise MeniscopeError(uri, "a ZeroMQ source is zmq+tcp://host:port, e.g. zmq+tcp://127.0.0.1:5557")
        opts = parse_options(ZmqOptions, uri, options)
        host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
        return cls(f"tcp://{host}:{port}", timeout=opts.timeout, open_timeout=opts.open_timeout, hwm=opts.hwm, uri=uri)

    def _open(self) -> StreamFormat:
        sock = zmq.Context.instance().socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, self.hwm)
        sock.setsockopt(zmq.SUBSCRIBE, b"")
        try:
            sock.connect(self.endpoint)
            if not sock.poll(int(self.open_timeout * 1000)):
                raise MeniscopeError(
                    self.uri, f"no frames within {self.open_timeout:g} s: is a sender publishing there?"
                )
            first = self._decode(sock.recv_multipart(copy=False))
            if first.batch is None or first.format is None:
                raise MeniscopeError(self.uri, "the sender ended its stream before sending any frame")
        except BaseException:
            sock.close()
            raise
        self._socket, self._pending, self._ended = sock, first.batch, False
        self._sequence, self._last_received, self._lost_messages = first.sequence, int(first.batch.indices[-1]), 0
        return first.format

    def _read(self, max_frames: int) -> FrameBatch | None:
        taken: list[FrameBatch] = []
        count = 0
        deadline = time.monotonic() + self.timeout
        while count < max_frames:
            if self._pending is not None:
                batch, self._pending = self._pending, None
            else:
                batch = self._receive(deadline)
            if batch is None:
                break
            if len(batch) > max_frames - count:
                room = max_frames - count
                batch, self._pending = batch.select(slice(room)), batch.select(slice(room, None))
            taken.append(batch)
            count += len(batch)
        if not taken:
            return None if self._ended else self.empty_batch()
        return FrameBatch.concatenate(taken)

    def _receive(self, deadline: float) -> FrameBatch | None:
        """The next message's frames, or None when the stream ended or nothing came before ``deadline``."""
        assert self._socket is not None
        if self._ended or not self._socket.poll(max(0, int((deadline - time.monotonic()) * 1000))):
            return None
        message = self._decode(self._socket.recv_multipart(copy=False))
        if message.batch is None:
            self._ended = True
            return None
        if message.format != self.format:
            raise MeniscopeError(self.uri, f"the sender changed the frame format mid-stream: {message.format}")
        if message.batch.indices[0] <= self._last_received:
            self._ended = True  # the sender restarted: its indices begin again
            return None
        self._lost_messages += max(0, message.sequence - self._sequence - 1)
        self._sequence, self._last_received = message.sequence, int(message.batch.indices[-1])
        return message.batch

    def _decode(self, frames: list[zmq.Frame]) -> zmq_format.Message:
        try:
            return zmq_format.decode([f.buffer for f in frames])
        except ValueError as exc:
            raise MeniscopeError(self.uri, f"bad message: {exc}") from None

    def _close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket, self._pending = None, None

    def _details(self) -> dict[str, Any]:
        return {"endpoint": self.endpoint, "hwm": self.hwm, "lost_messages": self._lost_messages, "ended": self._ended}


class FrameSender:
    """Publishes frame batches of one stream on an XPUB socket; never blocks on a slow subscriber.

    Batches must not be modified after :meth:`send`: their pixels go out without a copy.
    """

    def __init__(self, endpoint: str, fmt: StreamFormat, *, hwm: int = DEFAULT_HWM, bind: bool = True) -> None:
        self.endpoint, self.format = endpoint, fmt
        self.sequence = 0
        self._socket = zmq.Context.instance().socket(zmq.XPUB)
        self._socket.setsockopt(zmq.SNDHWM, hwm)
        self._socket.setsockopt(zmq.LINGER, 1000)  # let queued frames and the end message go out on close
        try:
            (self._socket.bind if bind else self._socket.connect)(endpoint)
        except zmq.ZMQError as exc:
            self._socket.close(linger=0)
            raise MeniscopeError(endpoint, f"cannot {'bind' if bind else 'connect'}: {exc}") from None
        if bind:  # a wildcard port ("tcp://127.0.0.1:*") resolves to the one the system chose
            self.endpoint = self._socket.getsockopt_string(zmq.LAST_ENDPOINT)

    def wait_for_subscriber(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a subscriber to join; True when one did."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0 and self._socket.poll(int(left * 1000)):
            if self._socket.recv()[:1] == b"\x01":  # a subscription (b"\x00" is an unsubscription)
                return True
        return False

    def send(self, batch: FrameBatch) -> None:
        """Publish a batch, one message per run of consecutive indices; dropped for subscribers that lag."""
        runs = np.flatnonzero(np.diff(batch.indices) != 1) + 1
        for lo, hi in zip([0, *runs], [*runs, len(batch)]):
            if hi > lo:
                part = batch.select(slice(lo, hi))
                self._socket.send_multipart(zmq_format.encode(part, self.format, self.sequence), copy=False)
                self.sequence += 1

    def close(self, end_timeout: float = 1.0) -> None:
        """Send the end message (waiting up to ``end_timeout`` s for room in lagging queues), then close."""
        if self._socket.closed:
            return
        self._socket.setsockopt(zmq.XPUB_NODROP, 1)
        self._socket.setsockopt(zmq.SNDTIMEO, int(end_timeout * 1000))
        try:
            self._socket.send_multipart(zmq_format.encode_end(self.sequence))
        except zmq.Again:
            pass  # a subscriber that stopped reading misses the end; it sees a stream that went quiet
        self._socket.close()

    def __enter__(self) -> FrameSender:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
