"""The PNG beside a report: the per-frame centre displacement, each window's fitted curve, the ejections
(Price et al. 2022, Figs. 16 and 17), and when there is truth, the true curve too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from service.analysis.fit import model_curve
from service.analysis.results import Report
from service.errors import MeniscopeError
from service.plotting import pyplot

#: Windows drawn at most: beyond this the curves are too dense to read.
MAX_WINDOWS = 12
#: Fitted curves by window status, so that a glance finds the bad ones: red is for failure alone, orange
#: for a fit that cannot be trusted; a status added later is drawn grey until it is given a colour.
STATUS_COLOURS = {"ok": "tab:blue", "settled": "tab:green", "unresolved": "tab:orange", "failed": "tab:red"}
OTHER_STATUS = "tab:gray"
#: Statuses whose whole window is shaded in its colour (a failed window has no curve to draw).
SHADED = ("unresolved", "failed")


def plot_report(report: Report, centre_mm: np.ndarray, path: Path, truth_mm: np.ndarray | None = None) -> Path:
    """Draw the first :data:`MAX_WINDOWS` windows of ``report`` over ``centre_mm`` (N,) and write ``path``."""
    plt = pyplot()

    fps = report.source.fps
    windows = report.windows[:MAX_WINDOWS]
    end = windows[-1].end_frame if windows else len(centre_mm)
    t_ms = np.arange(end) / fps * 1e3
    fig, ax = plt.subplots(figsize=(12, 4.5), layout="constrained")
    ax.plot(t_ms, centre_mm[:end], ".", ms=2, color="0.45", label=f"D(0, t) fitted ({report.method})")
    if truth_mm is not None:
        ax.plot(t_ms, truth_mm[:end], "-", lw=0.8, color="tab:purple", alpha=0.7, label="truth")
    for w in windows:
        frames = np.arange(w.start_frame + w.transient_frames, w.end_frame)
        curve = model_curve(w, (frames - w.start_frame) / fps)
        modes = "".join(f"\n{m.frequency_hz:.0f} Hz\n{m.decay_rate_per_s:.0f} s⁻¹" for m in w.modes[:1])
        colour = STATUS_COLOURS.get(w.status, OTHER_STATUS)
        ax.plot(frames / fps * 1e3, curve, "-", lw=1.4, color=colour)
        if w.status in SHADED:
            ax.axvspan(w.start_frame / fps * 1e3, w.end_frame / fps * 1e3, color=colour, alpha=0.12, lw=0)
        if w.end_frame - w.start_frame < 0.5 * end / len(windows):
            continue  # a sliver before the first ejection: no room for a label
        ax.annotate(
            f"{w.status}{modes}",
            (w.start_frame / fps * 1e3, 1.0),
            xycoords=("data", "axes fraction"),
            va="top",
            fontsize=7,
            color=colour,
        )
    for e in report.ejections:
        if e < end:
            ax.axvline(e / fps * 1e3, color="k", lw=0.7, ls="--")
    shown = (
        f"first {len(windows)} of {len(report.windows)} windows"
        if len(report.windows) > len(windows)
        else f"{len(windows)} windows"
    )
    ax.set(
        xlabel="time (ms)",
        ylabel="centre displacement D(0, t) (mm)",
        title=f"{Path(report.source.path).name}: {shown}; dashed lines: ejections; fitted curves coloured by status",
    )
    statuses = dict.fromkeys(w.status for w in windows)  # those drawn, in order of appearance
    handles = ax.get_legend_handles_labels()[0] + [
        Line2D([], [], lw=1.4, color=STATUS_COLOURS.get(s, OTHER_STATUS), label=f"fit: {s}") for s in statuses
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)  # beside the plot, off the data
    try:
        fig.savefig(path, dpi=110)
    except OSError as exc:
        raise MeniscopeError(path, f"cannot write the plot: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
    return path
