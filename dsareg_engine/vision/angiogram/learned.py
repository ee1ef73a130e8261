"""The vessel probability of an X-ray angiogram from the shipped network (:mod:`.unet`, weights in ``weights/``).

``vessel_probability(pixels) -> (H, W) float32 in [0, 1]``: the image is brought to the working scale
(:mod:`.prepare`), its field of view found (:mod:`.field_of_view`, combined with the file's shutter when given),
normalised, run through the network on the CPU (or wherever torch puts it) at the working scale and at half of it
(:func:`across_scales`: wide vessels kept), and the probability brought back to the image's pixels; 0 outside the
field of view. The weights file records what it was trained on (``data.images``, ``data.sha256``) and how
(``training``); ``python -m benchmarks.engine segmentation-train`` makes it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy import ndimage

from .shipped import WEIGHTS_PATH
from .prepare import WorkingScale, grown, normalized, shrunk, working_image
from .unet import UNetSettings, VesselUNet, padded_to_level


@functools.lru_cache(maxsize=4)
def load_network(path: Path = WEIGHTS_PATH) -> VesselUNet:
    """The network of a weights record, in eval mode (cached per path)."""
    record = torch.load(Path(path), map_location="cpu", weights_only=True)
    model = VesselUNet(UNetSettings(**record["network"]))
    model.load_state_dict(record["state"])
    return model.eval()


def network_probability(model: VesselUNet, network_input: np.ndarray) -> np.ndarray:
    """``sigmoid(model(network_input))`` for one normalised image ``(H, W)``, same shape."""
    tensor = torch.from_numpy(np.ascontiguousarray(network_input, np.float32))[None, None]
    padded, (height, width) = padded_to_level(tensor, model.settings.multiple_px)
    with torch.inference_mode():
        logits = model(padded)[0, 0, :height, :width]
    return torch.sigmoid(logits).numpy().astype(np.float32)


@dataclass(frozen=True)
class ScaleReading:
    """The second, coarser reading that keeps wide vessels (:func:`across_scales`). Lengths in px at the working
    scale. Measured basis (docs/benchmarks/segmentation.md, "A second site, emulated"; the 3-fold networks, never
    on an image they saw): the 40 coronary images at 300 px, median / p10 Dice 0.734 / 0.649 → 0.735 / 0.647;
    their emulated 512² second site (1.7–2.4 × magnified, main arteries labelled) 0.230 / 0.037 → 0.509 / 0.310.

    Attributes:
        factor: the coarse reading's extra area averaging (2: a vessel 10–25 px wide at the working scale is
            5–12 px there, inside what the network was trained on: labels' diameters 4.5 px median, 10 px p90 at
            300 px, times 0.6–1.6 scale augmentation).
        threshold: a pixel is vessel in a reading at this probability (the mask's own 0.5).
        border_px: only the coarse vessels' interior, more than this from their border, is taken: the coarse
            reading places a border to within its own pixel (``factor`` px here, half of it either way); the
            border comes from the fine reading.
        min_side_px: no coarse reading where its shorter side would be under this (the network's 4 levels).
    """

    factor: int = 2
    threshold: float = 0.5
    border_px: float = 1.0
    min_side_px: int = 32


def across_scales(fine: np.ndarray, coarse: np.ndarray, settings: ScaleReading = ScaleReading()) -> np.ndarray:
    """The probability ``(h, w)`` of two readings on the working grid: the fine one (the network at the working
    scale), and where a vessel piece of the coarse one (``coarse``: the reading of the image area-averaged by
    ``settings.factor``, brought back to the working grid) continues a vessel of the fine one (touches it,
    8-neighbours), the larger of the two inside that piece's interior (more than ``border_px`` from its border).

    Why: the network was trained on vessels of diameter 4.5 px median, 10 px p90, 16 px p99 (the 40 labels at
    300 px) scaled 0.6–1.6 ×; a trunk 20–25 px wide at the working scale (a magnified field: a 512² frame of a
    small one) is read at that scale as its two edges and its branches, its lumen missed. Averaged by 2 it is a
    vessel of 10–12 px, which the network knows, so the coarse reading holds the lumen. Kept only where it continues
    a fine vessel (at 0.5 × a training-scale image also gives coarse-only blobs), and only its interior: the coarse
    reading's border is uncertain by a coarse pixel, so vessels of ordinary width keep the fine reading's border
    (the max of the two over whole pieces cost the 300-px images 0.07 of precision, this 0.03)."""
    fine_vessels = fine >= settings.threshold
    coarse_vessels = coarse >= settings.threshold
    pieces, count = ndimage.label(coarse_vessels, structure=np.ones((3, 3), bool))
    continues = np.zeros(count + 1, bool)
    continues[np.unique(pieces[fine_vessels])] = True
    continues[0] = False
    depth = cv2.distanceTransform(coarse_vessels.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)  # Euclidean
    interior = continues[pieces] & (depth > settings.border_px)
    return np.where(interior, np.maximum(fine, coarse), fine).astype(np.float32)


def vessel_probability(pixels: np.ndarray, field: np.ndarray | None = None, *, vessels_dark: bool = True,
                       model: VesselUNet | None = None, scale: WorkingScale = WorkingScale(),
                       reading: ScaleReading | None = ScaleReading()) -> tuple[np.ndarray, np.ndarray]:
    """``(probability (H, W) float32 in [0, 1], field of view (H, W) bool)`` for ``pixels (H, W)``.

    ``field``: the file's field of view, if it has one. ``model``: default the shipped network. ``reading``: the
    coarse second reading (:class:`ScaleReading`, :func:`across_scales`); ``None``: the working scale only.
    """
    work = working_image(pixels, field, vessels_dark=vessels_dark, scale=scale)
    model = model or load_network()
    probability = network_probability(model, work.network_input)
    probability[~work.field] = 0.0
    if reading is not None and reading.factor > 1 and min(work.field.shape) >= reading.factor * reading.min_side_px:
        coarse_pixels = shrunk(work.pixels, reading.factor)
        coarse_field = shrunk(work.field.astype(np.float32), reading.factor) >= 0.5
        coarse = network_probability(model, normalized(coarse_pixels, coarse_field, vessels_dark=vessels_dark))
        coarse[~coarse_field] = 0.0
        coarse = np.clip(grown(coarse, work.field.shape), 0.0, 1.0)
        coarse[~work.field] = 0.0
        probability = across_scales(probability, coarse, reading)
    return work.back(probability), work.full_field()
