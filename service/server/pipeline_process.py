"""The frame path in a process of its own, fed to the web process through a pipe.

One unauthenticated client polling the API used to take frames from the pipeline: both shared one interpreter
lock. Now the pipeline process (:func:`serve_pipeline`) runs the :class:`Engine`: supervisor, pipeline, fit
pool, ZeroMQ publisher, history writer and the window metrics. It sends the web process the WebSocket messages
and, ten times a second, a :class:`Report` (health, statistics, latest frame, metrics text); the web process
reads the history from SQLite itself. Whatever the web process does, or fails to do (a flood of requests,
SIGSTOP), costs the frame path nothing: the messages it does not read in time are dropped and counted, never
waited for.

:class:`PipelineProcess` is the web process's handle: it starts the pipeline process, passes settings changes
on, notices when it dies (not ready, with the reason) and starts it again after 1, 2, 4, ... s.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import queue
import signal
import threading
import time
from multiprocessing.connection import Connection, wait
from typing import Any

from service.errors import MeniscopeError
from service.pipeline.supervisor import Health
from service.server.engine import Engine, Report
from service.server.hub import Hub
from service.server.settings import ServiceSettings

log = logging.getLogger(__name__)

#: Seconds between two reports of the pipeline process.
REPORT_S = 0.1
#: A pipeline process that has not reported for this long (s) is stalled (hung, or stopped by a signal).
SILENT_S = 3.0
#: WebSocket messages waiting for the web process, at most (beyond: dropped and counted).
FANOUT_QUEUE = 1024
#: Seconds the pipeline process may take to open the history and bind ZeroMQ (imports included, on a busy PC).
START_S = 120.0
#: Seconds to wait for a ZeroMQ port held by the pipeline process of a web process that crashed.
PORT_WAIT_S = 20.0
#: Seconds it may take to stop (pipeline, fits in flight, publishers, history) before it is killed.
STOP_S = 30.0


class _Link:
    """One end of the pipe, shared by threads: a message at a time; a closed pipe makes sending a no-op."""

    def __init__(self, conn: Connection) -> None:
        self.conn, self._lock, self.broken = conn, threading.Lock(), False

    def send(self, message: tuple[Any, ...]) -> None:
        with self._lock:
            if self.broken:
                return
            try:
                self.conn.send(message)
            except (OSError, EOFError, ValueError):
                self.broken = True


class PipeFanout:
    """The WebSocket messages for the web process, sent by a thread of their own from a bounded queue: a web
    process that does not read makes that thread wait, and further messages are dropped (counted), while the
    thread that publishes windows never waits."""

    def __init__(self, link: _Link) -> None:
        self.link, self.clients, self.skipped = link, 0, 0
        self._queue: queue.Queue[str | None] = queue.Queue(FANOUT_QUEUE)
        self._thread = threading.Thread(target=self._run, name="meniscope-fanout", daemon=True)
        self._thread.start()

    def broadcast(self, message: str) -> None:
        try:
            self._queue.put_nowait(message)
        except queue.Full:
            self.skipped += 1

    def stop(self) -> None:
        try:
            self._queue.put(None, timeout=1.0)
        except queue.Full:
            return  # the web process reads nothing: what is queued stays unsent
        self._thread.join(1.0)

    def _run(self) -> None:
        while (message := self._queue.get()) is not None:
            self.link.send(("ws", message))


def serve_pipeline(settings: ServiceSettings, conn: Connection) -> None:
    """The pipeline process: run the engine for ``settings`` until told to stop (a message, SIGTERM, SIGINT, or
    the web process gone), then stop it in order."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    logging.basicConfig(level=logging.WARNING, format="meniscope serve (pipeline): %(levelname)s: %(message)s")
    link = _Link(conn)
    fanout = PipeFanout(link)
    try:
        engine = Engine(settings, fanout)
    except MeniscopeError as exc:
        link.send(("failed", str(exc)))
        return
    link.send(("started", engine.zmq.endpoint if engine.zmq is not None else None))
    engine.start()
    threading.Thread(
        target=_commands, args=(conn, engine, fanout, stop), name="meniscope-commands", daemon=True
    ).start()
    while not stop.wait(REPORT_S):
        link.send(("report", dataclasses.replace(engine.report(), websocket_skipped=fanout.skipped)))
    engine.stop()
    fanout.stop()
    link.send(("report", dataclasses.replace(engine.report(), websocket_skipped=fanout.skipped)))


def _commands(conn: Connection, engine: Engine, fanout: PipeFanout, stop: threading.Event) -> None:
    """What the web process asks: new settings, the number of WebSocket clients, a printer's ejection event, stop
    (also when it is gone)."""
    while True:
        try:
            kind, *args = conn.recv()
        except (EOFError, OSError):
            break
        if kind == "config":
            engine.reconfigure(args[0])
        elif kind == "clients":
            fanout.clients = args[0]
        elif kind == "ejection":
            engine.eject(*args)
        elif kind == "stop":
            break
    stop.set()


