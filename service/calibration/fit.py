"""Analysis by synthesis: the scene and the motion of K lab frames fitted jointly, coarse to fine, from several starts.

Unknowns: the scene parameters of :data:`.parameters.PARAMETERS` and Eq. 1's (d, p, a, b) of every fitted
frame (motion per frame: it needs no segmentation and holds in the ejection's transient too). Each stage
is one bounded least-squares problem (scipy's trust-region reflective) on the blurred pyramid of
:mod:`.synthesis`, its Jacobian by finite differences with the frames' independence declared (a frame's
residuals depend on its own motion only), so a step costs one renderer per scene parameter plus four
renders of all frames. Before the first stage each frame's motion starts at its nearest neighbour in a
library rendered with the candidate scene; the ROI is found before the first stage and again after it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from tqdm import tqdm

from service.calibration import parameters as P
from service.calibration.artifacts import face_pixels, recover, with_spheres
from service.calibration.footage import Footage
from service.calibration.noise import NoiseFit, fit_noise
from service.calibration.roi import find_roi
from service.calibration.synthesis import Synthesis, pyramid
from service.errors import MeniscopeError
from service.physics import CoefficientRanges
from service.scene import Scene

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
    """One coarse-to-fine stage: the pyramid's blur levels (px), rays per pixel per axis, evaluations allowed."""

    sigmas: tuple[float, ...]
    supersample: int
    max_evaluations: int


SCHEDULE = (Stage((6.0, 3.0), 1, 10), Stage((3.0, 1.5), 1, 10), Stage((1.5, 0.7), 2, 8))
#: Fluid roughness (GGX alpha) of the extra starts: a near-mirror and a rough metal.
START_ALPHAS = (0.004, 0.1)


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


class Problem:
    """The least-squares problem of one stage: lab pyramid, synthesis, the scene parameters and K frames' motion."""

    def __init__(self, synth: Synthesis, base: Scene, lab: np.ndarray, sigmas: tuple[float, ...]) -> None:
        self.synth, self.base, self.sigmas = synth, base, sigmas
        self.target = pyramid(lab, sigmas)  # (K, Q)
        self.k = len(lab)
        self.n_scene = len(P.PARAMETERS)
        self.x0 = P.read(base)
        lo, hi = P.bounds(base)
        self.low = np.concatenate([lo, np.tile(MOTION_LOW, self.k)])
        self.high = np.concatenate([hi, np.tile(MOTION_HIGH, self.k)])
        self.scale = np.concatenate([SCENE_SCALE, np.tile(MOTION_SCALE, self.k)])

    def unpack(self, x: np.ndarray) -> tuple[Scene, np.ndarray]:
        return P.write(self.base, x[: self.n_scene]), x[self.n_scene :].reshape(self.k, 4)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        scene, motion = self.unpack(x)
        return (self.synth.levels(scene, motion, self.sigmas) - self.target).ravel()

    def sparsity(self) -> lil_matrix:
        """Which residual depends on which unknown: all on the scene, frame k's on its own motion only."""
        q = self.target.shape[1]
        m = lil_matrix((self.k * q, self.n_scene + 4 * self.k), dtype=np.int8)
        m[:, : self.n_scene] = 1
        for k in range(self.k):
            m[k * q : (k + 1) * q, self.n_scene + 4 * k : self.n_scene + 4 * k + 4] = 1
        return m

    def solve(self, motion: np.ndarray, max_evaluations: int) -> tuple[np.ndarray, object]:
        """Least squares from the base scene and ``motion``, in units of ``scale`` around the start."""
        start = np.clip(np.concatenate([self.x0, motion.ravel()]), self.low, self.high)
        fun = lambda u: self.residuals(start + u * self.scale)
        res = least_squares(
            fun,
            np.zeros_like(start),
            bounds=((self.low - start) / self.scale, (self.high - start) / self.scale),
            jac_sparsity=self.sparsity(),
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
    problem = Problem(synth, scene, lab, sigmas)
    k, q = problem.target.shape
    scale = np.tile(MOTION_SCALE, k)
    low, high = np.tile(MOTION_LOW, k), np.tile(MOTION_HIGH, k)
    sparsity = lil_matrix((k * q, 4 * k), dtype=np.int8)
    for i in range(k):
        sparsity[i * q : (i + 1) * q, 4 * i : 4 * i + 4] = 1
    fixed = P.read(scene)
    best, best_cost = None, None
    for start in Library(synth, scene, sigmas, size=1500).nearest(lab, starts):
        x0 = np.clip(start.ravel(), low, high)
        fun = lambda u, x0=x0: problem.residuals(np.concatenate([fixed, x0 + u * scale]))
        res = least_squares(
            fun,
            np.zeros_like(x0),
            bounds=((low - x0) / scale, (high - x0) / scale),
            jac_sparsity=sparsity,
            diff_step=DIFF_STEP,
            max_nfev=max_evaluations,
            method="trf",
            tr_solver="lsmr",
        )
        motion = (x0 + res.x * scale).reshape(k, 4)
        cost = (res.fun.reshape(k, q) ** 2).sum(axis=1)
        if best is None:
            best, best_cost = motion, cost
        else:
            better = cost < best_cost
            best[better], best_cost[better] = motion[better], cost[better]
    return best


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


def rms_finest(synth: Synthesis, scene: Scene, motion: np.ndarray, lab: np.ndarray) -> float:
    """RMS difference (fraction of full scale) of lab frames and their synthesis, pixel by pixel."""
    return float(np.sqrt(np.mean((synth.stored(scene, motion) - lab) ** 2)))


def calibrate(
    footage: Footage,
    guess: Scene,
    schedule: tuple[Stage, ...] = SCHEDULE,
    start_alphas: tuple[float, ...] = START_ALPHAS,
    progress: bool = True,
) -> Calibration:
    """Fit ``guess`` to ``footage``: ROI, scene parameters, per-frame motion, noise, artifact spheres."""
    began = time.perf_counter()
    synth = Synthesis(supersample=schedule[0].supersample)
    # an explicit (ideal) sensor block to fit, and no artifact spheres: the guess's are not where the lab's are
    # (their glints would pull the fit), and a scene without them builds several times faster; they are found
    # at the end from the static image
    base = with_spheres(P.write(guess, P.read(guess)), np.zeros((0, 4)))
    scene, corner, score = locate(synth, base, footage)
    first = schedule[0]
    bar = tqdm(total=len(start_alphas) + 1 + len(schedule) - 1, desc="calibrate", unit="stage", disable=not progress)
    # several starts on the coarsest stage: the guess's roughness and the extra ones
    starts, best = [], None
    for alpha in (None, *start_alphas):
        start = scene if alpha is None else P.write(scene, _set(P.read(scene), "fluid.roughness", math.log10(alpha)))
        lab = crop(footage.frames, start)
        motion = motion_only(synth, start, lab, first.sigmas)
        problem = Problem(synth, start, lab, first.sigmas)
        x, res = problem.solve(motion, first.max_evaluations)
        starts.append({"fluid.roughness": start.fluid.roughness, "cost": float(res.cost)})
        if best is None or res.cost < best[0]:
            best = (res.cost, problem.unpack(x))
        bar.update()
    scene, motion = best[1]
    residual_before = rms_finest(
        synth,
        base,
        library_motion(synth, scene, crop(footage.frames, scene), first.sigmas),
        crop(footage.frames, scene),
    )
    again, corner_again, score_again = locate(synth, scene, footage)  # with the scene as fitted so far
    if score_again > score:  # the better likeness decides: a fit on a wrong crop can mislead the second look
        scene, corner, score = again, corner_again, score_again
    bar.update()
    sigma: dict[str, float] = {}
    for stage in schedule[1:]:
        synth.quality["supersample"] = stage.supersample
        lab = crop(footage.frames, scene)
        problem = Problem(synth, scene, lab, stage.sigmas)
        fresh = motion_only(synth, scene, lab, stage.sigmas)
        keep = _frame_costs(problem, scene, motion) <= _frame_costs(problem, scene, fresh)
        motion = np.where(keep[:, None], motion, fresh)
        x, res = problem.solve(motion, stage.max_evaluations)
        scene, motion = problem.unpack(x)
        sigma = _uncertainty(problem, x, res)
        bar.update()
    bar.close()
    lab_stack = crop(footage.stack, scene)
    moving = _moving(synth, scene)
    noise = fit_noise(lab_stack, ~moving, scene.sensor.offset, footage.full_scale)
    scene = _with_noise(scene, noise)
    spheres = _spheres(synth, scene, lab_stack, moving, noise)
    scene = with_spheres(scene, spheres if spheres is not None else np.zeros((0, 4)))
    lab = crop(footage.frames, scene)
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
        spheres_found=0 if spheres is None else len(spheres),
        seconds=time.perf_counter() - began,
        builds=synth.builds,
        starts=starts,
    )


