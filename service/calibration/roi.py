"""Where the nozzle sits in a recorded frame larger than the ROI: the scene's ROI found by correlation.

The fluid's highlights move with the unknown material and light, the nozzle's outline does not, so the
lab's mean frame and a render of the whole frame are compared by their edges (the magnitude of the
Laplacian of the blurred image): the face's outer edge and the bore's rim. Once the scene is calibrated,
:func:`refine_shift` places it to a fraction of a pixel by the static pixels alone (the fluid's reach masked).
"""

from __future__ import annotations

import cv2
import numpy as np

#: Blur (px) before the Laplacian: edges a few pixels wide survive a guess that is off.
EDGE_BLUR_PX = 1.5


def edges(image: np.ndarray) -> np.ndarray:
    """Edge strength of an image (h, w): |Laplacian| of its Gaussian blur, float32."""
    blurred = cv2.GaussianBlur(image.astype(np.float32), (0, 0), EDGE_BLUR_PX, borderType=cv2.BORDER_REPLICATE)
    return np.abs(cv2.Laplacian(blurred, cv2.CV_32F))


def find_roi(lab: np.ndarray, template: np.ndarray, reach: int) -> tuple[np.ndarray, float]:
    """Shift (x, y), sub-pixel, that best lays ``template`` (a render of the whole frame) on ``lab`` (same shape),
    within ``reach`` px, and the peak's normalised correlation of their edges (1: same outline). Sub-pixel by
    a parabola through the peak and its neighbours on each axis."""
    pad = max(1, reach)
    img = cv2.copyMakeBorder(edges(lab), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    score = cv2.matchTemplate(img, edges(template), cv2.TM_CCOEFF_NORMED)
    y, x = np.unravel_index(int(np.argmax(score)), score.shape)
    shift = np.array([x - pad, y - pad], dtype=np.float64)
    for axis, (i, n) in enumerate(((x, score.shape[1]), (y, score.shape[0]))):
        if 0 < i < n - 1:
            at = (lambda j: score[y, j]) if axis == 0 else (lambda j: score[j, x])
            left, mid, right = at(i - 1), at(i), at(i + 1)
            curve = left - 2 * mid + right
            if curve < 0:
                shift[axis] += float(np.clip(0.5 * (left - right) / curve, -0.5, 0.5))
    return shift, float(score.max())


#: Largest correction (px) :func:`refine_shift` may make: beyond it the match has locked on something else.
REFINE_REACH_PX = 3.0


def refine_shift(lab: np.ndarray, model: np.ndarray, static: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Sub-pixel shift (x, y) by which the nozzle in ``lab`` (a mean frame) sits from where it is in ``model`` (the
    calibrated scene's static frame, same shape), matched on the ``static`` pixels of the model only (ECC,
    translation), and the correlation; None when the match fails or lands beyond :data:`REFINE_REACH_PX`. The
    fluid's highlights sit wherever each frame's fitted motion put them, so only what does not move can say
    where the ROI is (on Blender recordings the whole-frame match was 1-1.4 px off, this 0.05-0.5 px)."""
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    try:
        corr, warp = cv2.findTransformECC(
            lab.astype(np.float32),
            model.astype(np.float32),
            warp,
            cv2.MOTION_TRANSLATION,
            criteria,
            static.astype(np.uint8),
            3,
        )
    except cv2.error:
        return None
    shift = -warp[:, 2].astype(np.float64)
    if not np.all(np.isfinite(shift)) or np.abs(shift).max() > REFINE_REACH_PX:
        return None
    return shift, float(corr)
