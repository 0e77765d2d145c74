"""Analysis by synthesis: the scene and the motion of K lab frames fitted jointly, coarse to fine, from several starts.

Unknowns: the scene parameters of :data:`.parameters.PARAMETERS` and the motion (:class:`Motion`): Eq. 1's
d and p once per window between ejections (constant there), a and b per fitted frame (free, so the
ejection's transient bulge needs no model). Each stage is one bounded least-squares problem (scipy's
trust-region reflective) on the blurred pyramid of :mod:`.synthesis`, its Jacobian by finite differences
with the sparsity declared (a frame's residuals depend on its window's d, p and its own a, b), so a step costs one renderer per scene parameter plus four
renders of all frames. Before the first stage each frame's motion starts at its nearest neighbour in a
library rendered with the candidate scene; the ROI is found before the first stage and again after it. Before the
finer stages the light's azimuth is chosen from a grid of directions scored on the finest level (:func:`aim`); after
them the scene descends along its profiles (:func:`.profile.descend`), and whole windows held to Eq. 1 choose among
the points of the profiles the single frames cannot tell apart (:mod:`.windows`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from tqdm import tqdm

from service.calibration import parameters as P
from service.calibration.artifacts import face_pixels, recover, still_pixels, with_spheres
from service.calibration.footage import Footage
from service.calibration.noise import NoiseFit, fit_noise
from service.calibration.roi import find_roi, refine_shift
from service.calibration.synthesis import Synthesis, gaussian, pyramid
from service.errors import MeniscopeError
from service.physics import CoefficientRanges
from service.scene import Scene

if TYPE_CHECKING:
    from service.calibration.profile import Profile

#: Bounds of the per-frame coefficients: the training ranges widened to hold an ejection's bulge.
MOTION_LOW = np.array([-0.08, -0.4, -0.06, -0.03])
MOTION_HIGH = np.array([0.08, 0.4, 0.14, 0.03])
#: Typical size of a change of each coefficient (d, p, a, b): the unit the optimiser steps in.
MOTION_SCALE = np.array([0.005, 0.03, 0.005, 0.003])
#: Typical size of a change of each scene parameter, in its fitted coordinate (PARAMETERS' order).
SCENE_SCALE = np.array([0.15, 0.05, 2.0, 2.0, 0.1, 0.1, 0.5, 0.2, 0.005])
#: Finite-difference step, in those units.
DIFF_STEP = 0.05


@dataclass(frozen=True)
class Stage:
    """One coarse-to-fine stage: the pyramid's blur levels (px), rays per pixel per axis, evaluations allowed, and
    the rays per axis of the pixels where the frame steps sharply (0: none; ``Renderer``'s ``edge_supersample``)."""

    sigmas: tuple[float, ...]
    supersample: int
    max_evaluations: int
    edge_supersample: int = 0


#: Evaluations of the finest stage: 48 landed closer to the truth than 8 on a near-mirror's Blender video, in one
#: run (docs/new_camera.md, "The finest stage run longer").
FINEST_EVALUATIONS = 48
SCHEDULE = (Stage((6.0, 3.0), 1, 10), Stage((3.0, 1.5), 1, 10), Stage((1.5, 0.7), 2, FINEST_EVALUATIONS))


def with_edge_rays(schedule: tuple[Stage, ...], rays: int) -> tuple[Stage, ...]:
    """``schedule`` with its finest stage's steep pixels traced again at ``rays`` per axis (0: none). Point-sampled at
    2 x 2, a highlight's edge, the bore's shadow and the glints make a sun twice too wide fit Blender Cycles' frames
    best; the edge rays take some of that bias out at several times the calibration's time (docs/calibration.md, "The
    sun's angle and the renderer's rays per pixel", "Edge rays in the calibration")."""
    return (*schedule[:-1], replace(schedule[-1], edge_supersample=rays))


#: Fluid roughness (GGX alpha) of the extra starts: a near-mirror and a rough metal.
START_ALPHAS = (0.004, 0.1)
#: Starts carried through the finer stages, best first by their finest-level cost after the coarse stage; the lowest
#: final cost wins. One: carrying all three (finest stage 12 evaluations) let a lower final cost pick a wrong scene
#: on Blender's rough recording (light 2.9 deg off, angle -35 %) and did not bring all-at-once into the targets.
CARRY = 1
#: The light directions tried before the finer stages: the guess's azimuth and elevation offset by multiples of
#: ``LIGHT_STEP_DEG`` up to ``LIGHT_REACH_DEG`` either way (the issue's mismatch: up to 10 deg in each), each
#: scored on the finest level (:func:`aim`, :func:`with_azimuth`). The coarse levels cannot tell a light ``+x`` deg
#: round from one ``-x`` deg round when the guess's light faces the camera (the scene is mirror-symmetric about their plane):
#: on Blender's light recording (true 188, -34 from 180, -40) the middle level scored azimuth 172 and 188 within 1 %
#: at elevation -40, and the fit went the wrong way; the finest level told them apart (397 against 277 at -34).
LIGHT_STEP_DEG = 5.0
LIGHT_REACH_DEG = 10.0
#: The scene parameters the light grid sets.
LIGHT = ("light.azimuth_deg", "light.elevation_deg")
#: Least-squares evaluations refining each frame's motion (from its nearest library render) to score a light.
LIGHT_EVALUATIONS = 6


@dataclass
class Calibration:
    """What a calibration found: the scene, the per-frame motion, uncertainties, and the evidence."""

    guess: Scene
    scene: Scene
    roi: tuple[float, float]
    roi_score: float
    motion: np.ndarray  # (K, 4)
    sigma: dict[str, float]  # 1-sigma of each fitted parameter, in the file's units
    residual_before: float  # RMS on the finest level, fraction of full scale
    residual_after: float
    noise: NoiseFit
    spheres_found: int
    seconds: float
    builds: int
    starts: list[dict] = field(default_factory=list)
    profiles: dict[str, Profile] = field(default_factory=dict)  # the finest level's cost along weak parameters
    moves: list[dict] = field(default_factory=list)  # the descent along the profiles after the finest stage
    ridge: list[dict] = field(default_factory=list)  # the points of the profiles scored by whole windows, and which won
    finest: Stage = SCHEDULE[-1]  # the finest stage's blur levels and rays, which the report's figure renders with
    held: tuple[str, ...] = ()  # parameters kept at the guess's value (the user's measurements), not fitted


#: Columns of (d, p, a, b) tied across a window's frames by default: d and p (see :class:`Motion`).
TIED = (0, 1)


class Motion:
    """The motion unknowns of K frames: the ``tied`` columns of Eq. 1's (d, p, a, b) once per window between
    ejections (d and p are constant in a window), the others per frame. Tying d and p across a window's frames
    stops each frame's curvature trading with the fluid's roughness, the light's angle and the blur (Blender
    rough and all-at-once recordings: alpha -2 % and +11 % tied, -37 % and +70 % untied). Tying p alone fits
    each frame's motion better for a given scene (d trades with a: with the true scene on the near-mirror
    recording, fine-level cost 4.4 with p tied, 80-104 with d and p tied from their frames' medians, 1.3 for
    the true motion), but the joint calibration then trades alpha again (-38 %, +60 %, mirror +589 %).
    Each frame its own window is the untied case."""

    def __init__(self, windows: np.ndarray, tied: tuple[int, ...] = TIED) -> None:
        self.group = np.unique(np.asarray(windows), return_inverse=True)[1]
        self.k, self.g = len(self.group), int(self.group.max()) + 1
        self.tied = np.array(sorted(tied), dtype=int)
        self.free = np.setdiff1d(np.arange(4), self.tied)
        nt, nf = len(self.tied), len(self.free)
        self.size = nt * self.g + nf * self.k
        self.low, self.high, self.scale = (
            np.concatenate([np.tile(v[self.tied], self.g), np.tile(v[self.free], self.k)])
            for v in (MOTION_LOW, MOTION_HIGH, MOTION_SCALE)
        )

    def expand(self, v: np.ndarray) -> np.ndarray:
        """Per-frame coefficients (K, 4) of the unknowns ``v``."""
        nt = len(self.tied) * self.g
        out = np.empty((self.k, 4))
        out[:, self.tied] = v[:nt].reshape(self.g, len(self.tied))[self.group]
        out[:, self.free] = v[nt:].reshape(self.k, len(self.free))
        return out

    def pack(self, motion: np.ndarray) -> np.ndarray:
        """The unknowns of per-frame coefficients (K, 4): each window's tied values the median of its frames'."""
        tied = np.stack([np.median(motion[self.group == i][:, self.tied], axis=0) for i in range(self.g)])
        return np.concatenate([tied.ravel(), motion[:, self.free].ravel()])

    def sparsity(self, q: int, n_scene: int) -> lil_matrix:
        """Which residual (K*q of them) depends on which unknown: all on the ``n_scene`` scene parameters, frame
        k's on its window's tied values and its own free ones."""
        m = lil_matrix((self.k * q, n_scene + self.size), dtype=np.int8)
        m[:, :n_scene] = 1
        nt, nf = len(self.tied), len(self.free)
        for k, g in enumerate(self.group):
            rows = slice(k * q, (k + 1) * q)
            m[rows, n_scene + nt * g : n_scene + nt * (g + 1)] = 1
            m[rows, n_scene + nt * self.g + nf * k : n_scene + nt * self.g + nf * (k + 1)] = 1
        return m


class Problem:
    """The least-squares problem of one stage: lab pyramid, synthesis, the ``fitted`` scene parameters (the rest held
    at the base scene's) and K frames' motion (:class:`Motion`, tied within the ``windows`` (K,) the frames belong
    to; untied when omitted)."""

    def __init__(
        self,
        synth: Synthesis,
        base: Scene,
        lab: np.ndarray,
        sigmas: tuple[float, ...],
        windows: np.ndarray | None = None,
        tied: tuple[int, ...] = TIED,
        fitted: tuple[P.Parameter, ...] = P.PARAMETERS,
    ) -> None:
        self.synth, self.base, self.sigmas, self.fitted = synth, base, sigmas, fitted
        self.target = pyramid(lab, sigmas)  # (K, Q)
        self.k = len(lab)
        self.motion = Motion(np.arange(self.k) if windows is None else windows, tied)
        self.n_scene = len(fitted)
        self.x0 = P.read(base, fitted)
        lo, hi = P.bounds(base, fitted)
        self.low = np.concatenate([lo, self.motion.low])
        self.high = np.concatenate([hi, self.motion.high])
        scale = SCENE_SCALE[[P.PARAMETERS.index(p) for p in fitted]]
        self.scale = np.concatenate([scale, self.motion.scale])

    def unpack(self, x: np.ndarray) -> tuple[Scene, np.ndarray]:
        return P.write(self.base, x[: self.n_scene], self.fitted), self.motion.expand(x[self.n_scene :])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        scene, motion = self.unpack(x)
        return (self.synth.levels(scene, motion, self.sigmas) - self.target).ravel()

    def frame_costs(self, scene: Scene, motion: np.ndarray) -> np.ndarray:
        """Each frame's squared residual (K,) for per-frame ``motion`` (K, 4) in ``scene``."""
        r = self.synth.levels(scene, motion, self.sigmas) - self.target
        return (r**2).sum(axis=1)

    def solve(self, motion: np.ndarray, max_evaluations: int) -> tuple[np.ndarray, object]:
        """Least squares from the base scene and ``motion`` (K, 4), in units of ``scale`` around the start."""
        start = np.clip(np.concatenate([self.x0, self.motion.pack(motion)]), self.low, self.high)
        fun = lambda u: self.residuals(start + u * self.scale)
        res = least_squares(
            fun,
            np.zeros_like(start),
            bounds=((self.low - start) / self.scale, (self.high - start) / self.scale),
            jac_sparsity=self.motion.sparsity(self.target.shape[1], self.n_scene),
            diff_step=DIFF_STEP,
            x_scale=1.0,
            max_nfev=max_evaluations,
            method="trf",
            tr_solver="lsmr",
        )
        return start + res.x * self.scale, res


class Library:
    """``size`` renders of a scene with random motion (the training ranges, a fifth of them with an ejection's
    bulge) as pyramids: each lab frame's nearest neighbour is where its motion starts."""

    def __init__(self, synth: Synthesis, scene: Scene, sigmas: tuple[float, ...], size: int = 600, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.coeffs = CoefficientRanges().sample(size, rng)
        bulge = rng.random(size) < 0.2
        self.coeffs[bulge, 2] = rng.uniform(0.03, MOTION_HIGH[2], bulge.sum())
        self.sigmas = sigmas
        self.model = synth.levels(scene, self.coeffs, sigmas)
        self._norm = (self.model**2).sum(1)

    def nearest(self, lab: np.ndarray, count: int = 1) -> np.ndarray:
        """Motion (count, K, 4) of each lab frame's ``count`` nearest neighbours (lab frames (K, h, w)), nearest first."""
        target = pyramid(lab, self.sigmas)
        dist = (target**2).sum(1)[:, None] - 2 * target @ self.model.T + self._norm[None, :]
        return self.coeffs[np.argsort(dist, axis=1)[:, :count].T]


def motion_only(
    synth: Synthesis,
    scene: Scene,
    lab: np.ndarray,
    sigmas: tuple[float, ...],
    starts: int = 5,
    max_evaluations: int = 15,
) -> np.ndarray:
    """Each frame's motion (K, 4) for a fixed scene: its ``starts`` nearest library neighbours each refined by
    least squares (scene fixed, so no renderer is built), the best kept per frame. Highlights make the motion
    landscape rugged; several starts per frame are cheap here and spare the joint fit a bad start."""
    problem = Problem(synth, scene, lab, sigmas)  # untied: each frame its own motion
    best, best_cost = None, None
    for start in Library(synth, scene, sigmas, size=1500).nearest(lab, starts):
        motion, cost = refine_motion(problem, start, max_evaluations)
        if best is None:
            best, best_cost = motion, cost
        else:
            better = cost < best_cost
            best[better], best_cost[better] = motion[better], cost[better]
    return best


def refine_motion(problem: Problem, start: np.ndarray, max_evaluations: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's motion (K, 4) refined by least squares from ``start`` (K, 4) with ``problem``'s base scene held
    (no renderer is built), and each frame's squared residual (K,) there."""
    k, q = problem.target.shape
    mot = problem.motion
    fixed = problem.x0
    x0 = np.clip(mot.pack(start), mot.low, mot.high)
    res = least_squares(
        lambda u: problem.residuals(np.concatenate([fixed, x0 + u * mot.scale])),
        np.zeros_like(x0),
        bounds=((mot.low - x0) / mot.scale, (mot.high - x0) / mot.scale),
        jac_sparsity=mot.sparsity(q, 0),
        diff_step=DIFF_STEP,
        max_nfev=max_evaluations,
        method="trf",
        tr_solver="lsmr",
    )
    return mot.expand(x0 + res.x * mot.scale), (res.fun.reshape(k, q) ** 2).sum(axis=1)


def light_grid(guess: Scene, step: float = LIGHT_STEP_DEG, reach: float = LIGHT_REACH_DEG) -> np.ndarray:
    """Light directions (N, 2: azimuth, elevation in degrees) on a square grid of ``step`` round the guess's out to
    ``reach`` either way, nearest first; elevations clipped to the parameter's bounds."""
    n = math.floor(reach / step + 1e-9)
    offsets = step * np.arange(-n, n + 1)  # 0 exactly in the middle
    da, de = (v.ravel() for v in np.meshgrid(offsets, offsets, indexing="ij"))
    order = np.argsort(np.hypot(da, de), kind="stable")
    light = guess.light
    return np.column_stack([light.azimuth_deg + da[order], np.clip(light.elevation_deg + de[order], -89.0, 89.0)])


def aim(
    synth: Synthesis,
    scene: Scene,
    lab: np.ndarray,
    sigmas: tuple[float, ...],
    names: tuple[str, ...],
    values: np.ndarray,
) -> tuple[Scene, list[dict]]:
    """``scene`` with the parameters ``names`` set to the row of ``values`` (N, len(names), file units), or kept at
    its own, that scores lowest on ``sigmas``, the rest of the scene held; each scored by every frame's motion from
    its nearest render in a :class:`Library` refined by :data:`LIGHT_EVALUATIONS` least-squares evaluations.
    Returns the scene and every row's values and cost (its own first)."""
    params = [next(p for p in P.PARAMETERS if p.name == name) for name in names]
    own = [p.from_fit(v) for p, v in zip(params, P.read(scene, tuple(params)))]
    tried = []
    for row in np.vstack([own, values]):
        x = P.read(scene)
        for p, v in zip(params, row):
            x = _set(x, p.name, p.to_fit(float(v)))
        candidate = P.write(scene, x)
        problem = Problem(synth, candidate, lab, sigmas)
        start = Library(synth, candidate, sigmas).nearest(lab)[0]
        cost = 0.5 * float(refine_motion(problem, start, LIGHT_EVALUATIONS)[1].sum())
        tried.append(({**{n: float(v) for n, v in zip(names, row)}, "cost": cost}, candidate))
    best = min(tried, key=lambda t: t[0]["cost"])[1]
    return best, [t[0] for t in tried]


def held_light(directions: np.ndarray, guess: Scene, held: tuple[str, ...]) -> np.ndarray:
    """The light grid's ``directions`` (N, 2: azimuth, elevation) with the ``held`` ones of the two at the guess's
    value, each direction once, in their order."""
    out = np.array(directions, dtype=np.float64)
    for column, (name, value) in enumerate(zip(LIGHT, (guess.light.azimuth_deg, guess.light.elevation_deg))):
        if name in held:
            out[:, column] = value
    _, first = np.unique(out, axis=0, return_index=True)
    return out[np.sort(first)]


def with_azimuth(start: Scene, aimed: Scene) -> Scene:
    """``start`` with the light's azimuth of ``aimed`` (the light grid's best direction), its elevation left to the
    finer stages: with each frame's curvature free, as :func:`aim` scores, a broad highlight trades the elevation
    with it (on Blender's rough and angle recordings, light at -40 deg, the grid's best was -50, and the fit from
    there ended 4.1 and 1.4 deg off), while the azimuth is the side of the camera's plane the coarse levels
    cannot tell."""
    return P.write(start, _set(P.read(start), "light.azimuth_deg", aimed.light.azimuth_deg))


def library_motion(synth: Synthesis, scene: Scene, lab: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
    """Each lab frame's nearest neighbour (K, 4) in a :class:`Library` of ``scene``."""
    return Library(synth, scene, sigmas).nearest(lab)[0]


def crop(frames: np.ndarray, scene: Scene) -> np.ndarray:
    """The ROI of full frames (N, H, W) at the scene's ``camera.roi``."""
    (x, y), cam = scene.camera.roi, scene.camera
    return frames[:, y : y + cam.height_px, x : x + cam.width_px]


def locate(synth: Synthesis, scene: Scene, footage: Footage) -> tuple[Scene, np.ndarray, float]:
    """``scene`` with its ROI moved to where the nozzle is in the lab's recorded frames (:func:`.roi.find_roi`
    on the mean frame against a render of the whole frame with the nozzle at its centre)."""
    from service.simulate import canvas

    mean = footage.stack.mean(axis=0)
    (height, width), cam = mean.shape, scene.camera
    if height < cam.height_px or width < cam.width_px:
        raise MeniscopeError(
            footage.path, f"frames {width}x{height} are smaller than the scene's ROI {cam.width_px}x{cam.height_px}"
        )
    data = scene.as_dict()
    centred = ((width - cam.width_px) // 2, (height - cam.height_px) // 2)
    data["camera"]["roi"] = list(centred)
    big, (cx, cy) = canvas(Scene.from_dict(data), (width, height))
    coeffs = CoefficientRanges().sample(64, np.random.default_rng(1))
    template = synth.stored(big, coeffs).mean(axis=0)[cy : cy + height, cx : cx + width]
    shift, score = find_roi(mean, template, reach=max(width - cam.width_px, height - cam.height_px))
    corner = np.clip(np.array(centred) + shift, 0, [width - cam.width_px, height - cam.height_px])
    return _with_roi(scene, corner), corner, score


#: Pixels round the fluid's reach left out of :func:`settle_roi`'s match (its highlights' blur).
FLUID_MARGIN_PX = 3


def settle_roi(synth: Synthesis, scene: Scene, footage: Footage, corner: np.ndarray) -> tuple[Scene, np.ndarray, float]:
    """The calibrated ``scene``'s ROI placed by its static pixels (:func:`.roi.refine_shift`: the lab's mean frame
    against the scene's static frame on the whole recorded frame, the fluid's reach and its margin masked); the
    sub-pixel corner and the correlation (0 and ``corner`` unchanged when the match fails)."""
    import cv2

    from service.simulate import canvas

    mean = footage.stack.mean(axis=0)
    height, width = mean.shape
    big, (cx, cy) = canvas(with_spheres(scene, np.zeros((0, 4))), (width, height))
    model = synth.stored(big, np.zeros((1, 4)))[0][cy : cy + height, cx : cx + width]
    renderer = synth.renderer(big)
    fluid = np.zeros(renderer.shape, np.uint8)
    fluid.ravel()[np.unique(renderer.fluid_rays.pixel)] = 1
    grow = 2 * FLUID_MARGIN_PX + 1
    static = cv2.dilate(fluid, np.ones((grow, grow), np.uint8))[cy : cy + height, cx : cx + width] == 0
    found = refine_shift(mean, model, static)
    if found is None:
        return scene, corner, 0.0
    cam = scene.camera
    sub = np.clip(np.array(cam.roi, dtype=np.float64) + found[0], 0, [width - cam.width_px, height - cam.height_px])
    return _with_roi(scene, sub), sub, found[1]


def rms_finest(synth: Synthesis, scene: Scene, motion: np.ndarray, lab: np.ndarray) -> float:
    """RMS difference (fraction of full scale) of lab frames and their synthesis, pixel by pixel."""
    return float(np.sqrt(np.mean((synth.stored(scene, motion) - lab) ** 2)))


def calibrate(
    footage: Footage,
    guess: Scene,
    schedule: tuple[Stage, ...] = SCHEDULE,
    start_alphas: tuple[float, ...] = START_ALPHAS,
    progress: bool = True,
    carry: int = CARRY,
    profiled: dict[str, tuple[float, ...]] | None = None,
    light_directions: np.ndarray | None = None,
    held: tuple[str, ...] = (),
) -> Calibration:
    """Fit ``guess`` to ``footage``: ROI, scene parameters, per-frame motion, noise, artifact spheres. Every start
    is fitted on the coarse stage and scored on the finest level; the best ``carry`` go through the finer stages,
    each from the azimuth of the light direction among ``light_directions`` (N, 2: azimuth, elevation; default
    :func:`light_grid` of the guess) and the best start's own that scores lowest on the finest level with the best
    start's scene, at its own elevation (:func:`with_azimuth`); the lowest final cost wins.
    ``profiled``: parameters whose cost is profiled at the end, with their offsets (default :data:`.profile.PROFILED`),
    the scene moved along them while a profile finds a lower cost (:func:`.profile.descend`), then to the point of them
    whose ``footage.lab_windows`` fit best held to Eq. 1 (:func:`.windows.choose`; the uncertainties stay the
    descent's). ``held``: parameters kept at the guess's value throughout (:func:`.parameters.free`): neither fitted,
    profiled, refitted along a profile nor searched by the starts or the light grid."""
    from service.calibration.profile import PROFILED, descend  # they build on this module's Problem
    from service.calibration.windows import choose, further, ridge

    began = time.perf_counter()
    synth = Synthesis()
    # an explicit (ideal) sensor block to fit, and no artifact spheres: the guess's are not where the lab's are
    # (their glints would pull the fit), and a scene without them builds several times faster; they are found
    # at the end from the static image
    base = with_spheres(P.write(guess, P.read(guess)), np.zeros((0, 4)))
    scene, corner, score = locate(synth, base, footage)
    first, finest = schedule[0], schedule[-1]
    synth.use(first)
    fitted = P.free(held)
    profiled = {
        name: offsets for name, offsets in (PROFILED if profiled is None else profiled).items() if name not in held
    }
    if "fluid.roughness" in held:
        start_alphas = ()
    light_directions = held_light(light_grid(guess) if light_directions is None else light_directions, guess, held)
    bar = tqdm(  # each start twice (coarse fit, finest score), the second ROI look, the light, the finer stages,
        # the profiles
        total=2 * (len(start_alphas) + 1) + 2 + carry * (len(schedule) - 1) + len(profiled),
        desc="calibrate",
        unit="stage",
        disable=not progress,
    )
    # several starts on the coarsest stage: the guess's roughness and the extra ones
    candidates = []
    for alpha in (None, *start_alphas):
        start = scene if alpha is None else P.write(scene, _set(P.read(scene), "fluid.roughness", math.log10(alpha)))
        lab = crop(footage.frames, start)
        motion = motion_only(synth, start, lab, first.sigmas)
        problem = Problem(synth, start, lab, first.sigmas, footage.windows, fitted=fitted)
        x, res = problem.solve(motion, first.max_evaluations)
        candidates.append((*problem.unpack(x), {"fluid.roughness": start.fluid.roughness, "cost": float(res.cost)}))
        bar.update()
    # the coarse blur cannot tell a near-mirror from a rough metal (on Blender's near-mirror the three starts end
    # within 2.4 % of each other): each start's scene is scored on the finest level, its motion refitted there
    synth.use(finest)
    for cand in candidates:
        cand_scene, lab = cand[0], crop(footage.frames, cand[0])
        fine = Problem(synth, cand_scene, lab, finest.sigmas)
        cand[2]["fine_cost"] = float(
            0.5 * fine.frame_costs(cand_scene, motion_only(synth, cand_scene, lab, finest.sigmas)).sum()
        )
        bar.update()
    starts = [c[2] for c in candidates]
    ranked = sorted(candidates, key=lambda c: c[2]["fine_cost"])[:carry]
    synth.use(first)
    residual_before = rms_finest(
        synth,
        base,
        library_motion(synth, ranked[0][0], crop(footage.frames, ranked[0][0]), first.sigmas),
        crop(footage.frames, ranked[0][0]),
    )
    again, corner_again, score_again = locate(synth, ranked[0][0], footage)  # with the scene as fitted so far
    if score_again > score:  # the better likeness decides: a fit on a wrong crop can mislead the second look
        corner, score = corner_again, score_again
    bar.update()
    # the light's azimuth from the grid, scored with the best start's scene; the best `carry` starts each from there
    # through the finer stages (alpha and the light's angle trade there), the lowest final cost wins
    synth.use(finest)
    first_start = _with_roi(ranked[0][0], corner)
    aimed, ranked[0][2]["lights"] = aim(
        synth, first_start, crop(footage.frames, first_start), finest.sigmas, LIGHT, light_directions
    )
    bar.update()
    best = None
    for cand_scene, motion, info in ranked:
        scene = with_azimuth(_with_roi(cand_scene, corner), aimed)
        info["light"] = [scene.light.azimuth_deg, scene.light.elevation_deg]
        for stage in schedule[1:]:
            synth.use(stage)
            lab = crop(footage.frames, scene)
            problem = Problem(synth, scene, lab, stage.sigmas, footage.windows, fitted=fitted)
            fresh = motion_only(synth, scene, lab, stage.sigmas)
            keep = problem.frame_costs(scene, motion) <= problem.frame_costs(scene, fresh)
            motion = np.where(keep[:, None], motion, fresh)
            x, res = problem.solve(motion, stage.max_evaluations)
            scene, motion = problem.unpack(x)
            bar.update()
        info["final_cost"] = float(res.cost)
        info["final_roughness"] = scene.fluid.roughness
        if best is None or res.cost < best[0]:
            best = (res.cost, scene, motion, _uncertainty(problem, x, res))
    _, scene, motion, sigma = best
    settled, sub, corr = settle_roi(synth, scene, footage, corner)
    if corr > 0:
        corner, score = sub, corr
        if settled.camera.roi != scene.camera.roi:  # the frames' motion again, on the crop where the nozzle is
            scene = settled
            motion = motion_only(synth, scene, crop(footage.frames, scene), finest.sigmas)
    lab, last = crop(footage.frames, scene), finest.sigmas

    def tick() -> None:  # a further round of the descent (or a point walked to) the bar did not count
        if bar.n >= bar.total:
            bar.total += 1
        bar.update()

    scene, motion, profiles, moves, refit = descend(
        synth, scene, lab, motion, last, footage.windows, profiled, each=tick, fitted=fitted
    )
    if refit is not None:
        sigma = _uncertainty(*refit)
    scored: list[dict] = []  # the ridge's points scored by whole windows (none without windows or profiled partners)
    points = ridge(scene, motion, profiles) if footage.lab_windows else []
    if len(points) > 1:
        bar.total += len(points)
        walk = partial(further, synth, lab, last, fitted=fitted)
        chosen, scored = choose(synth, points, footage.lab_windows, footage.full_scale, last, walk, tick)
        scene, motion = chosen.scene, chosen.motion
    bar.close()
    lab_stack = crop(footage.stack, scene)
    moving = _moving(synth, scene)
    noise = fit_noise(lab_stack, ~moving, scene.sensor.offset, footage.full_scale)
    scene = _with_noise(scene, noise)
    lab = crop(footage.frames, scene)
    spheres = _spheres(synth, scene, lab_stack, moving, noise, footage.full_scale)
    scene = with_spheres(scene, spheres)
    return Calibration(
        guess=guess,
        scene=scene,
        roi=(float(corner[0]), float(corner[1])),
        roi_score=score,
        motion=motion,
        sigma=sigma,
        residual_before=residual_before,
        residual_after=rms_finest(synth, scene, motion, lab),
        noise=noise,
        spheres_found=len(spheres),
        seconds=time.perf_counter() - began,
        builds=synth.builds,
        starts=starts,
        profiles=profiles,
        moves=moves,
        ridge=scored,
        finest=finest,
        held=held,
    )


def _with_roi(scene: Scene, corner: np.ndarray) -> Scene:
    """``scene`` with its ROI's corner at the nearest pixel to ``corner`` (x, y)."""
    data = scene.as_dict()
    data["camera"]["roi"] = [int(v) for v in np.rint(corner)]
    return Scene.from_dict(data)


def _set(x: np.ndarray, name: str, value: float) -> np.ndarray:
    out = x.copy()
    out[P.index(name)] = value
    return out


def _uncertainty(problem: Problem, x: np.ndarray, res: object) -> dict[str, float]:
    """1-sigma of each scene parameter (file units) at the solution ``x`` from its Jacobian (Gauss-Newton, the
    motion marginalised): ``cov = s^2 (J^T J)^+`` with ``s^2`` the residual variance. Blurred pyramid pixels
    are correlated, so this is a lower bound; a parameter the data do not constrain gets a large value."""
    jac = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    m, n = jac.shape
    s2 = 2.0 * res.cost / max(m - n, 1)
    cov = np.linalg.pinv(jac.T @ jac) * s2
    spread = np.sqrt(np.maximum(np.diag(cov)[: problem.n_scene], 0.0)) * problem.scale[: problem.n_scene]
    # the file's units: half the span of one sigma either way (a log or squared coordinate is not linear)
    return {
        p.name: abs(p.from_fit(xi + si) - p.from_fit(xi - si)) / 2
        for p, xi, si in zip(problem.fitted, x[: problem.n_scene], spread)
    }


def _moving(synth: Synthesis, scene: Scene) -> np.ndarray:
    """Pixels (h, w) of the ROI that the fluid can reach (and one pixel round them, for the PSF)."""
    import cv2

    renderer = synth.renderer(scene)
    mask = np.zeros(renderer.shape, np.uint8)
    mask.ravel()[np.unique(renderer.fluid_rays.pixel)] = 1
    return cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(bool)


def _with_noise(scene: Scene, noise: NoiseFit) -> Scene:
    data = scene.as_dict()
    data["sensor"].update(full_well_e=noise.full_well_e, read_noise_e=noise.read_noise_e)
    return Scene.from_dict(data)


def _spheres(
    synth: Synthesis, scene: Scene, lab_stack: np.ndarray, moving: np.ndarray, noise: NoiseFit, full_scale: float
) -> np.ndarray:
    """The artifact spheres (G, 4) from the static residual (lab median minus the model's static frame without them),
    looked for on the face wherever the lab's pixels are still (however near the bore), in the guess's material: a
    sphere's glint is a point source whose flux its roughness does not change (:mod:`service.render.glints`)."""
    static = synth.stored(scene, np.zeros((1, 4)))[0]
    residual = np.median(lab_stack, axis=0) - static
    sigma_median = max(noise.read_noise_fraction, 1e-4) * 1.25 / math.sqrt(len(lab_stack))
    spread = 1.4826 * float(np.median(np.abs(residual[~moving] - np.median(residual[~moving]))))
    still = still_pixels(lab_stack, noise, scene.sensor.offset, full_scale)
    allowed = still & face_pixels(scene)
    # the face's level without the fluid: by the fluid's edge its blurred light would raise the bar over a glint
    face = gaussian(synth.renderer(scene).static_frame[None], scene.sensor.blur_sigma_px)[0]
    return recover(scene, residual, allowed, max(sigma_median, spread), face)