def _frame_costs(problem: Problem, scene: Scene, motion: np.ndarray) -> np.ndarray:
    """Each frame's squared residual (K,) for ``motion`` in ``scene``."""
    r = problem.residuals(np.concatenate([P.read(scene), motion.ravel()]))
    return (r.reshape(problem.k, -1) ** 2).sum(axis=1)


def _with_roi(scene: Scene, corner: np.ndarray) -> Scene:
    """``scene`` with its ROI's corner at the nearest pixel to ``corner`` (x, y)."""
    data = scene.as_dict()
    data["camera"]["roi"] = [int(v) for v in np.rint(corner)]
    return Scene.from_dict(data)


def _set(x: np.ndarray, name: str, value: float) -> np.ndarray:
    out = x.copy()
    out[[p.name for p in P.PARAMETERS].index(name)] = value
    return out


def _uncertainty(problem: Problem, x: np.ndarray, res: object) -> dict[str, float]:
    """1-sigma of each scene parameter (file units) at the solution ``x`` from its Jacobian (Gauss-Newton, the
    motion marginalised): ``cov = s^2 (J^T J)^+`` with ``s^2`` the residual variance. Blurred pyramid pixels
    are correlated, so this is a lower bound; a parameter the data do not constrain gets a large value."""
    jac = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    m, n = jac.shape
    s2 = 2.0 * res.cost / max(m - n, 1)
    cov = np.linalg.pinv(jac.T @ jac) * s2
    spread = np.sqrt(np.maximum(np.diag(cov)[: problem.n_scene], 0.0)) * SCENE_SCALE  # fitted coordinates
    return {
        p.name: float(p.from_fit(xi) * math.log(10) * si) if p.log else float(si)
        for p, xi, si in zip(P.PARAMETERS, x[: problem.n_scene], spread)
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


def _spheres(synth: Synthesis, scene: Scene, lab_stack: np.ndarray, moving: np.ndarray, noise: NoiseFit):
    """The artifact spheres from the static residual (lab median minus the model's static frame without them)."""
    static = synth.stored(scene, np.zeros((1, 4)))[0]
    residual = np.median(lab_stack, axis=0) - static
    sigma_median = max(noise.read_noise_fraction, 1e-4) * 1.25 / math.sqrt(len(lab_stack))
    spread = 1.4826 * float(np.median(np.abs(residual[~moving] - np.median(residual[~moving]))))
    found = recover(scene, residual, ~moving & face_pixels(scene), max(sigma_median, spread))
    return found if len(found) else None