class PipelineProcess:
    """The web process's handle on the pipeline process: starts it, forwards settings, restarts it when it dies,
    and says what it last reported."""

    def __init__(self, settings: ServiceSettings, hub: Hub) -> None:
        self.settings, self.hub = settings, hub
        self.report: Report | None = None
        self.endpoint: str | None = None  # the ZeroMQ endpoint bound (a port picked once is kept across restarts)
        self.restarts = 0
        self._context = multiprocessing.get_context("spawn")  # a fresh interpreter: no threads or locks inherited
        self._process: Any = None
        self._link: _Link | None = None
        self._started = threading.Event()
        self._failure: str | None = None  # why the latest pipeline process did not start
        self._down: tuple[str, float] | None = None  # why the pipeline process is not running, and since when
        self._stopping = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="meniscope-pipeline-watch", daemon=True)

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def start(self) -> PipelineProcess:
        """Start the pipeline process and wait until it has opened the history and bound ZeroMQ (their errors
        stop the service, as a bad setting should); the model and the source it opens in its own time."""
        deadline = time.monotonic() + PORT_WAIT_S
        self._spawn(self.settings)
        # after a crash of the web process its pipeline process drains and stops in a few seconds: until then it
        # holds the ZeroMQ port
        while (
            self._wait_started()
            and self._failure is not None
            and "in use" in self._failure
            and time.monotonic() < deadline
        ):
            self._end()
            time.sleep(0.5)
            self._spawn(self.settings)
        if not self._started.is_set() or self._failure is not None:
            self._end()
            raise MeniscopeError(
                self.settings.data_dir,
                self._failure
                or "the pipeline process did not start: "
                f"exit code {self._process.exitcode} (its error is in the log above)",
            )
        self._watcher.start()
        return self

    def _wait_started(self) -> bool:
        """Until the pipeline process says it started or failed (True), or it died or took :data:`START_S` s."""
        deadline = time.monotonic() + START_S
        while not self._started.wait(0.2):
            if not self._process.is_alive() or time.monotonic() > deadline:
                return self._started.is_set()
        return True

    def _spawn(self, settings: ServiceSettings) -> None:
        self._started.clear()
        self._failure = None
        ours, theirs = self._context.Pipe()
        self._process = self._context.Process(target=serve_pipeline, args=(settings, theirs), name="meniscope-pipeline")
        self._process.start()
        theirs.close()
        self._link = _Link(ours)
        threading.Thread(target=self._receive, args=(ours,), name="meniscope-pipeline-read", daemon=True).start()

    def _receive(self, conn: Connection) -> None:
        """Everything one pipeline process sends, until it is gone."""
        while True:
            try:
                kind, *args = conn.recv()
            except (EOFError, OSError):
                break
            if kind == "ws":
                self.hub.broadcast(args[0])
            elif kind == "report":
                self.report = args[0]
            elif kind == "started":
                self.endpoint, self._down = args[0], None
                self._started.set()
            elif kind == "failed":
                self._failure = args[0]
                self._started.set()
        conn.close()

    def _watch(self) -> None:
        """Tell the pipeline process how many WebSocket clients there are; restart it when it dies."""
        attempts, clients = 0, -1
        while not self._stopping.is_set():
            process = self._process
            if not wait([process.sentinel], REPORT_S * 2):
                if self.hub.clients != clients and self._link is not None:
                    clients = self.hub.clients
                    self._link.send(("clients", clients))
                if self._down is None:
                    attempts = 0
                continue
            if self._stopping.is_set():
                break
            attempts += 1
            delay = min(2.0 ** (attempts - 1), self.settings.retry_max_s)
            how = self._failure or f"exit code {process.exitcode}"
            reason = f"the pipeline process ended ({how}); starting it again in {delay:g} s (attempt {attempts})"
            log.warning("%s", reason)
            self._down, clients = (reason, time.time()), -1  # its last report stays: counters, metrics
            if self._stopping.wait(delay):
                break
            self.restarts += 1
            settings = (
                self.settings
                if self.endpoint is None
                else self.settings.model_copy(update={"zmq_publish": self.endpoint})
            )
            self._spawn(settings)

    def health(self) -> Health:
        """The health the pipeline process reported; not ready while it is down or silent."""
        down, report = self._down, self.report
        if down is not None:
            return Health("retrying", down[0], down[1], self.restarts)
        if report is None:
            return Health("starting", "the pipeline process is starting", time.time(), 0)
        silent = time.monotonic() - report.taken
        if silent > SILENT_S:
            return Health(
                "stalled",
                f"the pipeline process has not reported for {silent:.1f} s",
                report.health.since,
                report.health.attempts,
                report.health.source,
            )
        return report.health

    def reconfigure(self, settings: ServiceSettings) -> None:
        self.settings = settings
        if self._link is not None:
            self._link.send(
                (
                    "config",
                    settings if self.endpoint is None else settings.model_copy(update={"zmq_publish": self.endpoint}),
                )
            )

    def eject(self, frame: int | None, time_s: float | None) -> bool:
        """Send one of the printer's ejection events (checked already) to the pipeline process, whose segmenter
        cuts at it; False when it is not running (down, restarting), when the event cannot reach a segmenter."""
        link = self._link
        if link is None or link.broken or self._down is not None or not self._started.is_set():
            return False
        link.send(("ejection", frame, time_s))
        return not link.broken

    def stop(self) -> None:
        """Ask the pipeline process to stop (it stops the pipeline, drains the publishers, closes ZeroMQ and the
        history, in that order) and wait for it; kill it if it does not stop in :data:`STOP_S` s."""
        self._stopping.set()
        if self._link is not None:
            self._link.send(("stop",))
        if self._watcher.is_alive():
            self._watcher.join(STOP_S)
        self._end()

    def _end(self) -> None:
        process = self._process
        if process is None:
            return
        process.join(STOP_S)
        if process.is_alive():
            log.warning("the pipeline process did not stop within %g s: killing it", STOP_S)
            process.kill()
            process.join(5.0)
