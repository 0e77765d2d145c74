"""Whole windows of the lab video held to Eq. 1: they tell apart the scenes along a ridge the single frames leave open.

Single frames, each with a motion of its own, trade the light's direction, its size, the fluid's roughness and its
reflectance along a ridge where every frame's highlights fit about as well (docs/calibration.md, "Whole windows
along the ridge"). A window's frames share one Eq. 1 motion, ten numbers: only a scene on the right part of the ridge
makes its highlights move the way a damped membrane moves. This stage refines a few windows (every other frame)
through the calibrated scene from its library's per-frame starts (:func:`.synthesis.refine_window`, as ``analyze
--refine`` does), then through each point of the profiles that the single frames cannot tell from it, each search
started where the calibrated scene's ended (:func:`.synthesis.polish`), and keeps the point whose windows fit best.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.calibration import parameters as P
from service.calibration.fit import Library, crop
from service.calibration.footage import LabWindow
from service.calibration.profile import Profile, refit_at
from service.calibration.synthesis import Synthesis
from service.inverse import synthesis
from service.render.renderer import Renderer
from service.scene import Scene


@dataclass(frozen=True)
class Point:
    """A scene the windows score: the calibrated one (``parameter`` None) or a point of a profile, with every lab
    frame's motion (K, 4) fitted there."""

    parameter: str | None
    value: float
    scene: Scene
    motion: np.ndarray
    #: where the point is the end of its profile at which the single frames' interval is open: the step (fitted
    #: coordinate) to the next point beyond it
    beyond: float | None = None


def further(
    synth: Synthesis,
    lab: np.ndarray,
    sigmas: tuple[float, ...],
    point: Point,
    fitted: tuple[P.Parameter, ...] = P.PARAMETERS,
) -> Point | None:
    """The next point of ``point``'s profile beyond it (:attr:`Point.beyond`), its partners among the ``fitted``
    parameters and the ``lab`` frames' motion refitted there (:func:`.profile.refit_at`, on ``sigmas``); None where
    there is none or it leaves the parameter's bounds."""
    if point.parameter is None or point.beyond is None:
        return None
    index = P.index(point.parameter)
    coord = P.read(point.scene)[index] + point.beyond
    low, high = P.bounds(point.scene)
    if not low[index] <= coord <= high[index]:
        return None
    _, (scene, motion) = refit_at(synth, point.scene, lab, point.motion, sigmas, point.parameter, coord, fitted=fitted)
    return Point(point.parameter, P.PARAMETERS[index].from_fit(coord), scene, motion, point.beyond)


def ridge(scene: Scene, motion: np.ndarray, profiles: dict[str, Profile]) -> list[Point]:
    """The calibrated scene and every point of a profile with refitted partners that the single frames cannot tell
    from its best (:meth:`.Profile.indistinct_fits`)."""
    points = [Point(None, float("nan"), scene, motion)]
    for name, prof in profiles.items():
        if prof.partners:
            points += [Point(name, *fit) for fit in prof.indistinct_fits()]
    return points


#: Points at most that :func:`choose` walks beyond the end of a profile.
WALK = 2


def choose(
    synth: Synthesis,
    points: list[Point],
    windows: tuple[LabWindow, ...],
    full_scale: float,
    sigmas: tuple[float, ...],
    walk: Callable[[Point], Point | None] = lambda point: None,
    each: Callable[[], None] = lambda: None,
) -> tuple[Point, list[dict]]:
    """The point of ``points`` (the first is the calibrated scene) whose ``windows`` fit best held to Eq. 1: each
    window refined through the first point from its :class:`.fit.Library`'s nearest per-frame motion (on ``sigmas``),
    then through every other point from there; :func:`pick` chooses. Where the point chosen ends its profile on a
    side the single frames leave open, the next point beyond it (``walk``: :func:`further`) is scored too and taken
    while it fits every window better, :data:`WALK` points at most. Returns the point and a row per point scored (its
    residual RMS per window in stored units). ``each`` is called after every point."""
    first = points[0].scene
    library = Library(synth, first, sigmas)
    renderer = Renderer(first, sun_samples=synthesis.SUN_SAMPLES, threads=None, **synth.rays)
    starts = []
    for window in windows:
        frames = crop(window.frames, first)
        coefficients = library.nearest(frames / full_scale)[0]
        dt = float(window.t[1] - window.t[0])
        start = synthesis.start_motion(coefficients, window.t, 1.0 / dt)
        starts.append(synthesis.refine_window(renderer, frames, window.t, start))
    each()

    def score(point: Point) -> dict:  # the windows through ``point``, each from where the first point's ended
        renderer = Renderer(point.scene, sun_samples=synthesis.SUN_SAMPLES, threads=None, **synth.rays)
        polished = [
            synthesis.polish(renderer, crop(window.frames, point.scene), window.t, s.motion, s.blur_sigma_px)
            for window, s in zip(windows, starts)
        ]
        each()
        return _row(point, polished)

    rows = [_row(points[0], starts)] + [score(point) for point in points[1:]]
    rms = np.array([row["rms"] for row in rows])
    for row, better in zip(rows, np.all(rms < rms[0], axis=1)):
        row["better_in_every_window"] = bool(better)
    best = pick(rms)
    chosen, row = points[best], rows[best]
    for _ in range(WALK):
        beyond = walk(chosen)
        if beyond is None:
            break
        rows.append(score(beyond))
        rows[-1]["beyond"] = True
        rows[-1]["better_in_every_window"] = bool(np.all(np.array(rows[-1]["rms"]) < row["rms"]))
        if not rows[-1]["better_in_every_window"]:
            break
        chosen, row = beyond, rows[-1]
    row["chosen"] = True
    return chosen, rows


