"""The PNG beside a report: the per-frame centre displacement, each window's fitted curve, the ejections
(Price et al. 2022, Figs. 16 and 17), and when there is truth, the true curve too."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from service.analysis.fit import model_curve
from service.analysis.results import Report
from service.errors import MeniscopeError
from service.plotting import pyplot

#: Windows drawn at most: beyond this the curves are too dense to read.
MAX_WINDOWS = 12
_COLOURS = {"ok": "tab:red", "settled": "tab:green", "unresolved": "tab:orange", "failed": "tab:gray"}


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
        ax.plot(t_ms, truth_mm[:end], "-", lw=0.8, color="tab:blue", alpha=0.7, label="truth")
    for w in windows:
        frames = np.arange(w.start_frame + w.transient_frames, w.end_frame)
        curve = model_curve(w, (frames - w.start_frame) / fps)
        modes = ", ".join(f"{m.frequency_hz:.0f} Hz / {m.decay_rate_per_s:.0f} s⁻¹" for m in w.modes[:1])
        ax.plot(frames / fps * 1e3, curve, "-", lw=1.4, color=_COLOURS[w.status])
        if w.end_frame - w.start_frame < 0.5 * end / len(windows):
            continue  # a sliver before the first ejection: no room for a label
        ax.annotate(f"{w.status}\n{modes}", (w.start_frame / fps * 1e3, 1.0), xycoords=("data", "axes fraction"),
                    va="top", fontsize=7, color=_COLOURS[w.status])
    for e in report.ejections:
        if e < end:
            ax.axvline(e / fps * 1e3, color="k", lw=0.7, ls="--")
    shown = f"first {len(windows)} of {len(report.windows)} windows" if len(report.windows) > len(windows) else \
        f"{len(windows)} windows"
    ax.set(xlabel="time (ms)", ylabel="centre displacement D(0, t) (mm)",
           title=f"{Path(report.source.path).name}: {shown}; dashed lines: ejections; fitted curves coloured by status")
    ax.legend(loc="lower right", fontsize=8)
    try:
        fig.savefig(path, dpi=110)
    except OSError as exc:
        raise MeniscopeError(path, f"cannot write the plot: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
    return path
