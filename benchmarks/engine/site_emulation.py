"""A second site, emulated from the real labelled angiograms (``segmentation --emulate second-site``).

Issue 40's hidden second site: 512 × 512 frames, a rectangular collimator, only the main arteries labelled. We have
no such frames; :func:`second_site` turns each real 300-px image + whole-tree label of the labelled set into one,
deterministically (``numpy.random.default_rng([seed, crc32(name)])``; the medial axis with ``rng=0``), along three
axes that differ between sites:

1. **Framing and scale** (:func:`square_crop`): a square of side ``round(512 / s)`` px, ``s`` drawn uniformly in
   1.7–2.4 (at most the image's side), placed, among the positions whose share of pixels outside the round field of
   view (found from the image, :func:`~dsareg_engine.vision.angiogram.field_of_view.estimate_field_of_view`, eroded
   3 px) is within 0.5 % of the least such share, at one drawn at random; then resized to 512 × 512 (bicubic for the
   image, bilinear ≥ 0.5 for the labels). The round edge is gone, or mostly (where no square of that side fits the
   field); vessels become ``s`` times wider in pixels than at 300 px.
2. **A rectangular collimator** (:func:`collimate`): each side carries a blade with probability 0.5 (at least one
   side), of width uniform in 3–15 % of the side, with a soft edge (a linear penumbra of 2–10 px); a blade is opaque
   (transmission 0–5 %) with probability 0.4, else semi-transparent (transmission 25–60 %: a blade attenuates, it
   does not zero the image). The image is multiplied by the product of the blades' transmissions. Labels are
   removed where the transmission is below 15 % (nothing visible there) and kept under a semi-transparent blade
   (the vessels still show through it).
3. **Only the main arteries labelled** (:func:`main_arteries`, on the 300-px label, before cropping): the label's
   medial axis with its local radius (distance to the background) averaged over the axis pixels within 3 px;
   ``R`` = the 95th percentile of that radius along the axis (the calibre of the image's largest vessel);
   hysteresis along the axis: axis pixels of radius ≥ max(0.4 ``R``, 2 px) connected (8-neighbours) to a pixel of
   radius ≥ 0.8 ``R``, in axis pieces of ≥ 15 pixels; redrawn as discs of each kept axis pixel's own radius,
   intersected with the label. A main artery is followed distally while it keeps ≥ 40 % of the largest vessel's
   calibre; side branches thinner than that where they leave it are dropped (median 74 % of a tree's label kept,
   36–93 %). Relative, not in mm: the 40 images'
   magnifications differ (``R`` runs from 3 to 11 px) and their pixel size is not published; a fixed 2.5 / 3.5 px
   rule left 3 of 40 images with no main artery at all, 0.55 ``R`` cut right coronaries short after their
   proximal part. The fractions were chosen from the labels' radius histograms and a look at the labels, before
   any method was scored on the emulated images.

The whole-tree label is carried through the same crop, resize and collimator, so both can be scored.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

SIDE_PX = 512
SCALE_RANGE = (1.7, 2.4)
BLADE_PROBABILITY = 0.5
BLADE_WIDTH_FRACTION = (0.03, 0.15)
PENUMBRA_PX = (2.0, 10.0)
OPAQUE_PROBABILITY = 0.4
OPAQUE_TRANSMISSION = (0.0, 0.05)
SEMI_TRANSMISSION = (0.25, 0.6)
INVISIBLE_BELOW = 0.15
SIDES = ("top", "bottom", "left", "right")


@dataclass(frozen=True)
class Blade:
    side: str  # top / bottom / left / right
    width_px: int  # from the image's edge to the middle of the penumbra
    transmission: float
    penumbra_px: float


@dataclass
class SiteImage:
    """An emulated second-site image: ``label`` the main arteries, ``whole`` the whole tree (both (H, W) bool)."""

    name: str
    pixels: np.ndarray  # float32 (H, W), vessels dark
    label: np.ndarray
    whole: np.ndarray
    framing: dict = field(default_factory=dict)
    inside: np.ndarray | None = None  # the collimator's field: True short of every blade's penumbra middle


def main_arteries(label: np.ndarray, *, low_fraction: float = 0.4, high_fraction: float = 0.8,
                  floor_px: float = 2.0, min_axis_px: int = 15, smooth_px: int = 3) -> np.ndarray:
    """The main arteries of a whole-tree ``label`` (module docstring, 3.); radii in the label's pixels."""
    from skimage.morphology import medial_axis

    label = np.asarray(label, bool)
    axis, distance = medial_axis(label, return_distance=True, rng=0)  # its tie-breaking is random
    if not axis.any():
        return np.zeros_like(label)
    window = np.ones((2 * smooth_px + 1,) * 2, np.float32)
    summed = cv2.filter2D(np.where(axis, distance, 0).astype(np.float32), -1, window, borderType=cv2.BORDER_CONSTANT)
    counted = cv2.filter2D(axis.astype(np.float32), -1, window, borderType=cv2.BORDER_CONSTANT)
    radius = np.where(axis, summed / np.maximum(counted, 1.0), 0.0)
    largest = float(np.percentile(radius[axis], 95))
    candidate = axis & (radius >= max(low_fraction * largest, floor_px))
    pieces, count = ndimage.label(candidate, structure=np.ones((3, 3), bool))
    if count == 0:
        return np.zeros_like(label)
    sizes = np.bincount(pieces.ravel(), minlength=count + 1)
    seeded = np.zeros(count + 1, bool)
    seeded[np.unique(pieces[candidate & (radius >= high_fraction * largest)])] = True
    keep = seeded & (sizes >= min_axis_px)
    keep[0] = False
    kept = keep[pieces]
    drawn = np.zeros(label.shape, np.uint8)
    for row, col in zip(*np.nonzero(kept)):
        cv2.circle(drawn, (int(col), int(row)), round(float(distance[row, col])), 1, thickness=-1)
    return drawn.astype(bool) & label


