"""The validation figures as PNGs (Price et al. 2022): D(0, t) inferred against truth per method (Figs. 9,
10, 14), lab frames beside their VAE reconstructions (Fig. 13) and beside renders of the coefficients
inferred from them (Fig. 15)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.plotting import pyplot
from service.validation.evaluate import RecordingResult


def plot_centre_series(result: RecordingResult, path: Path, windows: int = 3) -> Path:
    """Inferred (dots) and true (line) D(0, t) over the first ``windows`` windows, one panel per method."""
    plt = pyplot()
    shown = sum(len(w.frames) for w in result.windows[:windows])
    t_ms = result.frames[:shown] / result.fps * 1e3
    names = list(result.methods)
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.7 * len(names)), sharex=True, sharey=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        method = result.methods[name]
        breaks = np.flatnonzero(np.diff(result.frames[:shown]) > 1) + 1  # no line across the transients
        for part in np.split(np.arange(shown), breaks):
            ax.plot(t_ms[part], result.truth[part, 4] * 1e3, "k-", lw=1)
        ax.plot(t_ms, method.pred[:shown, 4] * 1e3, ".", ms=2.5, color="C3")
        s = method.scores
        ax.set_title(
            f"{name}: RMSE {s.rmse['centre'] * 1e3:.1f} um, r {s.centre_correlation or float('nan'):.3f}",
            fontsize=9,
            loc="left",
        )
        ax.set_ylabel("D(0, t) (um)", fontsize=8)
    axes[-1, 0].set_xlabel(f"time in {result.path.name} (ms); line: truth, dots: inferred per frame")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _scaled(images: np.ndarray) -> np.ndarray:
    """Each image (N, h, w) stretched to [0, 1] on its own, for display."""
    lo = images.min(axis=(1, 2), keepdims=True)
    hi = images.max(axis=(1, 2), keepdims=True)
    return (images - lo) / np.where(hi > lo, hi - lo, 1.0)


def plot_rows(rows: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """A grid of images: one row per entry of ``rows`` (label -> (N, h, w)), each image stretched on its own."""
    plt = pyplot()
    n = max(len(images) for images in rows.values())
    fig, axes = plt.subplots(len(rows), n, figsize=(1.4 * n, 1.5 * len(rows) + 0.4), squeeze=False)
    for row, (label, images) in zip(axes, rows.items()):
        for ax, image in zip(row, _scaled(np.asarray(images, np.float64))):
            ax.imshow(image, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(label, fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
