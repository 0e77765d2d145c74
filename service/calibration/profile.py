"""What the video says about a parameter the fit may trade away: the finest level's cost along it, every frame's
motion refitted at each value, and the range of values the frames cannot tell from the best.

A Gauss-Newton sigma is local and assumes independent pixels; blurred pixels are not, and a near-mirror's
cost is far from quadratic. The frames are closer to independent samples: at each profiled value every
frame's cost is compared with its cost at the best value, and a value is told apart only when the summed
difference exceeds ``Z`` standard errors of that sum over the frames (a paired test).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from service.calibration import parameters as P
from service.calibration.fit import Problem, refine_motion
from service.calibration.synthesis import Synthesis
from service.scene import Scene

#: Offsets from the calibrated value, in the fitted coordinate, profiled: the inner pair just inside the precision
#: the report needs (a bracket between them is what can be claimed: x0.83 to x1.2 for the angle, +-0.75 deg, about
#: +-0.1 px of blur at 0.7 px as its squared width), the outer pair to see how far the cost stays flat.
PROFILED: dict[str, tuple[float, ...]] = {
    "fluid.roughness": (-0.3, -0.08, 0.08, 0.3),
    "light.angle_deg": (-0.3, -0.08, 0.08, 0.3),
    "light.azimuth_deg": (-2.0, -0.75, 0.75, 2.0),
    "light.elevation_deg": (-2.0, -0.75, 0.75, 2.0),
    "sensor.blur_sigma_px": (-0.5, -0.15, 0.15, 0.5),
    "camera.elevation_deg": (-1.5, -0.4, 0.4, 1.5),
}
#: The parameters refitted at each value of a profiled one, because they trade with it on a highlight's width and
#: brightness: a wider sun or a rougher fluid, and a dimmer one (Blender's recording of a light of 8 deg, alpha 0.06,
#: reflectance 0.9: the calibration found 5.9 deg, 0.10, 0.50, and the frames could not tell the two scenes apart).
#: The camera's elevation and the light's trade on where the highlights sit (both move the half-vector): a Gauss-Newton
#: sigma at the optimum called the camera's elevation pinned to 0.004 deg where it was 1.2 deg off, beside a light
#: 1.4 deg low (docs/calibration.md, "All at once, 20 windows, 8-bit"). The light's direction trades with its angle,
#: alpha and the reflectance, the highlight moving and growing together (Blender's all-at-once recording: with those
#: refitted the cost stayed within 7 % over +-2 deg of azimuth, where held it rose 5.6x; on the near-mirror it rose 3x
#: at +-0.75 deg either way). Held, they would make the profile sharp along a ridge the video cannot resolve.
PARTNERS: dict[str, tuple[str, ...]] = {
    "fluid.roughness": ("light.angle_deg", "fluid.reflectance"),
    "light.angle_deg": ("fluid.roughness", "fluid.reflectance"),
    "light.azimuth_deg": ("light.elevation_deg", "light.angle_deg", "fluid.roughness", "fluid.reflectance"),
    "light.elevation_deg": ("light.azimuth_deg", "light.angle_deg", "fluid.roughness", "fluid.reflectance"),
    "camera.elevation_deg": ("light.elevation_deg",),
}
#: Least-squares evaluations refitting the partners and every frame's motion at each profiled value.
PARTNER_EVALUATIONS = 6
#: Standard errors (over frames) of the summed cost difference that tell a value apart from the best.
Z = 2.0


@dataclass(frozen=True)
class Profile:
    """Cost along one parameter: ``values`` (file units, ascending), each frame's cost there (V, K), the best value,
    the interval of profiled values not told apart from it and its ``bracket``: the nearest values told apart on
    either side (the interval's true ends lie between, so the bracket is what the profile's spacing can claim);
    ``open_low``/``open_high``: the interval reaches the profile's end (the parameter may lie further out)."""

    name: str
    values: np.ndarray
    frame_costs: np.ndarray
    best: float
    interval: tuple[float, float]
    bracket: tuple[float, float]
    open_low: bool
    open_high: bool
    #: the value profiled round (the calibrated one) and whether the frames tell it from the best (a lower cost)
    centre: float = float("nan")
    centre_told_apart: bool = False
    #: each partner's refitted value (file units) at each profiled value (V,)
    partners: dict[str, np.ndarray] = field(default_factory=dict)
    #: the scene (partners refitted) and every frame's motion (K, 4) at each profiled value
    fits: tuple[tuple[Scene, np.ndarray], ...] = field(default=(), repr=False)

    @property
    def best_fit(self) -> tuple[Scene, np.ndarray]:
        """The scene and every frame's motion (K, 4) at the best value."""
        return self.fits[int(np.argmin(self.frame_costs.sum(axis=1)))]

    def indistinct_fits(self) -> list[tuple[float, Scene, np.ndarray, float | None]]:
        """Each value the frames cannot tell from the best, other than the centre, with its scene and motion: the
        points of a ridge the single frames leave open; and where the value is an end of the profile the interval is
        open at, the step beyond it (in the fitted coordinate: the last spacing again), else None."""
        inside = (self.values >= self.interval[0]) & (self.values <= self.interval[1]) & (self.values != self.centre)
        coords = np.array([P.PARAMETERS[P.index(self.name)].to_fit(v) for v in self.values])
        last = len(coords) - 1
        beyond = {0: coords[0] - coords[1] if self.open_low else None}
        beyond[last] = coords[-1] - coords[-2] if self.open_high else None
        return [(float(self.values[i]), *self.fits[i], beyond.get(i)) for i in np.flatnonzero(inside)]

    @property
    def best_cost(self) -> float:
        """The summed cost at the best value."""
        return float(self.frame_costs.sum(axis=1).min())

    @property
    def centre_cost(self) -> float:
        """The summed cost at the centre."""
        return float(self.frame_costs.sum(axis=1)[np.flatnonzero(self.values == self.centre)[0]])

    def as_dict(self) -> dict:
        """JSON-safe summary for the report."""
        return {
            "values": [float(v) for v in self.values],
            "cost": [float(c) for c in self.frame_costs.sum(axis=1)],
            "best": float(self.best),
            "interval": [float(v) for v in self.interval],
            "bracket": [float(v) for v in self.bracket],
            "open_low": self.open_low,
            "open_high": self.open_high,
            "partners": {name: [float(v) for v in refitted] for name, refitted in self.partners.items()},
        }


