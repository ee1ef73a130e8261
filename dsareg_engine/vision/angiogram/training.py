"""Training the vessel network (:mod:`.unet`) on labelled X-ray angiograms, on the CPU.

The data: a folder of ``N.png`` (grey X-ray angiogram, vessels dark) and ``N_gt.png`` (0 / 255 expert label) pairs,
as in the DCA1-style coronary set in ``../shared/data/real-angiograms/coronary-labelled/``. Samples are augmented
(:mod:`.augment`); the loss is binary cross-entropy plus the soft Dice loss (thin vessels are a few % of the pixels);
Adam with a cosine-decayed learning rate. Runs are seeded: the same data, settings and seed give the same
weights on the same machine. ``python -m benchmarks.engine segmentation-train`` is the command;
``python -m benchmarks.engine segmentation`` trains one network per cross-validation fold and scores each image
only with the network that did not see it.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .augment import augmented_sample
from .unet import UNetSettings, VesselUNet


@dataclass(frozen=True)
class TrainingSettings:
    """Attributes:
        iterations: optimiser steps. batch: samples per step. crop_px: side of each training crop.
        learning_rate: Adam's initial rate (cosine-decayed to 2 % of it). seed: numpy and torch seed.
    """

    iterations: int = 1000
    batch: int = 8
    crop_px: int = 96
    learning_rate: float = 3e-3
    seed: int = 0


@dataclass(frozen=True)
class LabelledImage:
    name: str
    pixels: np.ndarray  # float32 (H, W), vessels dark
    label: np.ndarray  # bool (H, W)


def labelled_images(folder: Path) -> list[LabelledImage]:
    """The ``N.png`` / ``N_gt.png`` pairs of ``folder``, sorted by ``N`` (numbers first)."""
    from PIL import Image

    pairs = []
    for label_path in Path(folder).glob("*_gt.png"):
        image_path = label_path.with_name(label_path.name[:-len("_gt.png")] + ".png")
        if image_path.is_file():
            pixels = np.asarray(Image.open(image_path).convert("L"), np.float32)
            label = np.asarray(Image.open(label_path).convert("L")) > 127
            pairs.append(LabelledImage(image_path.stem, pixels, label))
    return sorted(pairs, key=lambda item: (not item.name.isdigit(), int(item.name) if item.name.isdigit() else 0,
                                           item.name))


def data_digest(images: list[LabelledImage]) -> str:
    """SHA-256 over the images' names, pixels and labels (what a network was trained on)."""
    digest = hashlib.sha256()
    for item in images:
        digest.update(item.name.encode())
        digest.update(item.pixels.astype(np.uint8).tobytes())
        digest.update(np.packbits(item.label).tobytes())
    return digest.hexdigest()


def folds(count: int, n_folds: int) -> list[np.ndarray]:
    """Image indices of each cross-validation fold: ``0..count-1`` dealt round-robin (fold ``k``: ``k, k + n, …``)."""
    return [np.arange(fold, count, n_folds) for fold in range(n_folds)]


def _loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    probability = torch.sigmoid(logits)
    overlap = (probability * target).sum()
    dice = 1.0 - (2.0 * overlap + 1.0) / (probability.sum() + target.sum() + 1.0)
    return F.binary_cross_entropy_with_logits(logits, target) + dice


def _batch(images: list[LabelledImage], rng: np.random.Generator, settings: TrainingSettings
           ) -> tuple[torch.Tensor, torch.Tensor]:
    samples = []
    for _ in range(settings.batch):
        item = images[int(rng.integers(len(images)))]
        samples.append(augmented_sample(item.pixels, item.label, rng, settings.crop_px))
    inputs = torch.from_numpy(np.stack([s[0] for s in samples])[:, None])
    targets = torch.from_numpy(np.stack([s[1] for s in samples])[:, None])
    return inputs, targets


def train(images: list[LabelledImage], settings: TrainingSettings = TrainingSettings(),
          network: UNetSettings = UNetSettings(), *, progress=None) -> dict:
    """A trained network as a weights record (:func:`save_weights` writes it; :mod:`.learned` reads it)."""
    rng = np.random.default_rng(settings.seed)
    torch.manual_seed(settings.seed)
    model = VesselUNet(network)
    optimiser = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, settings.iterations,
                                                          eta_min=0.02 * settings.learning_rate)
    started = time.perf_counter()
    model.train()
    for step in range(settings.iterations):
        inputs, targets = _batch(images, rng, settings)
        loss = _loss(model(inputs), targets)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        if progress is not None and (step + 1) % 100 == 0:
            progress(step + 1, loss.item(), time.perf_counter() - started)
    return {"state": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "network": asdict(network), "training": asdict(settings),
            "data": {"images": [item.name for item in images], "sha256": data_digest(images)},
            "seconds": round(time.perf_counter() - started, 1)}


def save_weights(record: dict, path: Path) -> None:
    """Write a weights record (tensors and plain values only: loadable with ``weights_only=True``)."""
    torch.save(record, Path(path))
