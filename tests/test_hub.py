"""The WebSocket hub: every client gets every message in order, one that goes away leaves at once, and a
server that stops cancels the senders (none swallowed)."""

from __future__ import annotations

import asyncio

import pytest
from fastapi import WebSocketDisconnect

from service.server.hub import Hub


class FakeClient:
    """A WebSocket that records what it is sent and disconnects when told."""

    def __init__(self) -> None:
        self.sent: list[str] = []
        self.gone = asyncio.Event()

    async def accept(self) -> None:
        pass

    async def send_text(self, message: str) -> None:
        self.sent.append(message)

    async def receive_text(self) -> str:
        await self.gone.wait()
        raise WebSocketDisconnect()


def test_clients_get_every_message_in_order_and_leave_when_they_close() -> None:
    async def scenario() -> None:
        hub = Hub(asyncio.get_running_loop(), 64)
        clients = [FakeClient() for _ in range(5)]
        tasks = [asyncio.ensure_future(hub.serve(c)) for c in clients]  # type: ignore[arg-type]
        await asyncio.sleep(0.01)
        assert hub.clients == 5
        for k in range(50):
            hub._fan_out(str(k))
            await asyncio.sleep(0)
        await asyncio.sleep(0.01)
        assert all(c.sent == [str(k) for k in range(50)] for c in clients)
        clients[0].gone.set()
        await asyncio.wait_for(tasks[0], 1)  # returns, not cancelled
        assert hub.clients == 4 and not tasks[0].cancelled()
        for task in tasks[1:]:
            task.cancel()  # the server stopping
        results = await asyncio.gather(*tasks[1:], return_exceptions=True)
        assert all(isinstance(r, asyncio.CancelledError) for r in results) and hub.clients == 0

    asyncio.run(scenario())


def test_a_client_that_lags_loses_its_oldest_messages_only() -> None:
    async def scenario() -> None:
        hub = Hub(asyncio.get_running_loop(), 4)
        lagging, reading = FakeClient(), FakeClient()
        tasks = [asyncio.ensure_future(hub.serve(c)) for c in (lagging, reading)]  # type: ignore[arg-type]
        await asyncio.sleep(0.01)
        for k in range(10):
            hub._fan_out(str(k))  # no await in between: neither sender runs, both queues overflow
        await asyncio.sleep(0.01)
        assert lagging.sent == reading.sent == ["6", "7", "8", "9"] and hub.skipped == 12
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(scenario())


@pytest.mark.parametrize("size", [1, 64])
def test_queue_sizes_are_honoured(size: int) -> None:
    async def scenario() -> None:
        hub = Hub(asyncio.get_running_loop(), size)
        client = FakeClient()
        task = asyncio.ensure_future(hub.serve(client))  # type: ignore[arg-type]
        await asyncio.sleep(0.01)
        for k in range(100):
            hub._fan_out(str(k))
        await asyncio.sleep(0.01)
        assert client.sent == [str(k) for k in range(100 - size, 100)]
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    asyncio.run(scenario())