def indistinct(frame_costs: np.ndarray, z: float = Z) -> np.ndarray:
    """Which rows of per-value, per-frame costs (V, K) the frames cannot tell from the lowest total: the summed paired
    difference at most ``z`` standard errors (``sqrt(K)`` times the differences' spread over frames)."""
    best = int(np.argmin(frame_costs.sum(axis=1)))
    diff = frame_costs - frame_costs[best]
    k = frame_costs.shape[1]
    spread = diff.std(axis=1, ddof=1) if k > 1 else np.zeros(len(diff))
    return diff.sum(axis=1) <= z * np.sqrt(k) * spread


def profile(
    synth: Synthesis,
    scene: Scene,
    lab: np.ndarray,
    motion: np.ndarray,
    sigmas: tuple[float, ...],
    name: str,
    offsets: tuple[float, ...],
    max_evaluations: int = 10,
    fitted: tuple[P.Parameter, ...] = P.PARAMETERS,
) -> Profile:
    """The cost of ``lab`` (K, h, w) on ``sigmas`` along parameter ``name`` at the calibrated value and ``offsets``
    from it (fitted coordinate, clipped to the bounds), each frame's motion refitted from ``motion`` (K, 4), and
    its :data:`PARTNERS` among the ``fitted`` parameters too (by :data:`PARTNER_EVALUATIONS` joint evaluations), the
    rest of the scene held."""
    index = P.index(name)
    param = P.PARAMETERS[index]
    partners = _partners(name, fitted)
    x = P.read(scene)
    lo, hi = P.bounds(scene)
    coords = np.unique(np.clip(x[index] + np.array((0.0, *offsets)), lo[index], hi[index]).round(6))
    centre = int(np.flatnonzero(coords == np.clip(x[index], lo[index], hi[index]).round(6))[0])
    refits = [refit_at(synth, scene, lab, motion, sigmas, name, c, max_evaluations, fitted) for c in coords]
    costs = np.array([cost for cost, _ in refits])
    fits = [fit for _, fit in refits]
    values = np.array([param.from_fit(c) for c in coords])
    told = ~indistinct(costs)
    kept = np.flatnonzero(~told)
    best = int(np.argmin(costs.sum(axis=1)))
    return Profile(
        name=name,
        values=values,
        frame_costs=costs,
        best=float(values[best]),
        interval=(float(values[kept.min()]), float(values[kept.max()])),
        bracket=(float(values[max(kept.min() - 1, 0)]), float(values[min(kept.max() + 1, len(values) - 1)])),
        open_low=bool(kept.min() == 0 and coords[0] > lo[index]),
        open_high=bool(kept.max() == len(coords) - 1 and coords[-1] < hi[index]),
        centre=float(values[centre]),
        centre_told_apart=bool(told[centre]),
        partners={p.name: np.array([p.from_fit(P.read(f[0], (p,))[0]) for f in fits]) for p in partners},
        fits=tuple(fits),
    )


