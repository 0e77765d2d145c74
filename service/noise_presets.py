"""The camera noise presets by name, apart from the noise model itself (:mod:`service.camera_effects`, which
loads numpy, OpenCV and pydantic), so that ``meniscope --help`` can list them without loading it."""

from __future__ import annotations

#: Noise presets for ``meniscope simulate --noise``: (full well e-, read noise e-, PSF sigma px,
#: black level). "lab" is a guess at a Phantom CMOS sensor (~16k e- well, ~20 e- read noise),
#: not a calibration.
NOISE_PRESETS: dict[str, tuple[float, float, float, float]] = {
    "none": (0.0, 0.0, 0.0, 0.0),
    "low": (40000.0, 10.0, 0.5, 0.0),
    "lab": (16000.0, 20.0, 0.7, 0.01),
    "high": (4000.0, 30.0, 1.0, 0.02),
}
