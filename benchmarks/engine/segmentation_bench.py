"""``python -m benchmarks.engine segmentation``: vessel segmentation of real X-ray angiograms against expert labels.

Every image is scored by each method; the network is cross-validated: the images are dealt into ``--folds`` folds
(:func:`~dsareg_engine.vision.angiogram.training.folds`), one network is trained per fold on the other folds'
images (or read from ``--fold-weights DIR/foldK.pt``, made by ``segmentation-train --exclude``; each record's list
of training images is checked against the fold), and an image is scored only by the network that did not see
it. Methods:

* ``network`` — the U-Net path of ``dsareg segment --method network`` (cross-validated as above);
* ``frangi`` — the classical path (``--method frangi``), no training;
* ``baseline`` — twenty lines of scikit-image: Frangi on the image, the field of view (pixels above 10 % of the
  range) eroded by 10 px, the top 12 % of the field's response;
* ``dsa`` — the DSA border model (``--method dsa``; what ``auto`` fell back to on grey images before this round).

Per image: Dice, precision, recall, coverage (mask / image), and the share of the mask within
``max(3, 1.2 % of the side)`` px of the field of view's edge (the field found from the image). ``--pictures DIR``
writes image | label | mask strips for the worst, median and best network images.

``--emulate second-site`` scores the same methods on the images made second-site-like by
:func:`benchmarks.engine.site_emulation.second_site` (512 px, a square crop inside the round field, a rectangular
collimator, only the main arteries labelled; ``--seed``), against the main-artery label and the whole-tree label.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

METHODS = ("network", "frangi", "baseline", "dsa")


def baseline_mask(pixels: np.ndarray) -> np.ndarray:
    """The twenty-line scikit-image baseline (module docstring)."""
    from scipy import ndimage
    from skimage.filters import frangi

    image = pixels.astype(np.float32) / max(float(pixels.max()), 1.0)
    field = ndimage.binary_erosion(image > 0.1 * float(image.max()), iterations=10)
    response = frangi(image, sigmas=(1, 2, 3, 4, 5), black_ridges=True)
    level = np.quantile(response[field], 0.88) if field.any() else np.inf
    return field & (response > level)


def scores(mask: np.ndarray, label: np.ndarray, field: np.ndarray) -> dict[str, float]:
    from dsareg_engine.vision.angiogram.field_of_view import inner_field

    hits = float((mask & label).sum())
    band = field & ~inner_field(field, max(3, round(0.012 * max(mask.shape))))
    kept = max(float(mask.sum()), 1.0)
    return {"dice": 2 * hits / max(float(mask.sum() + label.sum()), 1.0), "precision": hits / kept,
            "recall": hits / max(float(label.sum()), 1.0), "coverage": float(mask.mean()),
            "edge": float((mask & band).sum()) / kept}


def fold_networks(images, args) -> list:
    """One network per fold, each checked not to have seen its fold's images."""
    from dsareg_engine.vision.angiogram.learned import load_network
    from dsareg_engine.vision.angiogram.training import TrainingSettings, folds, save_weights, train

    networks = []
    for index, fold in enumerate(folds(len(images), args.folds)):
        held_out = {images[i].name for i in fold}
        path = Path(args.fold_weights) / f"fold{index}.pt"
        if not path.is_file():
            if not args.train:
                raise SystemExit(f"{path} is missing: train it (segmentation-train --exclude …) or pass --train")
            record = train([item for item in images if item.name not in held_out],
                           TrainingSettings(iterations=args.iterations))
            path.parent.mkdir(parents=True, exist_ok=True)
            save_weights(record, path)
        _check_fold(path, held_out)
        networks.append((set(held_out), load_network(path)))
    return networks


def _check_fold(path: Path, held_out: set[str]) -> None:
    import torch

    seen = set(torch.load(path, map_location="cpu", weights_only=True)["data"]["images"])
    if seen & held_out:
        raise SystemExit(f"{path} was trained on held-out images {sorted(seen & held_out)}: not a cross-validation")


def _segment(method: str, item, networks) -> tuple[np.ndarray, float]:
    from dsareg_engine.vision.angiogram import segment_angiogram
    from dsareg_engine.vision.angiogram.learned import vessel_probability
    from dsareg_engine.vision.angiogram.vessel_mask import vessel_mask
    from dsareg_engine.vision.segmentation import segment_vessels

    started = time.perf_counter()
    if method == "network":
        model = next(model for held_out, model in networks if item.name in held_out)
        mask = vessel_mask(*vessel_probability(item.pixels, model=model))[0]
    elif method == "frangi":
        mask = segment_angiogram(item.pixels, method="frangi").mask
    elif method == "baseline":
        mask = baseline_mask(item.pixels)
    else:
        mask = segment_vessels(item.pixels, "dsa")
    return mask, time.perf_counter() - started


