"""``meniscope bench faults``: the real service through the faults of issue 18, with recovery times.

Each fault runs against ``meniscope serve`` in a child process (as ``bench live`` starts it) while a
ZeroMQ subscriber records every window id published, and /readyz is polled every 0.1 s:

- a replayed recording truncated (what ``cp new.cine rec.cine`` does first), then restored; replaced by
  another recording (renamed over it); deleted, then restored;
- the ZeroMQ frame sender (``meniscope publish-frames``) killed with SIGKILL, then started again;
- the data folder unwritable for ``--unwritable-s`` seconds (root only: the folder is a small tmpfs filled
  to the last byte, a full disk; a read-only remount is refused while SQLite holds its files open);
- the service itself killed with SIGKILL and started again on the same data folder.

For each: whether the service stayed up, how soon readiness dropped and came back (s), and for the
last two the windows published on ZeroMQ that the history lacks afterwards. Writes ``faults.json`` and
``faults.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
from collections.abc import Callable
from pathlib import Path

from service.bench.live import ServeProcess, free_port, subscribe
from service.errors import MeniscopeError
from service.sources.replay import replay_uri


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "faults", help="the service through file, sender, disk and crash faults", description=__doc__
    )
    p.add_argument("--unwritable-s", type=float, default=20.0, help="how long the data folder is full (default 20)")
    p.add_argument("--out", type=Path, default=Path("bench-faults"), help="folder for the results")
    p.set_defaults(func=run)


def ready(service: ServeProcess) -> bool | None:
    """/readyz: True or False, None when the service does not answer."""
    try:
        return bool(json.loads(service.get("/readyz")).get("ready"))
    except urllib.error.HTTPError as err:
        return False if err.code == 503 else None
    except (OSError, ValueError):
        return None


def until(predicate: Callable[[], bool], timeout: float) -> float | None:
    """Seconds until ``predicate()`` held (polled every 0.1 s), None if it did not within ``timeout``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if predicate():
            return time.monotonic() - t0
        time.sleep(0.1)
    return None


class WindowIds:
    """A ZeroMQ subscriber of ``service`` recording the id of every window published."""

    def __init__(self, zmq_port: int) -> None:
        self.ids: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=subscribe, args=(zmq_port, self._stop, self._record), daemon=True)
        self._thread.start()

    def _record(self, parts: list[bytes]) -> None:
        self.ids.add(json.loads(parts[1])["id"])

    def stop(self) -> set[int]:
        self._stop.set()
        self._thread.join(5)
        return self.ids


def stored_ids(service: ServeProcess) -> set[int]:
    """Every window id in the service's history (paged through REST)."""
    ids: set[int] = set()
    since = 0
    while True:
        page = json.loads(service.get(f"/api/v1/windows?since={since}&limit=1000"))
        if not page["windows"]:
            return ids
        ids.update(w["id"] for w in page["windows"])
        since = page["last_id"]


def fault(
    service: ServeProcess,
    name: str,
    apply: Callable[[], None],
    restore: Callable[[], None] | None,
    timeout: float = 60.0,
) -> dict:
    """Apply a fault, time readiness dropping, restore (if anything), time readiness coming back."""
    apply()
    dropped = until(lambda: ready(service) is False, 15.0)
    if restore is not None:
        restore()
    back = until(lambda: ready(service) is True, timeout)
    return {"fault": name, "service_up": service.alive, "not_ready_after_s": dropped, "ready_again_after_s": back}


def replay_faults(tmp: Path, demo: Path) -> list[dict]:
    recordings = tmp / "recordings"
    recordings.mkdir()
    rec = recordings / "rec.cine"
    shutil.copy(demo, rec)
    service = ServeProcess(
        tmp / "data-replay",
        {"MENISCOPE_SOURCE": replay_uri(rec, speed=1, loop=1), "MENISCOPE_RECORDINGS_DIR": str(recordings)},
        tmp / "replay.log",
    )
    try:
        service.wait_ready()
        restore = lambda: shutil.copy(demo, rec)
        results = [
            fault(
                service, "replayed file truncated to 1000 bytes, then restored", lambda: os.truncate(rec, 1000), restore
            )
        ]
        other = recordings / "other.cine"
        shutil.copy(demo, other)
        results.append(
            fault(service, "replayed file replaced (another file renamed over it)", lambda: other.replace(rec), None)
        )
        results.append(fault(service, "replayed file deleted, then restored", rec.unlink, restore))
    finally:
        service.stop()
    return results


