"""The sensor's noise from the lab's own frames: static pixels' temporal variance against their mean.

Outside the bore nothing moves, so a static pixel's spread over time is the camera's noise alone:
``var = read^2 + (mean - black) / full_well`` in fractions of full scale (shot noise grows with the
signal, read noise does not; a quantisation step adds 1/12 of a step squared). Under a couple of steps of noise
(an 8-bit camera's) that last term is not exact: still pixels whose levels sit near a rounding boundary split their
samples between two levels whatever the noise, and the variance line goes far wrong on such a camera
(docs/calibration.md). There the noise is fitted to the pixels' own levels instead: the likelihood of the rounded
Gaussian (:func:`fit_rounded`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize, minimize_scalar
from scipy.special import ndtr

#: Most refits of the noise line without the pixels far above it (it settles in four or five).
ROUNDS = 20
#: Read noise (quantisation steps) under which the moments' uniform step^2 / 12 is not trusted and the noise is
#: fitted to the rounded levels (:func:`fit_rounded`); from about half a step of Gaussian noise up Sheppard's
#: correction holds on average, not on a few levels near a boundary.
ROUNDED_BELOW_STEPS = 2.0
#: A noise fitted to the rounded levels counts as identified where the likelihood, with the read noise this factor
#: either way (the shot noise refitted), is worse by at least :data:`LIKELIHOOD_DROP` (the 95 % point of a
#: likelihood ratio of one parameter, 3.84 / 2); the moments' fit, from :data:`ROUNDED_BELOW_STEPS` up, is. The read
#: noise is what every pixel's noise rests on; the full well is told only as far as the still pixels span signal.
FACTOR, LIKELIHOOD_DROP = 1.25, 1.92
#: Read noises (DN) the likelihood is profiled over before it is refined, and the bounds of the searches: read noise
#: as log(DN), shot noise as log(DN^2 per DN).
READ_GRID = tuple(float(r) for r in np.geomspace(0.03, 2.5, 10))
READ_BOUNDS, GAIN_BOUNDS = (math.log(0.01), 2.0), (-12.0, 4.0)
#: The one-dimensional searches stop at a thousandth of a log unit.
BOUNDED = {"xatol": 1e-3}
#: Golden-section steps of each pixel's own level (from its mean +- half a step: to 1e-4 of a step).
LEVEL_STEPS = 20


@dataclass(frozen=True)
class NoiseFit:
    """Full well (electrons at full scale, 0 where shot noise is not seen), read noise (electrons, or as a
    fraction of full scale when the full well is unknown), the pixels it rests on, and whether the video tells it
    (:data:`FACTOR`)."""

    full_well_e: float
    read_noise_e: float
    read_noise_fraction: float
    pixels: int
    signal_span: float
    identified: bool = True

    def sigma(self, signal: np.ndarray, full_scale: float) -> np.ndarray:
        """The temporal noise (fraction of full scale) this model expects of a static pixel ``signal`` above
        black: read noise, shot noise where the full well is known, and the quantisation step."""
        shot = np.maximum(signal, 0.0) / self.full_well_e if self.full_well_e > 0 else 0.0
        return np.sqrt(self.read_noise_fraction**2 + shot + 1.0 / (12.0 * full_scale**2))


def fit_noise(stack: np.ndarray, static: np.ndarray, black: float, full_scale: float) -> NoiseFit:
    """Noise of frames ``stack`` (S, h, w) in fractions of full scale over the ``static`` mask (h, w) bool."""
    values = stack[:, static].astype(np.float64)  # (S, P)
    mean, var = values.mean(axis=0), values.var(axis=0, ddof=1)
    var = var - 1.0 / (12.0 * full_scale**2)
    signal = np.maximum(mean - black, 0.0)
    # a line, refitted without the pixels far above it (where the fluid's shadow or a reflection reaches now and
    # then, a static pixel is not static) until the pixels kept stay the same: a few dozen such pixels of a dim
    # camera's thousands pull the first lines' slope far up (docs/calibration.md, "One kind at a time")
    keep = np.ones(len(var), bool)
    for _ in range(ROUNDS):
        A = np.stack([np.ones(keep.sum()), signal[keep]], axis=1)
        (intercept, slope), *_ = np.linalg.lstsq(A, var[keep], rcond=None)
        resid = var - (intercept + slope * signal)
        kept, keep = keep, resid < 4 * 1.4826 * np.median(np.abs(resid[keep])) + 1e-12
        if np.array_equal(kept, keep):
            break
    read = float(np.sqrt(max(intercept, 0.0)))
    pixels, span = int(keep.sum()), float(np.ptp(signal))
    if read * full_scale < ROUNDED_BELOW_STEPS:
        levels = np.round(values[:, keep] * full_scale)
        read_dn, gain, identified = fit_rounded(levels, black * full_scale, read * full_scale, slope * full_scale)
        read, slope = read_dn / full_scale, gain / full_scale
    else:
        identified = True
    if slope <= 0:
        return NoiseFit(0.0, 0.0, read, pixels, span, identified)
    full_well = float(1.0 / slope)
    return NoiseFit(full_well, read * full_well, read, pixels, span, identified)


class _Levels:
    """Still pixels' samples as counts per level (DN), and the likelihood of a noise under rounding, each pixel's
    own level profiled out."""

    def __init__(self, levels: np.ndarray, black: float) -> None:
        low = levels.min(axis=0)
        index = (levels - low).astype(np.int64)  # (S, P)
        width = int(index.max()) + 1
        p = levels.shape[1]
        self.counts = np.bincount((index + width * np.arange(p)).ravel(), minlength=p * width).reshape(p, width)
        self.level = low[:, None] + np.arange(width)  # (P, K) DN
        self.edges = low[:, None] + (np.arange(width + 1) - 0.5)  # (P, K + 1) DN: each level's lower edge, and the top
        self.mean = levels.mean(axis=0)
        self.black = black
        #: the lowest level takes the whole lower tail (a sensor clips at 0)
        self.floor = self.level <= 0

    def _pixels(self, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Each pixel's negative log-likelihood (P,) with its level at ``mu`` and its noise ``sigma`` (DN)."""
        below = ndtr((self.edges - mu[:, None]) / sigma[:, None])  # a level's upper edge is the next one's lower
        upper, lower = below[:, 1:], np.where(self.floor, 0.0, below[:, :-1])
        return -(self.counts * np.log(np.maximum(upper - lower, 1e-300))).sum(axis=1)

    def nll(self, read2: float, gain: float) -> float:
        """The negative log-likelihood of read noise ``read2`` (DN^2) and shot noise ``gain`` (DN^2 per DN above
        black), each pixel's level at its most likely (golden section within half a step of its mean)."""

        def sigma(mu: np.ndarray) -> np.ndarray:
            return np.sqrt(read2 + gain * np.maximum(mu - self.black, 0.0)) + 1e-9

        ratio = (math.sqrt(5.0) - 1.0) / 2.0
        a, b = self.mean - 0.5, self.mean + 0.5
        c, d = b - ratio * (b - a), a + ratio * (b - a)
        fc, fd = self._pixels(c, sigma(c)), self._pixels(d, sigma(d))
        for _ in range(LEVEL_STEPS):
            left = fc < fd  # the minimum lies in [a, d]
            a, b = np.where(left, a, c), np.where(left, d, b)
            new = np.where(left, b - ratio * (b - a), a + ratio * (b - a))  # the one point each pixel needs
            f_new = self._pixels(new, sigma(new))
            c, d = np.where(left, new, d), np.where(left, c, new)
            fc, fd = np.where(left, f_new, fd), np.where(left, fc, f_new)
        return float(np.minimum(fc, fd).sum())