def _summary(rows: list[dict], method: str) -> str:
    values = {key: np.array([row[method][key] for row in rows]) for key in ("dice", "precision", "recall",
                                                                            "coverage", "edge", "seconds")}
    dice = values["dice"]
    return (f"| {method} | {np.median(dice):.3f} | {np.percentile(dice, 10):.3f} | {dice.mean():.3f} | "
            f"{np.median(values['precision']):.3f} | {np.median(values['recall']):.3f} | "
            f"{np.median(values['coverage']) * 100:.1f} / {values['coverage'].max() * 100:.1f} | "
            f"{np.median(values['edge']) * 100:.2f} / {values['edge'].max() * 100:.2f} | "
            f"{np.median(values['seconds']):.3f} |")


def _pictures(rows: list[dict], images, masks: dict, out: Path, wholes: list | None = None) -> None:
    """Image | label | network mask strips; with ``wholes`` (the emulated second site) the label panel shows the
    main arteries white and the rest of the whole tree grey."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    prefix = "segmentation-site2" if wholes is not None else "segmentation"
    order = sorted(range(len(rows)), key=lambda i: rows[i]["network"]["dice"])
    for tag, index in (("worst", order[0]), ("median", order[len(order) // 2]), ("best", order[-1])):
        item = images[index]
        grey = np.clip(item.pixels, 0, 255).astype(np.uint8)
        label = item.label.astype(np.uint8) * 255
        if wholes is not None:
            label = np.where(item.label, 255, np.where(wholes[index], 110, 0)).astype(np.uint8)
        strip = np.concatenate([grey, label, masks[index].astype(np.uint8) * 255], axis=1)
        Image.fromarray(strip).save(out / f"{prefix}-{tag}-{item.name}.png")
        print(f"{out}/{prefix}-{tag}-{item.name}.png: image | label | network mask "
              f"(Dice {rows[index]['network']['dice']:.3f})")


def _agreement(item, network_mask: np.ndarray, networks) -> tuple[float, float, bool, bool]:
    """What ``auto`` compares: the ``dsa`` mask (inside the collimated field) against the network's: their Dice,
    the share of the ``dsa`` mask within 2 px of the network's, whether that was the network's reading after the
    flat-field correction (``segmentation_choice.judged_reading``; the image's own fold network reads both), and
    whether ``auto`` keeps ``dsa`` (``segmentation_choice.keeps_dsa``, its sparse-tree rule included)."""
    from dsareg_engine.vision.angiogram.learned import vessel_probability
    from dsareg_engine.vision.angiogram.vessel_mask import vessel_mask
    from dsareg_engine.vision.segmentation import segment_vessels
    from dsareg_engine.vision.angiogram.field_of_view import estimate_field_of_view
    from dsareg_engine.vision.segmentation_choice import (agrees, collimated_inside, judged_reading, keeps_dsa,
                                                          sparse_and_attached)

    model = next(model for held_out, model in networks if item.name in held_out)
    field = estimate_field_of_view(item.pixels)
    inside = collimated_inside(field)
    dsa_mask = segment_vessels(item.pixels, "dsa") & inside
    agreement, explained, flat, decided = judged_reading(
        item.pixels, dsa_mask, network_mask, field, lambda image: vessel_mask(*vessel_probability(image, model=model))[0])
    coverage, attached = (None, None) if agrees(agreement, explained) else sparse_and_attached(dsa_mask, decided, inside)
    return agreement, explained, flat, keeps_dsa(agreement, explained, coverage, attached)


def bench_segmentation(args: argparse.Namespace) -> int:
    import torch

    from dsareg_engine.vision.angiogram.field_of_view import estimate_field_of_view
    from dsareg_engine.vision.angiogram.training import labelled_images
    from dsareg_engine.vision.segmentation_choice import AGREEMENT_DICE, EXPLAINED_SHARE

    torch.set_num_threads(args.threads)
    images = labelled_images(Path(args.data))
    networks = fold_networks(images, args) if "network" in args.methods else []
    wholes = None
    if args.emulate == "second-site":
        images, wholes, true_fields = _second_site(images, args.seed)
    rows, whole_rows, network_masks = [], [], {}
    columns = [f"{method} Dice" for method in args.methods]
    if wholes is not None:
        columns = [f"{c} (main)" for c in columns] + [f"{c} (whole)" for c in columns]
    print("| image | " + " | ".join(columns) + " |")
    print(f"|---|{'---|' * len(columns)}")
    for index, item in enumerate(images):
        field = estimate_field_of_view(item.pixels)
        row, whole_row = {}, {}
        for method in args.methods:
            mask, seconds = _segment(method, item, networks)
            row[method] = {**scores(mask, item.label, field), "seconds": seconds}
            if wholes is not None:
                row[method]["edge_true"] = scores(mask, item.label, true_fields[index])["edge"]
                whole_row[method] = {**scores(mask, wholes[index], field), "seconds": seconds}
            if method == "network":
                network_masks[index] = mask
        if "network" in row and "dsa" in row:
            row["agreement"] = _agreement(item, network_masks[index], networks)
        rows.append(row)
        whole_rows.append(whole_row)
        dices = " | ".join(f"{row[method]['dice']:.3f}" for method in args.methods)
        if wholes is not None:
            dices += " | " + " | ".join(f"{whole_row[method]['dice']:.3f}" for method in args.methods)
        print(f"| {item.name} | {dices} |", flush=True)
    print(f"\n{len(images)} images, {args.folds}-fold cross-validation for the network\n")
    for title, table in (("main-artery label", rows), ("whole-tree label", whole_rows)) if wholes is not None \
            else (("label", rows),):
        if wholes is not None:
            print(f"\nagainst the {title}:\n")
        print("| method | Dice median | Dice p10 | Dice mean | precision median | recall median | coverage % median / "
              "max | on the field's edge % median / max | s per image median |")
        print("|---|---|---|---|---|---|---|---|---|")
        for method in args.methods:
            print(_summary(table, method))
    if wholes is not None:
        print("\nshare of the mask on the collimator's true edge (the same band around the blades' penumbra middle, "
              "semi-transparent blades included), % median / max: " + "; ".join(
                  f"{method} {np.median([r[method]['edge_true'] for r in rows]) * 100:.2f} / "
                  f"{max(r[method]['edge_true'] for r in rows) * 100:.2f}" for method in args.methods))
    if rows and "agreement" in rows[0]:
        agreement, explained, flat, keeps_dsa = (np.array([row["agreement"][k] for row in rows]) for k in (0, 1, 2, 3))
        print(f"\n`auto`'s dsa / network comparison (the network cross-validated): masks' Dice median "
              f"{np.median(agreement):.3f}, max {agreement.max():.3f}; share of the dsa mask within 2 px of the "
              f"network's median {np.median(explained):.3f}, max {explained.max():.3f} (the network's reading after "
              f"the flat-field correction on {int(flat.sum())}); `auto` keeps dsa on "
              f"{int(keeps_dsa.sum())} of {len(rows)} (Dice >= {AGREEMENT_DICE} and share >= {EXPLAINED_SHARE}, or its "
              "mask a sparse tree joined to the shared part: segmentation_choice.keeps_dsa)")
    if args.pictures and network_masks:
        _pictures(rows, images, network_masks, Path(args.pictures), wholes)
    return 0


def _second_site(images, seed: int) -> tuple[list, list, list]:
    """The images made second-site-like (:mod:`.site_emulation`): ``(images with the main-artery label, the
    whole-tree labels, the collimators' true fields)``; names kept, so each stays in its fold."""
    from dsareg_engine.vision.angiogram.training import LabelledImage

    from .site_emulation import second_site

    sites = [second_site(item.name, item.pixels, item.label, seed) for item in images]
    for site in sites:
        print(f"# {site.name}: crop (row, col, side) {site.framing['crop']}, x{site.framing['scale']}, blades "
              f"(side, px, transmission, penumbra px) {site.framing['blades']}")
    return ([LabelledImage(site.name, site.pixels, site.label) for site in sites],
            [site.whole for site in sites], [site.inside for site in sites])


def add_parser(which) -> None:
    sub = which.add_parser("segmentation", help="vessel segmentation of real angiograms vs expert labels "
                                                "(Dice, precision, recall, coverage; network cross-validated)")
    sub.add_argument("--data", required=True, help="folder of N.png / N_gt.png pairs")
    sub.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS, help="methods to score")
    sub.add_argument("--folds", type=int, default=3, help="cross-validation folds for the network (default 3)")
    sub.add_argument("--fold-weights", default="segmentation-folds", help="folder of foldK.pt (made if --train)")
    sub.add_argument("--train", action="store_true", help="train the missing fold networks (CPU, ~5-15 min each)")
    sub.add_argument("--iterations", type=int, default=1000, help="optimiser steps per fold network")
    sub.add_argument("--pictures", metavar="DIR", help="write image | label | mask strips here")
    sub.add_argument("--threads", type=int, default=2, help="torch threads")
    sub.add_argument("--emulate", choices=("second-site",), help="score on the images made second-site-like "
                     "(512 px, square crop, rectangular collimator, main arteries labelled: site_emulation.py)")
    sub.add_argument("--seed", type=int, default=0, help="seed of --emulate (default 0)")
    sub.set_defaults(func=bench_segmentation)
