"""The per-frame record every stage adds to and every front door reads: one typed row per frame.

A numpy structured array (one row per frame, one named field per measure) rather than column-stacked
floats whose column 4 meant different things in different modules; NaN in every field marks a frame
that never arrived (the segmenter fills such gaps).
"""

from __future__ import annotations

import numpy as np

#: Width of the per-frame network's latent (:data:`service.inverse.manifest.LATENT`): the VAE's 10 dimensions.
LATENT_SIZE = 10
#: d, p, a, b (Eq. 1: mm, 1, mm, mm), D(0, t) (mm), mean brightness (stored pixel units), highlight (how far
#: the brightest pixel stands above the mean, as a fraction of full scale: the meniscus is seen only through its
#: highlights), change (mean absolute difference from the frame before, pixel units; NaN without one) and novelty (the
#: coarse picture's distance from the nearest of the last few milliseconds' frames, pixel units; NaN without
#: them: :mod:`service.pipeline.measures`) and the per-frame network's latent (its encoder's posterior mean, float32;
#: NaN for the other methods: the window model's input) of one frame.
FRAME = np.dtype(
    [
        ("d", "f8"),
        ("p", "f8"),
        ("a", "f8"),
        ("b", "f8"),
        ("centre", "f8"),
        ("brightness", "f8"),
        ("highlight", "f8"),
        ("change", "f8"),
        ("novelty", "f8"),
        ("latent", "f4", (LATENT_SIZE,)),
    ]
)
#: A frame whose brightest pixel stands less than this fraction of full scale above its mean shows no highlight
#: (a dark, capped or unlit camera; a lens cap; the nozzle out of view): nothing of the meniscus is seen.
NO_HIGHLIGHT = 0.1
#: The fields of :data:`FRAME` that hold Eq. 1's coefficients, in the order inverse methods return them.
COEFFICIENTS = ("d", "p", "a", "b")


def coefficients_of(records: np.ndarray) -> np.ndarray:
    """The coefficients d, p, a, b of ``records`` as an (N, 4) float64 array."""
    return np.column_stack([records[name] for name in COEFFICIENTS])
