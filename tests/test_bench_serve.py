"""`meniscope bench serve --variants`: the service settings compared side by side, as the settings parse them; with
`--refine`, the lane off and on."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pytest

from service.bench import serve
from service.bench.serve import markdown, parse_variants, register
from service.errors import MeniscopeError


def test_variants_are_groups_of_settings_and_an_empty_group_is_the_defaults() -> None:
    assert parse_variants("") == [("", {})]
    assert parse_variants("batch_ms=1000, read_frames=128;;batch_ms=2") == [
        ("batch_ms=1000,read_frames=128", {"batch_ms": "1000", "read_frames": "128"}),
        ("", {}),
        ("batch_ms=2", {"batch_ms": "2"}),
    ]


def test_a_variant_that_is_not_key_value_pairs_is_one_error_naming_the_option() -> None:
    with pytest.raises(MeniscopeError, match="--variants.*KEY=VALUE"):
        parse_variants("batch_ms=2;fast")


def test_a_variant_the_settings_refuse_is_one_error_naming_it_before_anything_runs(
    demo_cine: Path, tmp_path: Path
) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["serve", "--source", str(demo_cine), "--out", str(tmp_path), "--variants", "batch_ms=-1"])
    with pytest.raises(MeniscopeError, match="--variants.*'batch_ms=-1'"):
        args.func(args)


def test_with_the_lane_the_tables_say_which_runs_had_it_and_what_it_refined() -> None:
    stages = {f"{k}_ms_p{q}": 1.0 for k in ("to_fit", "handoff", "fit", "publish") for q in (50, 99)}
    run = dict(
        batch=512, threads=1, variant="", run="x1", max_modes=2, frames_per_s_in=19000.0, frames_per_s_inferred=19000.0,
        dropped_fraction=0.0, windows_closed=100, windows_published=100, windows_skipped=0,
        publish_latency_ms_p50=5.0, publish_latency_ms_p99=9.0, on_time_fraction=1.0, load_average=[1.0, 1.0], **stages,
    )  # fmt: skip
    lane = dict(
        run, refine=True, windows_refined=3, refined_per_minute=1.5, refine_skipped=197.0,
        refine_latency_s_p50=30.0, refine_latency_s_p90=55.5, refine_wall_s_p50=28.0,
    )  # fmt: skip
    results = dict(
        source="demo.cine", seconds=120, fit_workers=1, fit_nice=10, runs=[dict(run, refine=False), lane],
        stage_costs={"windows_fitted": 1, "fit_ms_per_window": 3.0, "read_128": 6.0},
    )  # fmt: skip
    text = markdown(results)
    assert "| 512 x 1 | defaults | off | x1 |" in text and "| 512 x 1 | defaults | on | x1 |" in text
    assert "| 512 x 1 | defaults | x1 | 3 | 1.5 | 197 | 30.0 / 55.5 | 28.0 |" in text


class _CatchingUp:
    """A pipeline's counters that ran behind at the start: frames come at 3x the camera's rate for ``burst`` s,
    then at its rate (what a drift-free replay does after a stall)."""

    def __init__(self, rate: float, burst: float) -> None:
        self.t0, self.rate, self.burst = time.monotonic(), rate, burst

    @property
    def frames_acquired(self) -> int:
        t = time.monotonic() - self.t0
        return int(self.rate * (3 * min(t, self.burst) + max(t - self.burst, 0.0)))

    frames_inferred = frames_acquired


def test_a_run_is_counted_from_when_the_catch_up_after_its_start_is_over(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serve, "SETTLE_STEP_S", 0.1)
    assert serve._settle(_CatchingUp(19_000, 0.6), 19_000) >= 0.6  # not while frames come faster than they are made
    assert serve._settle(_CatchingUp(19_000, 0.0), 19_000) < 0.5  # at once when on schedule
    assert serve._settle(_CatchingUp(5_000, 0.0), 19_000) < 0.5  # and when slower than the camera
