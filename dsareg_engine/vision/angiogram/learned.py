"""The vessel probability of an X-ray angiogram from the shipped network (:mod:`.unet`, weights in ``weights/``).

``vessel_probability(pixels) -> (H, W) float32 in [0, 1]``: the image is brought to the working scale
(:mod:`.prepare`), its field of view found (:mod:`.field_of_view`, combined with the file's shutter when given),
normalised, run through the network on the CPU (or wherever torch puts it), and the probability brought back to
the image's pixels; 0 outside the field of view. The weights file records what it was trained on
(``data.images``, ``data.sha256``) and how (``training``); ``python -m benchmarks.engine segmentation-train``
makes it.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

from .shipped import WEIGHTS_PATH
from .prepare import WorkingScale, working_image
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


def vessel_probability(pixels: np.ndarray, field: np.ndarray | None = None, *, vessels_dark: bool = True,
                       model: VesselUNet | None = None, scale: WorkingScale = WorkingScale()
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(probability (H, W) float32 in [0, 1], field of view (H, W) bool)`` for ``pixels (H, W)``.

    ``field``: the file's field of view (True inside), if it has one. ``model``: default the shipped network.
    """
    work = working_image(pixels, field, vessels_dark=vessels_dark, scale=scale)
    probability = network_probability(model or load_network(), work.network_input)
    probability[~work.field] = 0.0
    return work.back(probability), work.full_field()
