"""``python -m benchmarks.engine segmentation-train``: train the vessel network and write its weights.

The shipped weights (``dsareg_engine/vision/angiogram/weights/vessel_unet.pt``) come from::

    python -m benchmarks.engine segmentation-train --data ../shared/data/real-angiograms/coronary-labelled \\
        --out dsareg_engine/vision/angiogram/weights/vessel_unet.pt

on all 40 labelled images of that folder (its README names the source: the training half of a DCA1-style set,
fercer/Coronary ``Angios_40_training``). ``--exclude`` leaves images out (a cross-validation fold); the record
lists the images it saw and their SHA-256.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def train_network(args: argparse.Namespace) -> int:
    import torch

    from dsareg_engine.errors import DsaregInputError
    from dsareg_engine.vision.angiogram.training import TrainingSettings, labelled_images, save_weights, train

    torch.set_num_threads(args.threads)
    images = [item for item in labelled_images(Path(args.data)) if item.name not in set(args.exclude)]
    if not images:
        raise DsaregInputError(f"no N.png / N_gt.png pairs in {args.data}", field="--data")
    settings = TrainingSettings(iterations=args.iterations, seed=args.seed)
    print(f"training on {len(images)} images ({', '.join(item.name for item in images)}), "
          f"{settings.iterations} iterations, seed {settings.seed}", flush=True)
    record = train(images, settings, progress=lambda step, loss, seconds: print(
        f"  step {step}: loss {loss:.3f}, {seconds:.0f} s", flush=True))
    save_weights(record, Path(args.out))
    print(f"{args.out}: {record['seconds']} s of training, data sha256 {record['data']['sha256'][:16]}…")
    return 0


def add_parser(which) -> None:
    sub = which.add_parser("segmentation-train", help="train the vessel network on labelled angiograms (CPU)")
    sub.add_argument("--data", required=True, help="folder of N.png / N_gt.png pairs")
    sub.add_argument("--out", required=True, help="where to write the weights (.pt)")
    sub.add_argument("--exclude", nargs="*", default=[], metavar="N", help="image names to leave out")
    sub.add_argument("--iterations", type=int, default=1000, help="optimiser steps (default 1000)")
    sub.add_argument("--seed", type=int, default=0, help="random seed")
    sub.add_argument("--threads", type=int, default=2, help="torch threads")
    sub.set_defaults(func=train_network)
