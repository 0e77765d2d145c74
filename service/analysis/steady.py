"""Eq. 1 within a window: d and p hold still between ejections, only a and b oscillate.

The window fit therefore takes each window's steady D(0, t): its d + p R once (medians) plus each
frame's a + b, in ``meniscope analyze`` and ``meniscope serve`` alike.
"""

from __future__ import annotations

import numpy as np

from service.medians import nanmedian
from service.physics import centre_displacement


def window_steady_centre(
    coefficients: np.ndarray, radius_mm: float, transient: int, starts_at_ejection: bool
) -> np.ndarray:
    """D(0, t) of one window's frames as Eq. 1 has it: the window's d + p R (medians over its frames, after
    the ``transient`` frames of the ejection when it starts at one) plus each frame's a + b.
    (m, 4) -> (m,), mm; NaN rows stay NaN.

    Eq. 1 holds d and p constant between ejections; taking them per frame would add their per-frame
    estimation noise to the oscillation (on the shipped models it is most of the D(0, t) error).
    """
    d, p, a, b = np.asarray(coefficients, np.float64).T
    skip = transient if starts_at_ejection else 0
    lo = skip if len(d) > skip else 0
    # a window whose frames are all missing: NaN, which the fit reports
    return centre_displacement(nanmedian(d[lo:]), nanmedian(p[lo:]), a, b, radius_mm)
