"""WebSocket fan-out: every client has its own bounded queue and sender task.

The publishing thread hands a message over with :meth:`Hub.broadcast` and returns at once. A client
whose queue is full loses its oldest message (counted), so a slow or stalled browser never slows the
pipeline or any other client; it sees the newest data when it catches up.
"""

from __future__ import annotations

import asyncio

from fastapi import WebSocket, WebSocketDisconnect


class Hub:
    """The connected WebSocket clients of one event loop, each lagging by at most ``queue_size`` messages."""

    def __init__(self, loop: asyncio.AbstractEventLoop, queue_size: int) -> None:
        self.loop, self.queue_size = loop, queue_size
        self._clients: set[asyncio.Queue[str]] = set()
        self.skipped = 0  # messages dropped for clients that lagged

    @property
    def clients(self) -> int:
        return len(self._clients)

    def broadcast(self, message: str) -> None:
        """Queue ``message`` for every client; callable from any thread, never blocks."""
        if self._clients and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._fan_out, message)

    def _fan_out(self, message: str) -> None:
        for q in self._clients:
            if q.full():
                q.get_nowait()
                self.skipped += 1
            q.put_nowait(message)

    async def serve(self, ws: WebSocket) -> None:
        """Send this client everything broadcast from now on, until it disconnects. One await per message: the
        receiver that notices the close cancels the sending task rather than racing it on every message (two
        futures and an ``asyncio.wait`` per message per client cost the frame path twice the interpreter time)."""
        await ws.accept()
        q: asyncio.Queue[str] = asyncio.Queue(self.queue_size)
        self._clients.add(q)
        sender = asyncio.current_task()
        assert sender is not None
        receiver = asyncio.ensure_future(self._drain(ws))  # notices the close; clients need not send

        def closed(_: asyncio.Future[None]) -> None:
            sender.cancel()

        receiver.add_done_callback(closed)
        try:
            while True:
                await ws.send_text(await q.get())
        except asyncio.CancelledError:
            if not receiver.done():
                raise  # cancelled from outside (the server stopping), not by the client's close
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass  # the client went away mid-send
        finally:
            self._clients.discard(q)
            receiver.remove_done_callback(closed)
            receiver.cancel()

    @staticmethod
    async def _drain(ws: WebSocket) -> None:
        try:
            while True:
                await ws.receive_text()
        except (WebSocketDisconnect, RuntimeError):
            return
