"""Synthetic recordings with ground truth: ejections, damped oscillations between them (Eq. 1), a camera.

``meniscope simulate`` renders them so that every analysis can be scored against known motion
(scene.md, "Recordings and ground truth"). A recording of W windows has W ejections, one every
``fps / ejection_hz`` frames, each rounded to the nearest frame (``floor(k fps / hz + 0.5)``, so a
non-integer period gives windows one frame longer or shorter); the recording ends where ejection W
would be. Window k spans frames ``[ejection k, ejection k + 1)`` and its time ``t = (frame -
start_frame) / fps`` starts at its ejection. Its first ``transient_frames`` frames show the ejection:
the meniscus bulges out towards the camera and snaps back as the droplet leaves, modelled as an
extra mode-1 amplitude ``bulge_mm * sin(pi (i + 0.5) / transient_frames)`` on frame ``i`` of the
transient, on top of the window's true motion, which holds on every frame of the window.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from service.camera_effects import CameraEffects
from service.errors import MeniscopeError, require_folder_of
from service.physics import WindowMotion
from service.recordings import open_writer
from service.scene import Scene

if TYPE_CHECKING:  # the renderer (numba) loads only when frames are rendered
    from service.render import Renderer
    from service.window_kinds import WindowKind

SCHEMA = "meniscope.truth/1"
#: Recording formats by extension and the bit depths each stores.
FORMATS: dict[str, tuple[int, ...]] = {".cine": (8, 12, 16), ".avi": (8,)}
#: Highest mode frequency allowed, as a fraction of the frame rate (Nyquist is 0.5): >= 2.9 frames per period.
MAX_FREQUENCY_FPS_FRACTION = 0.35
#: Frames rendered and written at once: bounds memory for any window length.
BATCH_FRAMES = 512


@dataclass(frozen=True)
class WindowRanges:
    """Uniform ranges each window's true motion is drawn from (phases uniform in [0, 2 pi)).

    Physically: two axisymmetric membrane modes whose frequency ratio is near l2 / l1 = 2.30
    (Bessel roots), mode 2 decaying faster (``g2 = g1 * g2_over_g1``, ``g2_over_g1 > 1``) so mode 1
    is always the dominant, longest-lasting one; decay rates 100 to 3000 /s, so within a 10 ms
    window some windows settle and some do not. Amplitudes and offsets stay inside the default
    :class:`service.physics.CoefficientRanges`, where the renders are informative and the inverse
    models are trained. Units: d, A mm; p dimensionless; f Hz; g 1/s.
    """

    d: tuple[float, float] = (-0.03, 0.03)
    p: tuple[float, float] = (-0.15, 0.15)
    A1: tuple[float, float] = (0.010, 0.025)
    A2: tuple[float, float] = (0.003, 0.012)
    f1: tuple[float, float] = (500.0, 2500.0)
    f2_over_f1: tuple[float, float] = (2.2, 2.4)
    g1: tuple[float, float] = (100.0, 1000.0)
    g2_over_g1: tuple[float, float] = (1.5, 3.0)

    def for_fps(self, fps: float) -> WindowRanges:
        """These ranges with f1's upper end lowered so f2 stays below 0.35 fps; ValueError if none is left."""
        f1_max = MAX_FREQUENCY_FPS_FRACTION * fps / self.f2_over_f1[1]
        if f1_max <= self.f1[0]:
            raise ValueError(
                f"{fps:g} frames/s cannot sample mode 2 (f2 up to {self.f1[0] * self.f2_over_f1[1]:g} Hz "
                f"needs at least {self.f1[0] * self.f2_over_f1[1] / MAX_FREQUENCY_FPS_FRACTION:g} frames/s)"
            )
        return replace(self, f1=(self.f1[0], min(self.f1[1], f1_max)))

    def sample(self, rng: np.random.Generator) -> WindowMotion:
        """One window's true motion."""
        u = lambda lohi: float(rng.uniform(*lohi))
        d, p, A1, A2, f1, g1 = u(self.d), u(self.p), u(self.A1), u(self.A2), u(self.f1), u(self.g1)
        f2, g2 = f1 * u(self.f2_over_f1), g1 * u(self.g2_over_g1)
        phi1, phi2 = u((0.0, 2 * math.pi)), u((0.0, 2 * math.pi))
        return WindowMotion(d=d, p=p, A1=A1, g1=g1, f1=f1, phi1=phi1, A2=A2, g2=g2, f2=f2, phi2=phi2)


