"""The analysis PNG colours each window's fit by its status, so that a glance finds the bad ones: red only for failure."""

from __future__ import annotations

from pathlib import Path

import matplotlib.colors as mcolors
import matplotlib.image as mimage
import numpy as np

from service.analysis.plot import STATUS_COLOURS, plot_report
from service.analysis.results import ModeEstimate, Report, Source, Status, WindowResult

FPS = 19000.0
RED = np.array(mcolors.to_rgb(STATUS_COLOURS["failed"]))


def window(index: int, status: str) -> WindowResult:
    """A 190-frame window: one 2 kHz mode when ok, none when settled, nothing fitted when it failed."""
    mode = ModeEstimate(frequency_hz=2000.0, decay_rate_per_s=900.0, amplitude_mm=0.01, phase_rad=0.3)
    return WindowResult(
        index=index,
        start_frame=190 * index,
        end_frame=190 * (index + 1),
        status=status,
        modes=[mode] if status == "ok" else [],
        offset_mm=None if status == "failed" else 0.02,
        reason=None if status == "ok" else f"{status} (a test window)",
        samples=190,
    )


def red_pixels(statuses: list[str], path: Path) -> int:
    """Pixels of the failure red (within a shaded tint of it) in the plot of windows with these statuses."""
    windows = [window(i, s) for i, s in enumerate(statuses)]
    report = Report(
        source=Source(path="rec.cine", frames=190 * len(windows), fps=FPS),
        method="network",
        ejections=[w.start_frame for w in windows[1:]],
        windows=windows,
    )
    t = np.arange(190 * len(windows)) / FPS
    plot_report(report, 0.02 + 0.01 * np.cos(2 * np.pi * 2000 * (t % 0.01)), path)
    rgb = mimage.imread(path)[..., :3]
    white = np.ones(3)
    tints = [white + a * (RED - white) for a in (0.12, 1.0)]  # the shaded span, the label and legend line
    return int(sum((np.abs(rgb - tint).max(axis=-1) < 0.03).sum() for tint in tints))


def test_only_failure_is_red() -> None:
    assert [s for s, c in STATUS_COLOURS.items() if mcolors.to_rgb(c) == tuple(RED)] == ["failed"]
    assert set(STATUS_COLOURS) == set(Status.__args__)  # every status has a colour of its own
    assert len({mcolors.to_hex(c) for c in STATUS_COLOURS.values()}) == len(STATUS_COLOURS)


def test_a_failed_window_shows_red_and_good_ones_none(tmp_path: Path) -> None:
    assert red_pixels(["ok", "settled", "ok"], tmp_path / "good.png") == 0
    assert red_pixels(["ok", "failed", "settled"], tmp_path / "bad.png") > 2000  # its span is shaded
