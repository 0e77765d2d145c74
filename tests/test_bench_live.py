"""`meniscope bench live`: the real service started, clients attached, its own latency histogram read back."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from service.bench.live import measure, register
from service.errors import MeniscopeError


def test_a_short_run_reads_the_windows_the_service_published_and_its_clients_received() -> None:
    r = measure(2.0)
    assert r["windows_published"] > 0
    assert r["received"]["websocket"] > 0 and r["received"]["zeromq"] > 0  # real sockets, real messages
    shares = [r["within_ms"][b] for b in sorted(r["within_ms"], key=float)]
    assert shares == sorted(shares) and 0.0 <= shares[0] and shares[-1] <= 1.0  # cumulative shares of the windows
    assert r["frames_dropped"] >= 0 and r["windows_skipped"] >= 0


def test_no_runs_is_one_error_naming_the_options(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["live", "--runs", "0", "--out", str(tmp_path)])
    with pytest.raises(MeniscopeError, match="--runs"):
        args.func(args)