def fit_rounded(levels: np.ndarray, black: float, read: float, gain: float) -> tuple[float, float, bool]:
    """Read noise (DN), shot noise (DN^2 per DN above ``black``; 0: not seen) and whether the read noise is told
    within :data:`FACTOR`, by maximum likelihood of still pixels' rounded ``levels`` (S, P) in DN. The likelihood can
    have two modes of near-equal height (a read noise near none with more shot noise, and the true one), so the read
    noise is profiled over :data:`READ_GRID` first (the shot noise refitted at each) and the best point refined from
    there and from the moments' fit (``read`` DN, ``gain``); it is told where every read noise further than
    :data:`FACTOR` from it, on the grid and at that factor, is worse by :data:`LIKELIHOOD_DROP`."""
    data = _Levels(levels, black)

    def best_gain(read2: float) -> tuple[float, float]:  # the likelihood's best over the shot noise
        found = minimize_scalar(
            lambda x: data.nll(read2, math.exp(x)), bounds=GAIN_BOUNDS, method="bounded", options=BOUNDED
        )
        return float(found.fun), math.exp(found.x)

    grid = [(r, *best_gain(r * r)) for r in READ_GRID]
    read_grid, _, gain_grid = min(grid, key=lambda row: row[1])
    starts = [(max(read * read, READ_GRID[0] ** 2), max(gain, math.exp(GAIN_BOUNDS[0]))), (read_grid**2, gain_grid)]
    fits = [
        minimize(
            lambda x: data.nll(math.exp(x[0]), math.exp(x[1])),
            np.log(start),
            method="Nelder-Mead",
            options={"xatol": 1e-3, "fatol": 0.05},
        )
        for start in starts
    ]
    best = min(fits, key=lambda fit: fit.fun)
    read2, gain = (math.exp(v) for v in best.x)
    no_shot = minimize_scalar(
        lambda x: data.nll(math.exp(2 * x), 0.0), bounds=READ_BOUNDS, method="bounded", options=BOUNDED
    )
    if no_shot.fun - best.fun < LIKELIHOOD_DROP:  # shot noise not seen: the read noise alone
        read2, gain, best_fun = math.exp(2 * no_shot.x), 0.0, float(no_shot.fun)
        others = [data.nll(r * r, 0.0) for r in READ_GRID if not _near(r, math.sqrt(read2))]
        at_factor = [data.nll(read2 * f * f, 0.0) for f in (FACTOR, 1 / FACTOR)]
    else:
        best_fun = float(best.fun)
        others = [nll for r, nll, _ in grid if not _near(r, math.sqrt(read2))]
        at_factor = [best_gain(read2 * f * f)[0] for f in (FACTOR, 1 / FACTOR)]
    told = all(nll - best_fun >= LIKELIHOOD_DROP for nll in others + at_factor)
    return math.sqrt(read2), gain, told


def _near(r: float, read: float) -> bool:
    """Whether read noise ``r`` lies within :data:`FACTOR` of ``read``."""
    return read / FACTOR <= r <= read * FACTOR