@dataclass(frozen=True)
class Transient:
    """The ejection seen at the start of each window: a mode-1 bulge lasting ``duration_s``.

    ``bulge_mm``: range of the bulge's peak amplitude (mm, positive = out of the nozzle, towards
    the camera): about four times the largest oscillation, so the ejection stands out.
    """

    duration_s: float = 0.25e-3
    bulge_mm: tuple[float, float] = (0.06, 0.10)

    def frames(self, fps: float) -> int:
        """Frames the transient covers at ``fps`` (at least one): 5 at 19,000 frames/s."""
        return max(1, int(math.floor(self.duration_s * fps + 0.5)))

    def profile(self, n: int) -> np.ndarray:
        """Shape (n,): the bulge on each transient frame as a fraction of its peak, sin(pi (i + 0.5) / n)."""
        return np.sin(np.pi * (np.arange(n) + 0.5) / n)


def ejection_frames(windows: int, fps: float, ejection_hz: float, first: int = 0) -> np.ndarray:
    """Shape (windows + 1,): frame of ejections ``first .. first + windows``, ``floor(k fps / hz + 0.5)``
    (from ejection 0, the last one is the frame count)."""
    return np.floor((first + np.arange(windows + 1)) * (fps / ejection_hz) + 0.5).astype(np.int64)


@dataclass(frozen=True)
class Plan:
    """Everything random about a recording's windows ``first_window .. first_window + W - 1``, drawn before any
    frame is rendered (a recording plans them all from window 0; a live stream a window at a time)."""

    fps: float
    ejections: np.ndarray  # (W + 1,) int64: ejection frames, then the frame after the last window
    truths: tuple[WindowMotion, ...]  # (W,)
    bulges_mm: np.ndarray  # (W,) peak bulge of each ejection, mm
    transient_frames: int
    ranges: WindowRanges
    transient: Transient
    first_window: int = 0

    @property
    def frame_count(self) -> int:
        """The frame after the last window: the recording's frame count when the plan starts at window 0."""
        return int(self.ejections[-1])

    def window_truth(self, window: int, radius_mm: float) -> dict[str, Any]:
        """Window ``window`` of this plan as the truth sidecar lists it (scene.md, "Recordings and ground
        truth"), frames counted from the recording's first; ``radius_mm``: the nozzle's bore radius."""
        start, end, truth = int(self.ejections[window]), int(self.ejections[window + 1]), self.truths[window]
        return {
            "index": self.first_window + window,
            "start_frame": start,
            "end_frame": end,
            "oscillation_start_frame": start + self.transient_frames,
            "bulge_mm": float(self.bulges_mm[window]),
            "offset_mm": truth.offset_mm(radius_mm),
            "truth": truth.as_dict(),
        }

    def coefficients(self, window: int, start: int, stop: int) -> np.ndarray:
        """Shape (stop - start, 4), columns d, p, a, b (Eq. 1) of frames ``start..stop-1`` of a window."""
        i = np.arange(start, stop)
        coeffs = self.truths[window].coefficients(i / self.fps).to_array()
        transient = i < self.transient_frames
        coeffs[transient, 2] += self.bulges_mm[window] * self.transient.profile(self.transient_frames)[i[transient]]
        return coeffs


def plan_recording(
    windows: int,
    fps: float,
    ejection_hz: float,
    rng: np.random.Generator,
    ranges: WindowRanges = WindowRanges(),
    transient: Transient = Transient(),
    first_window: int = 0,
    kinds: Sequence[WindowKind] = (),
) -> Plan:
    """Draw the motion of windows ``first_window ..`` of the ejection schedule: one :class:`WindowMotion` and
    one bulge per window. With ``kinds`` (:mod:`service.window_kinds`), window k is of kind
    ``kinds[k % len(kinds)]``: its ranges, bulge and length come from there instead of ``ranges`` and
    ``transient.bulge_mm`` and the uniform schedule.

    Raises ValueError when the schedule's windows (``floor(fps / hz)`` frames or one more, however many
    are drawn) would be too short to hold the transient and ten frames of oscillation, or when ``fps``
    cannot sample the modes (:meth:`WindowRanges.for_fps`).
    """
    if windows < 1:
        raise ValueError(f"need at least one window, got {windows}")
    ranges = ranges.for_fps(fps)
    n_transient = transient.frames(fps)
    ejections = ejection_frames(windows, fps, ejection_hz, first_window)
    shortest = math.floor(fps / ejection_hz)  # every window has this many frames or one more
    if shortest < n_transient + 10:
        raise ValueError(
            f"an ejection every {fps / ejection_hz:.3g} frames leaves no room for the {n_transient}-frame "
            f"transient and ten frames of oscillation: lower the ejection rate"
        )
    if kinds:
        of = [kinds[(first_window + k) % len(kinds)] for k in range(windows)]
        periods = [kind.periods(first_window + k) * fps / ejection_hz for k, kind in enumerate(of)]
        ejections = ejections[0] + np.floor(np.concatenate([[0.0], np.cumsum(periods)]) + 0.5).astype(np.int64)
        if min(periods) < n_transient + 10:
            raise ValueError("a window kind's period leaves no room for the transient: lower the ejection rate")
        truths = tuple(kind.ranges.for_fps(fps).sample(rng) for kind in of)
        bulges = np.array([rng.uniform(*kind.bulge_mm) for kind in of])
        return Plan(fps, ejections, truths, bulges, n_transient, ranges, transient, first_window)
    truths = tuple(ranges.sample(rng) for _ in range(windows))
    bulges = rng.uniform(*transient.bulge_mm, size=windows)
    return Plan(fps, ejections, truths, bulges, n_transient, ranges, transient, first_window)


