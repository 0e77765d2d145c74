"""A camera with ground truth: ``sim://?seed=3&noise=lab&speed=0.05``, frames rendered live from the physics model.

What ``meniscope simulate`` writes to a file (:mod:`service.simulate`), as an endless stream: an ejection
every ``1 / ejection_hz`` (:func:`~service.simulate.ejection_frames`), each window's damped oscillation
(Eq. 1) drawn from :class:`~service.simulate.WindowRanges` with its ejection's
:class:`~service.simulate.Transient`, rendered by the scene's :class:`~service.render.Renderer` into its
ROI of the sensor (black around it, :class:`~service.simulate.CameraFrames`) at its frame rate and passed
through a camera preset (:data:`~service.camera_effects.NOISE_PRESETS`). Frame ``i`` is at ``i / fps`` s,
ejection 0 at frame 0. Windows are drawn one after another from the seed and rendered in blocks of
:data:`BLOCK_FRAMES` inside each window, each window's noise from a generator of its own, so the same
seed gives the same frames however they are read. :meth:`SimulatedSource.describe` shows the truth of
the window of the last frame delivered, as the truth sidecar lists it.

Speed: the renderer cannot keep the camera's 19,000 frames/s on two cores. At the default quality (one
ray per pixel, four sun directions: the shipped network's errors on such renders matched those on the
training renders' two by two rays, at a quarter of the cost) this source made 2,000-2,400 frames/s of
the default scene with one render thread on a two-core machine under a load of 3 to 5, and 1,200-1,600
through the "lab" camera (its blur and noise cost as much as the render); two threads were no faster
there. So ``speed`` defaults to "max": frames come as fast as they render, at whatever rate the
machine allows, their timestamps still on the camera's clock. A speed above 0 paces them like a replay
(:class:`~service.sources.pacing.Pacer`; 0.05 is 950 frames/s); one faster than the renderer delivers
every frame, later and later. ``threads`` (default 1) leaves the other cores to inference and the fits.
"""

from __future__ import annotations

import functools
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args
from urllib.parse import SplitResult

import numpy as np
from pydantic import Field, field_validator

from service import DEFAULT_SCENE
from service.camera_effects import NOISE_PRESETS, BitDepth, noise_preset, pixel_dtype
from service.errors import MeniscopeError
from service.scene import Scene
from service.simulate import CameraFrames, Plan, plan_recording
from service.sources.base import FrameBatch, FrameSource, SourceOptions, StreamFormat, parse_options
from service.sources.pacing import Pacer, Speed

if TYPE_CHECKING:  # the renderer (numba) loads when a simulated source opens
    from service.render import Renderer

#: Frames rendered at once inside a window: a read that reaches its timeout overruns it by one block at most.
BLOCK_FRAMES = 32


class SimulatedOptions(SourceOptions):
    speed: Speed = 0.0
    seed: int = Field(0, ge=0, description="seed of the motion and the noise")
    noise: str = Field("lab", description=f"camera preset: {', '.join(NOISE_PRESETS)}")
    bit_depth: int = Field(12, description="stored bits per pixel: 8, 10, 12 or 16")
    ejection_hz: float = Field(100.0, gt=0, allow_inf_nan=False, description="ejections per second")
    supersample: int = Field(1, ge=1, le=8, description="rays per pixel along each axis")
    sun_samples: int = Field(4, ge=1, le=64, description="directions over the sun's disc")
    threads: int = Field(1, ge=1, le=64, description="render threads")
    scene: Path = Field(DEFAULT_SCENE, description="scene file (the service passes its own)")

    @field_validator("noise")
    @classmethod
    def _a_preset(cls, value: str) -> str:
        if value not in NOISE_PRESETS:
            raise ValueError(f"choose one of {', '.join(NOISE_PRESETS)}")
        return value

    @field_validator("bit_depth")
    @classmethod
    def _a_camera_depth(cls, value: int) -> int:
        if value not in get_args(BitDepth):
            raise ValueError(f"choose one of {', '.join(map(str, get_args(BitDepth)))}")
        return value


@functools.lru_cache(maxsize=2)
def scene_renderer(scene_json: str, supersample: int, sun_samples: int, threads: int) -> Renderer:
    """A renderer of the scene (canonical JSON), kept for the next opening: shading the static scene takes a
    second or more, and the service reopens its source after every failure. It has rendered one frame, so
    numba has compiled the ray tracer (a minute on a fresh install) before a stream's clock starts."""
    from service.render import Renderer

    renderer = Renderer(Scene.model_validate_json(scene_json), supersample, sun_samples, threads=threads)
    renderer.render(np.zeros((1, 4)))
    return renderer