def refit_at(
    synth: Synthesis,
    scene: Scene,
    lab: np.ndarray,
    motion: np.ndarray,
    sigmas: tuple[float, ...],
    name: str,
    coord: float,
    max_evaluations: int = 10,
    fitted: tuple[P.Parameter, ...] = P.PARAMETERS,
) -> tuple[np.ndarray, tuple[Scene, np.ndarray]]:
    """``scene`` with parameter ``name`` at ``coord`` (its fitted coordinate) and its :data:`PARTNERS` among the
    ``fitted`` parameters and every frame's motion refitted from ``motion`` (K, 4) on ``sigmas``, the rest held: each
    frame's cost there (K,) and the scene and motion found."""
    x = P.read(scene)
    x[P.index(name)] = coord
    candidate = P.write(scene, x)
    partners = _partners(name, fitted)
    if not partners:
        moved, cost = refine_motion(Problem(synth, candidate, lab, sigmas), motion, max_evaluations)
        return cost, (candidate, moved)
    problem = Problem(synth, candidate, lab, sigmas, fitted=partners)
    solved, res = problem.solve(motion, PARTNER_EVALUATIONS)
    return (res.fun.reshape(problem.target.shape) ** 2).sum(axis=1), problem.unpack(solved)


def _partners(name: str, fitted: tuple[P.Parameter, ...]) -> tuple[P.Parameter, ...]:
    """The :data:`PARTNERS` of ``name`` that the calibration fits (a held one trades with nothing)."""
    return tuple(p for p in fitted if p.name in PARTNERS.get(name, ()))


#: Moves of :func:`descend` at most, after the finest stage.
DESCENT_ROUNDS = 3
#: Least-squares evaluations of the whole problem after each move.
DESCENT_EVALUATIONS = 16


def descend(
    synth: Synthesis,
    scene: Scene,
    lab: np.ndarray,
    motion: np.ndarray,
    sigmas: tuple[float, ...],
    windows: np.ndarray,
    profiled: dict[str, tuple[float, ...]],
    rounds: int = DESCENT_ROUNDS,
    evaluations: int = DESCENT_EVALUATIONS,
    each: Callable[[], None] = lambda: None,
    fitted: tuple[P.Parameter, ...] = P.PARAMETERS,
) -> tuple[Scene, np.ndarray, dict[str, Profile], list[dict], tuple | None]:
    """The finest stage's ``scene`` and ``motion`` (K, 4) moved along their profiles while the frames tell a profiled
    value from the calibrated one: the least squares stops on a highlight's ridge short of where a single parameter,
    its partners and the frames' motion refitted, costs less (Blender's all-at-once recording). Each round profiles
    ``profiled``, moves to the lowest-cost profile whose centre the frames tell from its best, and fits the whole
    problem again from there (``evaluations``, the ``fitted`` parameters, motion tied within ``windows``); it stops
    when no profile does, when a round's centre costs no less than the round's before (that round is undone), or after
    ``rounds`` moves. ``each`` is called after every profile. Returns the scene, the motion, the profiles at them (the
    report's), the moves, and the last kept fit as ``(problem, x, result)`` (None without a move)."""
    moves: list[dict] = []
    kept: tuple | None = None
    previous = None
    while profiled:
        profiles = {}
        for name, offsets in profiled.items():
            profiles[name] = profile(synth, scene, lab, motion, sigmas, name, offsets, fitted=fitted)
            each()
        cost = min(p.centre_cost for p in profiles.values())  # each refits the motion, some the partners too
        if previous is not None and not cost < previous[0]:
            moves[-1]["kept"] = False
            _, scene, motion, profiles, kept = previous
            return scene, motion, profiles, moves, kept
        lower = [p for p in profiles.values() if p.centre_told_apart]
        if not lower or len(moves) == rounds:
            return scene, motion, profiles, moves, kept
        previous = (cost, scene, motion, profiles, kept)
        step = min(lower, key=lambda p: p.best_cost)
        problem = Problem(synth, step.best_fit[0], lab, sigmas, windows, fitted=fitted)
        x, res = problem.solve(step.best_fit[1], evaluations)
        scene, motion = problem.unpack(x)
        kept = (problem, x, res)
        moves.append(
            {
                "parameter": step.name,
                "from": step.centre,
                "to": step.best,
                "centre_cost": cost,
                "profile_cost": step.best_cost,
                "kept": True,
            }
        )
    return scene, motion, {}, moves, kept