def pick(rms: np.ndarray) -> int:
    """Which row of the points' residual RMS per window (P, W) wins: the first (the calibrated scene) unless another
    fits every window better (on Blender's light recording a sun 0.6 deg narrower scored 0.5 % lower summed over
    three windows and worse in two of them: noise, not evidence); of those, the lowest summed mean square."""
    eligible = np.flatnonzero(np.all(rms < rms[0], axis=1) | (np.arange(len(rms)) == 0))
    return int(eligible[np.argmin(np.square(rms[eligible]).sum(axis=1))])


def _row(point: Point, refined: list[synthesis.Refined]) -> dict:
    """A point's line in the report: which profile and value (none for the calibrated scene), its windows' residual
    RMS and their summed mean square, and each window's offset (d + p R) and Eq. 1's first mode refined there (what
    a point on the ridge does to the numbers a user reads: :func:`spread`). A point walked to beyond its profile says
    ``beyond``; there, ``better_in_every_window`` is against the point it was walked from."""
    radius = point.scene.nozzle.radius_mm
    return {
        "parameter": point.parameter,
        "value": None if point.parameter is None else point.value,
        "scene": {p.name: p.from_fit(float(v)) for p, v in zip(P.PARAMETERS, P.read(point.scene))},
        "rms": [float(r.rms) for r in refined],
        "cost": float(np.sum(np.square([r.rms for r in refined]))),
        "windows": [
            {
                "offset_mm": r.motion.offset_mm(radius),
                "amplitude_mm": float(r.motion.A1),
                "frequency_hz": float(r.motion.f1),
                "decay_rate_per_s": float(r.motion.g1),
            }
            for r in refined
        ],
        "chosen": False,
        "beyond": False,
    }


#: The numbers :func:`spread` compares across the ridge, and whether each is compared relative to the chosen point's.
SPREAD = {"offset_mm": False, "amplitude_mm": True, "frequency_hz": True, "decay_rate_per_s": True}


def spread(rows: list[dict]) -> dict[str, dict[str, float]]:
    """How far the lab windows' numbers move over the scenes the single frames leave open: for each profiled parameter
    with points in ``rows`` (:func:`choose`'s; points walked beyond a profile are left out unless chosen), the median
    over windows of each number's change from the chosen point (offset in mm, the rest relative), the largest over
    that parameter's points. Neither the profiles' paired test nor the windows told these scenes apart, so this is
    what the calibration leaves open in the numbers a method reads through its scene: one step along each profile,
    a lower estimate of their systematic error, not a bound."""
    chosen = next((row for row in rows if row["chosen"]), None)
    out: dict[str, dict[str, float]] = {}
    for row in rows:
        if chosen is None or row is chosen or row["parameter"] is None or row["beyond"]:
            continue
        moved = out.setdefault(row["parameter"], dict.fromkeys(SPREAD, 0.0))
        for key, relative in SPREAD.items():
            here = np.array([w[key] for w in row["windows"]])
            there = np.array([w[key] for w in chosen["windows"]])
            change = np.abs(here - there)
            if relative:  # a window whose number is 0 at the chosen point has no relative change to count
                keep = there != 0
                change = change[keep] / np.abs(there[keep])
            if change.size:
                moved[key] = max(moved[key], float(np.median(change)))
    return out