class SimulatedSource(FrameSource):
    """Frames of the scene's damped oscillations and ejections, rendered as they are read (module docstring).

    ``clock`` and ``sleep`` pace the stream (tests pass a simulated clock).
    """

    kind = "simulated"

    def __init__(
        self,
        scene: str | Path = DEFAULT_SCENE,
        *,
        seed: int = 0,
        noise: str = "lab",
        bit_depth: BitDepth = 12,
        ejection_hz: float = 100.0,
        speed: float = 0.0,
        supersample: int = 1,
        sun_samples: int = 4,
        threads: int = 1,
        timeout: float = 0.1,
        uri: str = "sim://",
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__(uri, timeout)
        self.scene_path, self.seed, self.noise, self.ejection_hz = Path(scene), seed, noise, ejection_hz
        self.effects = noise_preset(noise, bit_depth)
        self.speed, self.quality = speed, (supersample, sun_samples, threads)
        self._clock = clock
        self._pacer = Pacer(speed, clock, sleep)
        self._scene: Scene | None = None
        self._camera: CameraFrames | None = None
        self._motion = np.random.default_rng()
        self._noise_seeds = np.random.SeedSequence()
        self._plans: deque[Plan] = deque()  # windows from that of the last frame delivered to the one rendering
        self._window_rng = np.random.default_rng()  # the noise of the window being rendered
        self._rendered_in_window = 0
        self._pending: list[np.ndarray] = []  # rendered frames not yet delivered, the first being frame _next
        self._next = 0

    @classmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> SimulatedSource:
        if parts.netloc or parts.path not in ("", "/"):
            raise MeniscopeError(uri, "a simulated source has no host or path: sim://?seed=3&noise=lab&speed=0.05")
        o = parse_options(SimulatedOptions, uri, options)
        return cls(
            o.scene,
            seed=o.seed,
            noise=o.noise,
            bit_depth=o.bit_depth,  # type: ignore[arg-type]
            ejection_hz=o.ejection_hz,
            speed=o.speed,
            supersample=o.supersample,
            sun_samples=o.sun_samples,
            threads=o.threads,
            timeout=o.timeout,
            uri=uri,
        )

    def _open(self) -> StreamFormat:
        scene = Scene.load(self.scene_path)
        self._scene = scene
        motion, noise = np.random.SeedSequence(self.seed).spawn(2)  # as `meniscope simulate` splits its seed
        self._motion, self._noise_seeds = np.random.default_rng(motion), noise
        self._plans.clear()
        self._start_window(0)  # refuses an ejection rate or frame rate the windows cannot hold
        self._camera = CameraFrames(scene, scene_renderer(scene.to_json(), *self.quality), self.effects)
        self._pending, self._next = [], 0
        self._pacer.start(0.0)
        bits = self.effects.bit_depth
        return StreamFormat(self._camera.width, self._camera.height, pixel_dtype(bits), bits, scene.camera.fps)

    def _start_window(self, window: int) -> None:
        """Draw window ``window``'s motion and noise generator; its frames render from the next block on."""
        assert self._scene is not None
        try:
            plan = plan_recording(1, self._scene.camera.fps, self.ejection_hz, self._motion, first_window=window)
        except ValueError as exc:
            raise MeniscopeError(self.uri, str(exc)) from None
        self._plans.append(plan)
        self._window_rng = np.random.default_rng(self._noise_seeds.spawn(1)[0])  # window k: child k
        self._rendered_in_window = 0

    def _render_block(self) -> None:
        """Render the next block of frames (at most :data:`BLOCK_FRAMES`, never across an ejection)."""
        assert self._camera is not None
        plan = self._plans[-1]
        start, length = self._rendered_in_window, int(plan.ejections[1] - plan.ejections[0])
        stop = min(length, start + BLOCK_FRAMES)
        self._pending.append(self._camera.take(plan.coefficients(0, start, stop), self._window_rng))
        self._rendered_in_window = stop
        if stop == length:
            self._start_window(plan.first_window + 1)

    def _rendered(self) -> int:
        """The frame after the last one rendered."""
        return self._next + sum(len(p) for p in self._pending)

    def _read(self, max_frames: int) -> FrameBatch:
        start, fps = self._next, self.fps
        deadline = self._clock() + self.timeout
        while self._rendered() < start + max_frames and (self._rendered() == start or self._clock() < deadline):
            self._render_block()
        times = np.arange(start, min(self._rendered(), start + max_frames)) / fps
        self._pacer.wait(float(times[-1]), deadline - self._clock())
        due = int(np.searchsorted(times, self._pacer.now(), side="right"))
        if due == 0:
            return self.empty_batch()
        pixels = self._pending[0] if len(self._pending) == 1 else np.concatenate(self._pending)
        self._pending = [pixels[due:]] if due < len(pixels) else []
        self._next += due
        while len(self._plans) > 1 and self._plans[1].ejections[0] < self._next:
            self._plans.popleft()  # the last frame delivered lies beyond this window
        return FrameBatch(pixels[:due], np.arange(start, start + due, dtype=np.int64), times[:due])

    def _close(self) -> None:
        self._camera, self._pending = None, []

    def _details(self) -> dict[str, Any]:
        window = None
        if self._next > 0 and self._plans and self._scene is not None:
            window = self._plans[0].window_truth(0, self._scene.nozzle.radius_mm)
        supersample, sun_samples, threads = self.quality
        return {
            "scene": str(self.scene_path),
            "seed": self.seed,
            "noise": self.noise,
            "speed": self.speed,
            "ejection_hz": self.ejection_hz,
            "supersample": supersample,
            "sun_samples": sun_samples,
            "threads": threads,
            "position": self._next,
            "transient_frames": self._plans[0].transient_frames if self._plans else None,
            "window": window,
        }
