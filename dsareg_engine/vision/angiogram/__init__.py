"""Vessels in real X-ray angiograms (native or subtracted, cerebral or coronary): field of view, polarity from
physics, a small U-Net trained here on real labelled angiograms, the classical Frangi path as its fallback and
comparison, and the mask's clean-up.

* :mod:`.field_of_view` — where the detector sees the patient (the file's shutter, or flat border regions);
* :mod:`.prepare` — polarity, working scale (≤ 512 px), normalisation inside the field;
* :mod:`.unet`, :mod:`.learned` — the network and its inference at two scales (weights in ``weights/``);
* :mod:`.augment`, :mod:`.training` — how the shipped weights were made (``python -m benchmarks.engine
  segmentation-train``);
* :mod:`.classical` — black top-hat + Frangi + quantile hysteresis;
* :mod:`.vessel_mask` — probability → mask (threshold 0.5, field edge, pieces, coverage cap).

``segment_angiogram(pixels)`` is the entry point; :mod:`dsareg_engine.vision.segmentation` routes the
``network`` and ``frangi`` methods (and ``auto`` on grey images) here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shipped import WEIGHTS_PATH, weights_available

ANGIOGRAM_METHODS = ("network", "frangi")
__all__ = ["ANGIOGRAM_METHODS", "AngiogramSegmentation", "WEIGHTS_PATH", "allow_network", "network_usable",
           "segment_angiogram", "weights_available"]

_NETWORK = {"allowed": True}


def allow_network(allowed: bool) -> None:
    """Whether this process may run the network (and import torch). A process that only checks inputs (the
    service's validator, under an address-space limit torch's import alone would exceed) turns it off: there
    ``network`` runs the classical path and ``auto`` keeps ``dsa``; the worker decides with the network."""
    _NETWORK["allowed"] = bool(allowed)


def network_usable() -> bool:
    """The network may run here and its weights are installed."""
    return _NETWORK["allowed"] and weights_available()


@dataclass(frozen=True)
class AngiogramSegmentation:
    """Attributes:
        mask: (H, W) bool vessels. probability: (H, W) float32 in [0, 1]. field: (H, W) bool field of view.
        method: ``"network"`` or ``"frangi"`` (the network falls back to Frangi when its weights are missing or
            the process does not run it, :func:`allow_network`).
        record: what :func:`~.vessel_mask.vessel_mask` did (threshold, pieces removed, edge margin, coverage).
    """

    mask: np.ndarray
    probability: np.ndarray
    field: np.ndarray
    method: str
    record: dict


def segment_angiogram(pixels: np.ndarray, field: np.ndarray | None = None, *, method: str = "network",
                      vessels_dark: bool = True) -> AngiogramSegmentation:
    """The vessels of a grey X-ray angiogram ``pixels (H, W)``; ``field``: the file's field of view, if any."""
    from .classical import classical_probability
    from .vessel_mask import vessel_mask

    if method == "network" and network_usable():
        from .learned import vessel_probability  # torch: only where the network runs

        probability, found_field = vessel_probability(pixels, field, vessels_dark=vessels_dark)
    else:
        method = "frangi"
        probability, found_field = classical_probability(pixels, field, vessels_dark=vessels_dark)
    mask, record = vessel_mask(probability, found_field)
    return AngiogramSegmentation(mask, probability, found_field, method, record)
