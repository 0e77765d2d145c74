"""``meniscope bench live``: the publish latency of the real service, as a user runs it, with clients attached.

``bench serve`` drives the pipeline and publishers in-process and leaves HTTP out; this starts
``meniscope serve`` itself (a fresh data folder, the demo at the camera's rate, free ports), attaches
what a deployment attaches (a WebSocket client, as the dashboard, and a ZeroMQ subscriber, as the
printer's controller) and reads the service's own ``meniscope_window_publish_latency_seconds``
histogram from ``/metrics`` before and after ``--seconds``: the share of windows published within
each of its bounds (the p99 lies under the first bound holding 99 %), the windows each client
received meanwhile, and frames dropped and windows left unfitted meanwhile. Writes ``live.json`` and
``live.md`` to ``--out`` and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

from service.bench.results import write_results
from service.errors import MeniscopeError

LATENCY = "meniscope_window_publish_latency_seconds"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "live", help="the real service's publish latency with a WebSocket and a ZeroMQ client", description=__doc__
    )
    p.add_argument("--seconds", type=float, default=30.0, help="length of each run (default 30)")
    p.add_argument("--runs", type=int, default=3, help="runs, each a fresh service (default 3)")
    p.add_argument("--out", type=Path, default=Path("bench-live"), help="folder for the results")
    p.set_defaults(func=run)


def free_port() -> int:
    """A TCP port nothing listens on now (the OS's pick)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServeProcess:
    """``meniscope serve`` in a child process on free ports with a data folder of its own, until :meth:`stop`."""

    def __init__(self, data_dir: Path, extra_env: dict[str, str] | None = None, log: Path | None = None) -> None:
        """``extra_env``: further MENISCOPE_ settings (source, ...); ``log``: its output, appended (default
        ``DATA_DIR/serve.log``; bench faults keeps it out of a data folder it makes unwritable)."""
        self.port, self.zmq_port = free_port(), free_port()
        env = dict(
            os.environ,
            MENISCOPE_DATA_DIR=str(data_dir),
            MENISCOPE_ZMQ_PUBLISH=f"tcp://127.0.0.1:{self.zmq_port}",
            **(extra_env or {}),
        )
        self._log = (log or data_dir / "serve.log").open("a+")
        self._process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port)],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )

    def get(self, path: str, timeout: float = 5.0) -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}{path}", timeout=timeout) as response:
            return response.read().decode()

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Until /readyz says ready; a service that exits or stays unready is one error with its last output."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise MeniscopeError("meniscope serve", f"exited with {self._process.returncode}: {self._tail()}")
            try:
                if json.loads(self.get("/readyz")).get("ready"):
                    return
            except (urllib.error.URLError, OSError, ValueError):
                pass  # not answering yet, or 503 while it opens the model and the source
            time.sleep(0.5)
        raise MeniscopeError("meniscope serve", f"not ready after {timeout:g} s: {self._tail()}")

    def _tail(self) -> str:
        self._log.seek(0)
        lines = self._log.read().strip().splitlines()
        return lines[-1] if lines else "no output"

    def kill(self) -> None:
        """SIGKILL, as a crash or the OOM killer ends it: no shutdown of any kind."""
        self._process.kill()
        self._process.wait()
        self._log.close()

    @property
    def alive(self) -> bool:
        return self._process.poll() is None

    def stop(self) -> None:
        self._process.terminate()
        try:
            self._process.wait(20)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._log.close()


class Clients:
    """A WebSocket client and a ZeroMQ subscriber of ``service``, counting the window messages each receives."""

    def __init__(self, service: ServeProcess) -> None:
        self.received = {"websocket": 0, "zeromq": 0}
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=f, args=(service,), daemon=True) for f in (self._ws, self._zmq)]
        for t in self._threads:
            t.start()

    def _ws(self, service: ServeProcess) -> None:
        from websockets.sync.client import connect

        with connect(f"ws://127.0.0.1:{service.port}/ws") as ws:
            while not self._stop.is_set():
                try:
                    if json.loads(ws.recv(timeout=0.5)).get("type") == "window":
                        self.received["websocket"] += 1
                except TimeoutError:
                    pass

    def _zmq(self, service: ServeProcess) -> None:
        subscribe(service.zmq_port, self._stop, lambda parts: self.received.update(zeromq=self.received["zeromq"] + 1))

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(5)