def canvas(scene: Scene, frame: tuple[int, int]) -> tuple[Scene, tuple[int, int]]:
    """A scene whose image holds a whole recorded ``frame`` (width, height) with the ROI at ``camera.roi``: the
    same camera and pixels, more of them, centred on the nozzle; and where the frame's corner lies in it.

    So a frame larger than the ROI shows the scene everywhere, as a real sensor would, with the nozzle
    wherever the ROI puts it (the ROI's centre is the principal point).
    """
    cam = scene.camera
    (x, y), (w, h) = cam.roi, (cam.width_px, cam.height_px)
    scene.check_roi(*frame, "--frame")
    mx, my = max(x, frame[0] - w - x), max(y, frame[1] - h - y)
    width, height = w + 2 * mx, h + 2 * my
    focal = 0.5 * w / math.tan(math.radians(cam.fov_deg) / 2)
    data = scene.as_dict()
    data["camera"].update(
        width_px=width, height_px=height, roi=[0, 0], fov_deg=math.degrees(2 * math.atan(0.5 * width / focal))
    )
    return Scene.from_dict(data), (mx - x, my - y)


class CameraFrames:
    """What the camera stores for Eq. 1 coefficients: ``renderer``'s frames (anything with ``render(coeffs (N, 4))
    -> (N, h, w)`` linear frames), cut at ``corner`` (x, y) to ``frame`` (width, height) px when given (see
    :func:`canvas`), else placed at the ROI (``camera.roi``) of a sensor that ends with it, black around it;
    then through the camera's ``effects``.
    """

    def __init__(
        self,
        scene: Scene,
        renderer: Renderer,
        effects: CameraEffects,
        frame: tuple[int, int] | None = None,
        corner: tuple[int, int] = (0, 0),
    ) -> None:
        cam = scene.camera
        x, y = cam.roi
        self.renderer, self.effects = renderer, effects
        if frame is None:
            self.width, self.height = x + cam.width_px, y + cam.height_px
            self._roi = (slice(None), slice(y, None), slice(x, None))
            self._cut = (slice(None),) * 3
        else:
            self.width, self.height = frame
            self._roi = (slice(None),) * 3
            self._cut = (slice(None), slice(corner[1], corner[1] + frame[1]), slice(corner[0], corner[0] + frame[0]))
        self._linear = np.zeros((0, self.height, self.width), np.float32)  # linear, black outside the ROI

    def take(self, coeffs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Stored pixels (N, height, width), uint8 or uint16, of coefficients (N, 4); ``rng`` draws the noise."""
        n = len(coeffs)
        if n > len(self._linear):
            self._linear = np.zeros((n, self.height, self.width), np.float32)
        linear = self._linear[:n]
        linear[self._roi] = self.renderer.render(coeffs)[self._cut]
        return self.effects.apply(linear, rng)


def truth_path(recording: str | Path) -> Path:
    """The ground-truth sidecar of a recording: its extension replaced by ``.truth.json``."""
    recording = Path(recording)
    return recording.with_name(recording.stem + ".truth.json")


def truth_document(
    plan: Plan,
    scene: Scene,
    recording: Path,
    effects: CameraEffects,
    seed: int,
    ejection_hz: float,
    noise: str | None,
    renderer: str,
    frame: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """The sidecar's content (scene.md, "Recordings and ground truth"): JSON-safe, finite numbers."""
    x, y = scene.camera.roi
    width, height = frame or (x + scene.camera.width_px, y + scene.camera.height_px)
    return {
        "schema": SCHEMA,
        "recording": {
            "path": recording.name,
            "frames": plan.frame_count,
            "fps": scene.camera.fps,
            "width": width,
            "height": height,
            "bit_depth": effects.bit_depth,
        },
        "scene": scene.as_dict(),
        "scene_sha256": scene.sha256,
        "seed": seed,
        "renderer": renderer,
        "ejection_hz": ejection_hz,
        "ejections": [int(e) for e in plan.ejections[:-1]],
        "time_origin": "t = (frame - start_frame) / fps, start_frame being the window's ejection",
        "transient": {
            "frames": plan.transient_frames,
            "duration_s": plan.transient.duration_s,
            "model": "a += bulge_mm * sin(pi * (frame - start_frame + 0.5) / frames) on the first `frames` "
            "frames of each window, on top of the true motion",
        },
        "ranges": {name: list(lohi) for name, lohi in asdict(plan.ranges).items()},
        "camera_effects": effects.model_dump(mode="json"),
        "noise": noise,
        "windows": [plan.window_truth(k, scene.nozzle.radius_mm) for k in range(len(plan.truths))],
    }


def check_output(out: Path, bit_depth: int) -> None:
    """Refuse a recording path or bit depth the writers cannot produce, before any rendering."""
    ext = out.suffix.lower()
    if ext not in FORMATS:
        raise MeniscopeError(out, f"unknown recording format {out.suffix or '(none)'!r}: use .cine or .avi")
    if bit_depth not in FORMATS[ext]:
        raise MeniscopeError(out, f"{ext} stores bit depths {list(FORMATS[ext])}, not {bit_depth}")
    require_folder_of(out)
    if not os.access(out.parent, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise MeniscopeError(out, "not writable")


def simulate(
    scene: Scene,
    out: str | Path,
    *,
    windows: int,
    seed: int,
    ejection_hz: float = 100.0,
    effects: CameraEffects = CameraEffects(),
    noise: str | None = None,
    ranges: WindowRanges = WindowRanges(),
    transient: Transient = Transient(),
    renderer: Renderer | None = None,
    frame: tuple[int, int] | None = None,
    kinds: Sequence[WindowKind] = (),
    kind_names: Sequence[str] = (),
) -> dict[str, Any]:
    """Render, pass through the camera and write a recording plus its ``.truth.json``; returns the truth.

    Deterministic by ``seed``: the motion comes from the first child of ``SeedSequence(seed)``, the
    camera noise of window k from child k of its second child. Frames outside the scene's ROI
    (``camera.roi``) are black before the camera effects. ``noise`` names the preset ``effects``
    came from, for the record; ``frame``: the recorded (width, height) when larger than the ROI (the renderer then
    renders :func:`canvas`'s scene); ``renderer`` is anything with ``render(coeffs (N, 4)) -> (N, H, W)`` linear
    frames, ours by default (``service.render.blender.BlenderRenderer`` for a second renderer), and the
    truth names its class. ``kinds`` (named ``kind_names`` in the truth) draw window k as
    ``kinds[k % len(kinds)]`` (:mod:`service.window_kinds`), spatter included. Memory stays bounded: at most :data:`BATCH_FRAMES` frames at once.
    """
    out = Path(out)
    check_output(out, effects.bit_depth)
    cam = scene.camera
    motion_seed, noise_seed = np.random.SeedSequence(seed).spawn(2)
    try:
        plan = plan_recording(
            windows, cam.fps, ejection_hz, np.random.default_rng(motion_seed), ranges, transient, kinds=kinds
        )
    except ValueError as exc:
        raise MeniscopeError(out, str(exc)) from None
    shown, corner = canvas(scene, frame) if frame else (scene, (0, 0))
    if renderer is None:
        from service.render import Renderer

        renderer = Renderer(shown)
    camera = CameraFrames(scene, renderer, effects, frame, corner)
    sidecar = truth_path(out)
    try:
        with (
            open_writer(out, camera.width, camera.height, cam.fps, bit_depth=effects.bit_depth) as writer,
            tqdm(total=plan.frame_count, unit="frame", desc=f"simulate {out.name}", disable=None) as bar,
        ):
            for k, window_seed in enumerate(noise_seed.spawn(windows)):
                rng = np.random.default_rng(window_seed)
                length = int(plan.ejections[k + 1] - plan.ejections[k])
                for start in range(0, length, BATCH_FRAMES):
                    stop = min(length, start + BATCH_FRAMES)
                    frames = camera.take(plan.coefficients(k, start, stop), rng)
                    if kinds:
                        from service.window_kinds import spatter

                        spatter(frames, kinds[k % len(kinds)].spatter, 2**effects.bit_depth - 1, rng)
                    writer.write(frames, None)
                    bar.update(stop - start)
        truth = truth_document(
            plan, scene, out, effects, seed, ejection_hz, noise, type(renderer).__name__, (camera.width, camera.height)
        )
        if isinstance(getattr(renderer, "sun_samples", None), int):  # ours: how finely it drew the sun's disc
            truth["sun_samples"] = renderer.sun_samples
        for k, window in enumerate(truth["windows"]) if kind_names else ():
            window["kind"] = kind_names[k % len(kind_names)]
        try:
            sidecar.write_text(json.dumps(truth, indent=1, allow_nan=False) + "\n")
        except OSError as exc:
            raise MeniscopeError(sidecar, f"cannot write the ground truth: {exc.strerror or exc}") from None
    except BaseException:
        out.unlink(missing_ok=True)
        sidecar.unlink(missing_ok=True)
        raise
    return truth
