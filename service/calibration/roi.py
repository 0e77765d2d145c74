"""Where the nozzle sits in a recorded frame larger than the ROI: the scene's ROI found by correlation.

The fluid's highlights move with the unknown material and light, the nozzle's outline does not, so the
lab's mean frame and a render of the whole frame are compared by their edges (the magnitude of the
Laplacian of the blurred image): the face's outer edge and the bore's rim.
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
