import numpy as np
import torch
from PIL import Image

from dsareg_engine.vision.angiogram.training import (LabelledImage, TrainingSettings, data_digest, folds,
                                                      labelled_images, save_weights, train)
from dsareg_engine.vision.angiogram.unet import UNetSettings
from tests.support.angiogram_images import unsubtracted_angiogram


def test_folds_partition_the_images():
    parts = folds(40, 3)
    assert sorted(np.concatenate(parts).tolist()) == list(range(40)) and [len(p) for p in parts] == [14, 13, 13]


def test_pairs_are_read_sorted_and_a_short_training_writes_a_loadable_record(tmp_path):
    for name in ("10", "2"):
        pixels, vessels, _ = unsubtracted_angiogram(size=64, seed=int(name))
        Image.fromarray(pixels.astype(np.uint8)).save(tmp_path / f"{name}.png")
        Image.fromarray(vessels.astype(np.uint8) * 255).save(tmp_path / f"{name}_gt.png")
    images = labelled_images(tmp_path)
    assert [item.name for item in images] == ["2", "10"] and images[0].label.dtype == bool
    record = train(images, TrainingSettings(iterations=2, batch=2, crop_px=32), UNetSettings(base_channels=2, levels=2))
    assert record["data"] == {"images": ["2", "10"], "sha256": data_digest(images)}
    save_weights(record, tmp_path / "w.pt")
    loaded = torch.load(tmp_path / "w.pt", map_location="cpu", weights_only=True)
    assert loaded["training"]["iterations"] == 2 and set(loaded["state"]) == set(record["state"])
    changed = LabelledImage("2", images[0].pixels + 1, images[0].label)
    assert data_digest([changed, images[1]]) != record["data"]["sha256"]
