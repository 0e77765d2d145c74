"""Pictures of the forward transform: a sheet of renders across the coefficient ranges (the
paper's Figure 6) and radial profiles beside their images (its Figure 4).

Sweep rows: one coefficient of (d, p, a, b) from its low to its high end of
:class:`service.physics.CoefficientRanges`, the others at mid-range. Profile rows: seeded
draws, each its ``z = -D(r)`` (Eq. 1) across the bore beside its render, with the outlet's
rim projected onto the image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.physics import CoefficientRanges, displacement
from service.plotting import pyplot
from service.render.camera import project
from service.render.renderer import Renderer

NAMES = ("d (mm)", "p", "a (mm)", "b (mm)")


def sweep_coefficients(ranges: CoefficientRanges, columns: int) -> np.ndarray:
    """Shape (4, columns, 4): row k sweeps coefficient k across its range, the others at mid-range."""
    bounds = ranges.bounds()  # (4, 2)
    mid = bounds.mean(axis=1)
    out = np.broadcast_to(mid, (4, columns, 4)).copy()
    for k in range(4):
        out[k, :, k] = np.linspace(bounds[k, 0], bounds[k, 1], columns)
    return out


def rim_outline(renderer: Renderer, points: int = 181) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates (col, row) of the outlet's rim, the circle r = R at z = 0."""
    theta = np.linspace(0.0, 2 * np.pi, points)
    R = renderer.scene.nozzle.radius_mm
    return project(renderer.scene, np.column_stack([R * np.cos(theta), R * np.sin(theta), np.zeros(points)]))


def write_sheet(
    renderer: Renderer,
    path: str | Path,
    ranges: CoefficientRanges = CoefficientRanges(),
    columns: int = 7,
    profiles: int = 3,
    seed: int = 0,
) -> np.ndarray:
    """Write the PNG sheet to ``path``; returns the coefficients drawn, (4 columns + profiles, 4)."""
    plt = pyplot()

    sweep = sweep_coefficients(ranges, columns)
    draws = ranges.sample(profiles, np.random.default_rng(seed))
    frames = renderer.render(np.concatenate([sweep.reshape(-1, 4), draws]))
    sweep_frames, draw_frames = frames[: 4 * columns].reshape(4, columns, *frames.shape[1:]), frames[4 * columns :]
    R = renderer.scene.nozzle.radius_mm
    r = np.linspace(-R, R, 401)
    rim_col, rim_row = rim_outline(renderer)

    fig = plt.figure(figsize=(1.6 * columns, 1.7 * (4 + profiles)))
    grid = fig.add_gridspec(4 + profiles, columns)
    for k in range(4):
        for j in range(columns):
            ax = fig.add_subplot(grid[k, j])
            ax.imshow(sweep_frames[k, j], cmap="gray", vmin=0, vmax=1)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{NAMES[k].split()[0]} = {sweep[k, j, k]:+.3g}", fontsize=8)
            if j == 0:
                ax.set_ylabel(NAMES[k], fontsize=9)
    half = columns // 2
    for i, c in enumerate(draws):
        ax = fig.add_subplot(grid[4 + i, :half])
        ax.plot(r, -displacement(np.abs(r), *c, R), color="tab:orange")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.axvline(-R, color="k", lw=0.8)
        ax.axvline(R, color="k", lw=0.8)
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("z = -D (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"d={c[0]:+.3f} mm  p={c[1]:+.3f}  a={c[2]:+.4f} mm  b={c[3]:+.4f} mm", fontsize=8)
        ax = fig.add_subplot(grid[4 + i, half : half + 2])
        ax.imshow(draw_frames[i], cmap="gray", vmin=0, vmax=1)
        ax.plot(rim_col, rim_row, color="tab:orange", lw=0.6, alpha=0.7)
        ax.set_xlim(-0.5, frames.shape[2] - 0.5)
        ax.set_ylim(frames.shape[1] - 0.5, -0.5)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title("render (rim in orange)", fontsize=8)
    fig.suptitle(
        "meniscope forward transform: sweeps across the coefficient ranges; profiles beside their renders", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return np.concatenate([sweep.reshape(-1, 4), draws])
