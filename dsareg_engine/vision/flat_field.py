"""A flat-field correction: the smooth gain across an X-ray image, fitted on its background and removed.

Every X-ray image carries a gain that varies smoothly over the field: the anode heel effect (a gradient along
the tube axis), an image intensifier's vignetting (darker towards the rim, about ``1 − a r²``), the inverse-square
and obliquity fall-off towards a flat panel's corners, a patient's thickness changing across the field. The
``dsa`` border model does not see it (it subtracts a local background, 16 px wide, before it looks for vessels);
the angiogram network does, because it normalises the image as a whole (:mod:`.angiogram.prepare`): where the
field is darker, its vessels have less contrast against the whole image's grey levels, and the network keeps
fewer of them (measured on the paper's mesh, 800 px, a vignette ``1 − 0.175 r²`` times a ±15 % gradient: the share
of the ``dsa`` mask within 2 px of the network's mask fell from 0.89 to 0.76, every vessel in the view still there).

:func:`flat_fielded` fits a quadratic surface in the image coordinates (six terms: a level, two gradients and the
three second-order terms, which hold a radial ``r²`` fall-off and any tilt of it) to the background pixels by
least squares, three rounds, each dropping the pixels more than 3 robust σ from the last fit, and subtracts it,
keeping the image's mean background level. An additive gain is exact for log-domain images (LOG / DISP XA, most
exported angiograms) and first-order for linear ones; the network reads a few percent of contrast the same
(on the case above, an additive and a multiplicative correction gave 0.898 and 0.897). The surface is too stiff
to follow anatomy at the vessels' scale: a diaphragm's edge or a bone stays in the image.
"""

from __future__ import annotations

import numpy as np

MIN_BACKGROUND_PX = 1000
"""Fewer background pixels than this: no correction (nothing to fit a surface on)."""
SAMPLE_PX = 40000
"""The fit reads at most about this many background pixels (an even stride through them)."""


def _terms(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The quadratic surface's six terms at ``(rows, cols)``, coordinates scaled to [−1, 1] over ``shape``."""
    y = (rows - 0.5 * (shape[0] - 1)) / max(0.5 * shape[0], 1.0)
    x = (cols - 0.5 * (shape[1] - 1)) / max(0.5 * shape[1], 1.0)
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)


def fitted_surface(pixels: np.ndarray, background: np.ndarray) -> np.ndarray | None:
    """The quadratic surface ``(H, W)`` float32 fitted robustly to ``pixels`` where ``background`` is True (module
    docstring), or None where ``background`` holds fewer than :data:`MIN_BACKGROUND_PX` pixels."""
    rows, cols = np.nonzero(background)
    if rows.size < MIN_BACKGROUND_PX:
        return None
    step = max(1, rows.size // SAMPLE_PX)
    rows, cols = rows[::step], cols[::step]
    terms = _terms(rows.astype(np.float64), cols.astype(np.float64), pixels.shape)
    values = np.asarray(pixels, np.float64)[rows, cols]
    kept = np.ones(values.shape, bool)
    for _ in range(3):
        coefficients = np.linalg.lstsq(terms[kept], values[kept], rcond=None)[0]
        residual = values - terms @ coefficients
        spread = 1.4826 * float(np.median(np.abs(residual[kept])))
        kept = np.abs(residual) <= 3.0 * max(spread, 1e-12)
        if kept.sum() < terms.shape[1] * 4:
            return None
    c0, cx, cy, cxx, cxy, cyy = coefficients  # evaluated by broadcasting: one (H, W) array, not six
    y = _terms(np.arange(pixels.shape[0], dtype=np.float64), np.zeros(pixels.shape[0]), pixels.shape)[:, 2][:, None]
    x = _terms(np.zeros(pixels.shape[1]), np.arange(pixels.shape[1], dtype=np.float64), pixels.shape)[:, 1][None, :]
    return (c0 + cx * x + cy * y + cxx * x * x + cxy * x * y + cyy * y * y).astype(np.float32)


def flat_fielded(pixels: np.ndarray, background: np.ndarray, field: np.ndarray | None = None) -> np.ndarray | None:
    """``pixels (H, W)`` less the smooth gain fitted on ``background`` (True: no vessel there), its mean level kept,
    float32; inside ``field`` only (the collimator's dark or bright outside is left as it is). None where there is
    too little background to fit (:func:`fitted_surface`)."""
    surface = fitted_surface(pixels, background)
    if surface is None:
        return None
    image = np.asarray(pixels, np.float32)
    level = float(np.mean(surface[background]))
    corrected = image - surface + level
    return corrected if field is None else np.where(field, corrected, image).astype(np.float32)