def square_crop(pixels: np.ndarray, side_px: int, rng: np.random.Generator, *, tolerance: float = 0.005
                ) -> tuple[int, int]:
    """Top-left ``(row, col)`` of a ``side_px`` square of ``pixels`` with (nearly) the least of the round field's
    outside in it (module docstring, 1.), one of those drawn by ``rng``."""
    from dsareg_engine.vision.angiogram.field_of_view import estimate_field_of_view, inner_field

    outside = ~inner_field(estimate_field_of_view(pixels), 3)
    height, width = outside.shape
    summed = np.pad(outside.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    counts = (summed[side_px:, side_px:] - summed[:-side_px, side_px:] - summed[side_px:, :-side_px]
              + summed[:-side_px, :-side_px])[: height - side_px + 1, : width - side_px + 1]
    rows, cols = np.nonzero(counts <= counts.min() + tolerance * side_px * side_px)
    pick = int(rng.integers(rows.size))
    return int(rows[pick]), int(cols[pick])


def draw_blades(rng: np.random.Generator, side_px: int = SIDE_PX) -> list[Blade]:
    """The collimator of one image (module docstring, 2.)."""
    chosen = [side for side in SIDES if rng.random() < BLADE_PROBABILITY]
    if not chosen:
        chosen = [SIDES[int(rng.integers(len(SIDES)))]]
    blades = []
    for side in chosen:
        width = round(rng.uniform(*BLADE_WIDTH_FRACTION) * side_px)
        opaque = rng.random() < OPAQUE_PROBABILITY
        transmission = float(rng.uniform(*(OPAQUE_TRANSMISSION if opaque else SEMI_TRANSMISSION)))
        blades.append(Blade(side, width, round(transmission, 3), round(float(rng.uniform(*PENUMBRA_PX)), 2)))
    return blades


def transmission_map(shape: tuple[int, int], blades: list[Blade]) -> np.ndarray:
    """The collimator's transmission ``(H, W)`` in 0..1: the product of the blades' (each 1 outside its band,
    ``transmission`` inside, a linear ramp ``penumbra_px`` wide centred on the band's inner edge)."""
    height, width = shape
    rows = np.arange(height, dtype=np.float32)[:, None] + 0.5
    cols = np.arange(width, dtype=np.float32)[None, :] + 0.5
    depth = {"top": rows, "bottom": height - rows, "left": cols, "right": width - cols}  # distance from that edge
    total = np.ones(shape, np.float32)
    for blade in blades:
        inside = np.clip((blade.width_px - depth[blade.side]) / blade.penumbra_px + 0.5, 0.0, 1.0)
        total = total * (1.0 - (1.0 - blade.transmission) * inside)
    return total


def collimated_field(shape: tuple[int, int], blades: list[Blade]) -> np.ndarray:
    """True where no blade is: short of the middle of every blade's penumbra (the field's true edge)."""
    return transmission_map(shape, [Blade(b.side, b.width_px, 0.0, 1e-3) for b in blades]) > 0.5


def collimate(pixels: np.ndarray, labels: list[np.ndarray], blades: list[Blade]
              ) -> tuple[np.ndarray, list[np.ndarray]]:
    """``pixels`` through the blades; each label cleared where the transmission is below :data:`INVISIBLE_BELOW`."""
    transmission = transmission_map(pixels.shape, blades)
    visible = transmission >= INVISIBLE_BELOW
    return (pixels * transmission).astype(np.float32), [label & visible for label in labels]


def image_seed(seed: int, name: str) -> list[int]:
    return [int(seed), zlib.crc32(name.encode())]


def second_site(name: str, pixels: np.ndarray, label: np.ndarray, seed: int = 0) -> SiteImage:
    """One real image + whole-tree label → the emulated second site's image + main-artery and whole-tree labels."""
    rng = np.random.default_rng(image_seed(seed, name))
    main = main_arteries(label)
    scale = float(rng.uniform(*SCALE_RANGE))
    side = min(round(SIDE_PX / scale), *pixels.shape)
    row, col = square_crop(pixels, side, rng)
    window = (slice(row, row + side), slice(col, col + side))
    image = cv2.resize(np.asarray(pixels, np.float32)[window], (SIDE_PX, SIDE_PX), interpolation=cv2.INTER_CUBIC)
    image = np.clip(image, 0.0, 255.0)
    resized = [cv2.resize(part[window].astype(np.float32), (SIDE_PX, SIDE_PX), interpolation=cv2.INTER_LINEAR) >= 0.5
               for part in (main, np.asarray(label, bool))]
    blades = draw_blades(rng)
    image, (main_out, whole_out) = collimate(image, resized, blades)
    framing = {"crop": (row, col, side), "scale": round(SIDE_PX / side, 3),
               "blades": [(b.side, b.width_px, b.transmission, b.penumbra_px) for b in blades]}
    return SiteImage(name, image, main_out, whole_out, framing, collimated_field(image.shape, blades))