def subscribe(port: int, stop: threading.Event, on_message: Callable[[list[bytes]], None]) -> None:
    """Every message the service's ZeroMQ publisher on ``port`` sends, to ``on_message``, until ``stop`` is set."""
    import zmq

    sub = zmq.Context.instance().socket(zmq.SUB)
    sub.setsockopt(zmq.RCVTIMEO, 500)
    sub.connect(f"tcp://127.0.0.1:{port}")
    sub.subscribe(b"")
    try:
        while not stop.is_set():
            try:
                on_message(sub.recv_multipart())
            except zmq.Again:
                pass
    finally:
        sub.close(linger=0)


#: The counters read beside the histogram.
COUNTERS = ("meniscope_frames_dropped_total", "meniscope_windows_skipped_total")


def scrape(service: ServeProcess) -> tuple[dict[str, float], dict[str, float]]:
    """From /metrics (parsed by prometheus_client's own parser): the latency histogram's cumulative bucket
    counts by bound (its ``le`` label, s, and "+Inf"), and :data:`COUNTERS` so far."""
    from prometheus_client.parser import text_string_to_metric_families

    buckets: dict[str, float] = {}
    counters: dict[str, float] = {}
    for family in text_string_to_metric_families(service.get("/metrics")):
        for sample in family.samples:
            if sample.name == f"{LATENCY}_bucket":
                buckets[sample.labels["le"]] = sample.value
            elif sample.name in COUNTERS:
                counters[sample.name] = sample.value
    return buckets, counters


def measure(seconds: float) -> dict:
    """One run: a fresh service, clients attached, the histogram's growth over ``seconds``."""
    with tempfile.TemporaryDirectory(prefix="meniscope-live-") as tmp:
        service = ServeProcess(Path(tmp))
        try:
            service.wait_ready()
            clients = Clients(service)
            time.sleep(3.0)  # clients connected, fit workers warm
            before, t0, load0 = scrape(service), time.monotonic(), os.getloadavg()[0]
            received0 = dict(clients.received)
            time.sleep(seconds)
            after, elapsed, load1 = scrape(service), time.monotonic() - t0, os.getloadavg()[0]
            received = {k: v - received0[k] for k, v in clients.received.items()}
            clients.stop()
        finally:
            service.stop()
    grown = {k: after[0][k] - before[0].get(k, 0.0) for k in after[0]}
    published = grown.pop("+Inf")
    bounds = sorted((float(k), v) for k, v in grown.items())
    within = {f"{b * 1e3:g}": v / max(published, 1) for b, v in bounds}
    p99_under = next((f"{b * 1e3:g}" for b, v in bounds if v >= 0.99 * published), None)
    return {
        "seconds": elapsed,
        "load_average": [load0, load1],
        "windows_published": published,
        "received": received,
        "within_ms": within,
        "p99_under_ms": p99_under,
        **{
            key: after[1].get(name, 0.0) - before[1].get(name, 0.0)
            for key, name in zip(("frames_dropped", "windows_skipped"), COUNTERS)
        },
    }


def markdown(runs: list[dict]) -> str:
    shown = ("2.5", "5", "10", "25")
    lines = [
        f"Live service benchmark: `meniscope serve` on the demo, a WebSocket and a ZeroMQ client attached, "
        f"{os.cpu_count()} CPUs.",
        "",
        "| run | windows published | received by WebSocket / ZeroMQ | "
        + " | ".join(f"within {b} ms" for b in shown)
        + " | p99 under (ms) | frames dropped | windows unfitted "
        "| load average |",
        "|" + "---|" * (8 + len(shown)),
    ]
    for k, r in enumerate(runs, 1):
        lines.append(
            f"| {k} | {r['windows_published']:.0f} | {r['received']['websocket']} / {r['received']['zeromq']} | "
            + " | ".join(f"{r['within_ms'].get(b, 0.0):.2%}" for b in shown)
            + f" | {r['p99_under_ms'] or '-'} | {r['frames_dropped']:.0f} | {r['windows_skipped']:.0f} | "
            f"{r['load_average'][0]:.1f} -> {r['load_average'][1]:.1f} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.runs < 1 or args.seconds <= 0:
        raise MeniscopeError(
            "--runs/--seconds", f"need at least one run of some seconds, got {args.runs} x {args.seconds}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for k in range(args.runs):
        print(f"bench live: run {k + 1} of {args.runs}, {args.seconds:g} s ...", flush=True)
        runs.append(measure(args.seconds))
    write_results(args.out / "live.json", {"runs": runs}, markdown(runs))
    return 0