def sender_fault(tmp: Path, demo: Path) -> dict:
    port = free_port()
    sender_cmd = [
        sys.executable,
        "-m",
        "service.cli",
        "publish-frames",
        str(demo),
        "--bind",
        f"tcp://127.0.0.1:{port}",
        "--speed",
        "1",
        "--loop",
    ]
    sender = subprocess.Popen(sender_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    service = ServeProcess(tmp / "data-zmq", {"MENISCOPE_SOURCE": f"zmq+tcp://127.0.0.1:{port}"}, tmp / "zmq.log")
    try:
        service.wait_ready()
        restarted: list[subprocess.Popen] = []
        result = fault(
            service,
            "ZeroMQ frame sender killed (SIGKILL), then started again",
            sender.kill,
            lambda: restarted.append(
                subprocess.Popen(sender_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            ),
        )
    finally:
        service.stop()
        for proc in [sender, *restarted]:
            proc.kill()
            proc.wait()
    return result


def unwritable_fault(tmp: Path, seconds: float) -> dict:
    name = f"data folder full (unwritable) for {seconds:g} s"
    if os.geteuid() != 0:
        return {"fault": name, "skipped": "needs root (a tmpfs of its own to fill)"}
    data = tmp / "data-full"
    data.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m", "meniscope-bench", str(data)], check=True)
    try:
        service = ServeProcess(data, log=tmp / "full.log")
        ids = WindowIds(service.zmq_port)
        try:
            service.wait_ready()
            time.sleep(5.0)
            ballast = data / "ballast"

            def fill() -> None:
                with open(ballast, "wb") as f:
                    try:
                        while True:
                            f.write(bytes(1 << 20))
                    except OSError:
                        pass

            result = fault(service, name, fill, lambda: (time.sleep(seconds), ballast.unlink()))
            time.sleep(5.0)
            published = ids.stop()
            result["windows_lost_from_history"] = len(published - stored_ids(service))
            result["windows_published"] = len(published)
        finally:
            service.stop()
    finally:
        subprocess.run(["umount", "-l", str(data)], check=False)
    return result


def crash_fault(tmp: Path) -> dict:
    data = tmp / "data-crash"
    service = ServeProcess(data, log=tmp / "crash.log")
    ids = WindowIds(service.zmq_port)
    service.wait_ready()
    time.sleep(5.0)
    service.kill()
    published = ids.stop()
    t0 = time.monotonic()
    service = ServeProcess(data, log=tmp / "crash.log")
    try:
        service.wait_ready()
        back = time.monotonic() - t0
        lost = published - stored_ids(service)
    finally:
        service.stop()
    return {
        "fault": "meniscope serve killed (SIGKILL), then started again",
        "service_up": True,
        "ready_again_after_s": back,
        "windows_published": len(published),
        "windows_lost_from_history": len(lost),
    }


def measure(unwritable_s: float) -> list[dict]:
    from service.pipeline.demo import demo_recording

    with tempfile.TemporaryDirectory(prefix="meniscope-faults-") as folder:
        tmp = Path(folder)
        demo = demo_recording(tmp / "demo-source")
        results = replay_faults(tmp, demo)
        results.append(sender_fault(tmp, demo))
        results.append(unwritable_fault(tmp, unwritable_s))
        results.append(crash_fault(tmp))
    return results


def markdown(results: list[dict]) -> str:
    def s(value: float | None) -> str:
        return "-" if value is None else f"{value:.1f}"

    lines = [
        f"Fault benchmark: `meniscope serve`, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the end.",
        "",
        "| fault | service up | not ready after (s) | ready again after (s) | windows published / lost from history |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        if "skipped" in r:
            lines.append(f"| {r['fault']} | skipped: {r['skipped']} | | | |")
            continue
        history = f"{r['windows_published']} / {r['windows_lost_from_history']}" if "windows_published" in r else "-"
        lines.append(
            f"| {r['fault']} | {'yes' if r['service_up'] else 'NO'} | {s(r.get('not_ready_after_s'))} | "
            f"{s(r.get('ready_again_after_s'))} | {history} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.unwritable_s <= 0:
        raise MeniscopeError("--unwritable-s", "must be positive")
    args.out.mkdir(parents=True, exist_ok=True)
    results = measure(args.unwritable_s)
    (args.out / "faults.json").write_text(json.dumps({"faults": results}, indent=1))
    table = markdown(results)
    (args.out / "faults.md").write_text(table)
    print(table)
    return 0
