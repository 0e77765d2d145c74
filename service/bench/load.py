"""``meniscope bench load``: frames the real service loses to its web clients (issue 18's load harness).

Starts ``meniscope serve`` as ``bench live`` does (the demo at the camera's 19,000 frames/s, a fresh data
folder, free ports) and runs three phases of ``--seconds`` each on it: no clients (the baseline); ``--readers``
WebSocket clients reading everything plus ``--stalled`` that connect and never read; one client fetching the
largest history page (``/api/v1/windows?limit=1000``) back to back. For each phase: frames acquired and
dropped, windows published and left unfitted (from /metrics), what the clients got, and the load average.
The web side shares the machine with the frame path: on a loaded machine the figures say little; rerun on a
quiet one. Writes ``load.json`` and ``load.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from service.bench.live import ServeProcess
from service.errors import MeniscopeError

#: The counters each phase reads before and after.
COUNTERS = {
    "frames_acquired": "meniscope_frames_acquired_total",
    "frames_dropped": "meniscope_frames_dropped_total",
    "windows_skipped": "meniscope_windows_skipped_total",
}
#: The largest history page the API serves.
PAGE = "/api/v1/windows?limit=1000"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "load", help="frames the service loses to WebSocket readers and history readers", description=__doc__
    )
    p.add_argument("--seconds", type=float, default=30.0, help="length of each phase (default 30)")
    p.add_argument("--readers", type=int, default=90, help="WebSocket clients reading (default 90)")
    p.add_argument("--stalled", type=int, default=10, help="WebSocket clients that never read (default 10)")
    p.add_argument("--out", type=Path, default=Path("bench-load"), help="folder for the results")
    p.set_defaults(func=run)


def counters(service: ServeProcess) -> dict[str, float]:
    """:data:`COUNTERS` and the windows published (all statuses) from /metrics."""
    from prometheus_client.parser import text_string_to_metric_families

    values = dict.fromkeys([*COUNTERS, "windows_published"], 0.0)
    names = {v: k for k, v in COUNTERS.items()}
    # the web process yields the CPU to the frames (web_nice): under a flood of clients a scrape may wait
    for family in text_string_to_metric_families(service.get("/metrics", timeout=60.0)):
        for sample in family.samples:
            if sample.name in names:
                values[names[sample.name]] = sample.value
            elif sample.name == "meniscope_windows_total":
                values["windows_published"] += sample.value
    return values


class WebSocketCrowd:
    """``readers`` clients counting the messages they read and ``stalled`` ones that read nothing, on one thread."""

    def __init__(self, port: int, readers: int, stalled: int) -> None:
        self.port, self.readers, self.stalled = port, readers, stalled
        self.messages = 0
        self.connected = 0
        self._loop = asyncio.new_event_loop()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(self._main(),), daemon=True)
        self._thread.start()

    async def _main(self) -> None:
        from websockets.asyncio.client import connect

        self._stop = asyncio.Event()
        url = f"ws://127.0.0.1:{self.port}/ws"

        async def reader() -> None:
            async with connect(url, max_queue=64) as ws:
                self.connected += 1
                while not self._stop.is_set():
                    try:
                        await asyncio.wait_for(ws.recv(), 0.5)
                        self.messages += 1
                    except TimeoutError:
                        pass

        async def stalled() -> None:  # its library buffers a little, then TCP's buffers fill: the server must skip
            async with connect(url, max_queue=1):
                self.connected += 1
                await self._stop.wait()

        await asyncio.gather(
            *[reader() for _ in range(self.readers)], *[stalled() for _ in range(self.stalled)], return_exceptions=True
        )

    def stop(self) -> None:
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)


class PageReader:
    """One client fetching :data:`PAGE` back to back, counting pages and bytes."""

    def __init__(self, port: int) -> None:
        self.url, self.pages, self.bytes = f"http://127.0.0.1:{port}{PAGE}", 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            with urllib.request.urlopen(self.url, timeout=30) as response:
                self.bytes += len(response.read())
            self.pages += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(30)


def phase(service: ServeProcess, seconds: float, name: str, clients: object | None) -> dict:
    """The counters' growth over ``seconds`` with ``clients`` attached (they are stopped after)."""
    time.sleep(2.0)  # clients connected
    before, t0, load0 = counters(service), time.monotonic(), os.getloadavg()[0]
    got0 = dict(vars(clients)) if clients is not None else {}
    time.sleep(seconds)
    after, elapsed, load1 = counters(service), time.monotonic() - t0, os.getloadavg()[0]
    got = {k: v - got0[k] for k, v in vars(clients).items() if k in ("messages", "pages", "bytes")} if clients else {}
    if clients is not None:
        clients.stop()  # type: ignore[attr-defined]
    grown = {k: after[k] - before[k] for k in after}
    return {
        "phase": name,
        "seconds": elapsed,
        "load_average": [load0, load1],
        **grown,
        "dropped_share": grown["frames_dropped"] / max(grown["frames_acquired"], 1.0),
        "clients": got,
    }


def measure(seconds: float, readers: int, stalled: int) -> list[dict]:
    with tempfile.TemporaryDirectory(prefix="meniscope-load-") as tmp:
        service = ServeProcess(Path(tmp))
        try:
            service.wait_ready()
            time.sleep(3.0)  # fit workers warm, history filling
            phases = [phase(service, seconds, "no clients", None)]
            crowd = WebSocketCrowd(service.port, readers, stalled)
            phases.append(phase(service, seconds, f"{readers} WebSocket readers + {stalled} stalled", crowd))
            phases[-1]["clients"]["connected"] = crowd.connected
            phases.append(phase(service, seconds, f"one client reading {PAGE} back to back", PageReader(service.port)))
        finally:
            service.stop()
    return phases


def markdown(phases: list[dict]) -> str:
    lines = [
        f"Load benchmark: `meniscope serve` on the demo at 19,000 frames/s, {os.cpu_count()} CPUs.",
        "",
        "| phase | s | frames acquired | frames dropped | windows published | windows unfitted | clients got "
        "| load average |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p in phases:
        got = ", ".join(f"{k} {v:g}" for k, v in p["clients"].items()) or "-"
        lines.append(
            f"| {p['phase']} | {p['seconds']:.0f} | {p['frames_acquired']:.0f} | {p['frames_dropped']:.0f} "
            f"({p['dropped_share']:.2%}) | {p['windows_published']:.0f} | {p['windows_skipped']:.0f} | {got} | "
            f"{p['load_average'][0]:.1f} -> {p['load_average'][1]:.1f} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.seconds <= 0 or args.readers < 0 or args.stalled < 0:
        raise MeniscopeError("bench load", "--seconds must be positive and --readers, --stalled not negative")
    args.out.mkdir(parents=True, exist_ok=True)
    phases = measure(args.seconds, args.readers, args.stalled)
    (args.out / "load.json").write_text(json.dumps({"phases": phases}, indent=1))
    table = markdown(phases)
    (args.out / "load.md").write_text(table)
    print(table)
    return 0
