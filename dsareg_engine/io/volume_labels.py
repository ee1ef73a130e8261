"""Label maps and masks read as vessels: every label above 0 is vessel unless ``options.volume_labels`` says which.

A segmentation is not an image: an expert's label map (TopCoW: 1 basilar, 2/3 PCA, 4/6 ICA, ...) or a 0/1 vessel
mask has a few whole values, 0 the background. Read by intensity it loses labels (Otsu's window "3 and up" drops
the basilar and a PCA) and all pieces but the largest. A volume is read as labels when its values are
whole numbers, at most :data:`MAX_LABELS` of them above 0, with 0 the background (at least half the voxels),
and either one value above 0 (a mask: 1, 255, ...) or label ids up to :data:`MAX_LABEL` (a volume of vessels'
partial-volume levels quantized to 100, 200, ... 800 is an image: read as labels, its outer, 1/8-filled voxels
would make the vessels 22 % too large);
``options.volume_labels`` reads it so whatever it looks like (and refuses a volume that is no label map);
``options.volume_kind`` (or a vessel window) reads it by intensity instead.

Every piece of the chosen labels (26-connected) is kept but specks (below :data:`MIN_PIECE_VOXELS` voxels and
:data:`MIN_PIECE_MM3`): an annotated tree in several pieces (vessels leaving and re-entering the field, a mask cut
at thin stretches) is the vessel model, not its largest piece. The surface is that of the kept voxels, smoothed
by :data:`SMOOTHING_SIGMA_VOX` and cut at half. Two decisions are recorded (:mod:`.input_decisions`): the labels
read as vessels, and the pieces kept with their share of the labelled voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DsaregInputError
from .input_decisions import InputDecision
from .volume_kind import VolumeReading

MAX_LABELS = 64
MAX_LABEL = 64  # label ids are small; a volume with larger whole values is an image unless it holds one value
MIN_BACKGROUND_SHARE = 0.5
MIN_PIECE_VOXELS = 8
MIN_PIECE_MM3 = 1.0
SMOOTHING_SIGMA_VOX = 0.5
SURFACE_LEVEL = 0.5


@dataclass(frozen=True)
class LabelMap:
    """The labels above 0 a volume holds (``present``, with their voxel ``counts``) and those read as vessels."""

    present: tuple[int, ...]
    counts: tuple[int, ...]
    chosen: tuple[int, ...]
    source: str  # "measured" (every label above 0) or "option" (options.volume_labels)

    @property
    def labelled(self) -> int:
        """Voxels of the chosen labels."""
        return int(sum(c for v, c in zip(self.present, self.counts) if v in self.chosen))

    def text(self) -> str:
        return "labels " + ", ".join(str(v) for v in self.chosen)


@dataclass
class LabelPieces:
    """What was kept of a label map: the voxels (``mask``), the field whose ``SURFACE_LEVEL`` crossing is their
    surface, the pieces kept / found, and the voxels kept of the chosen labels'."""

    mask: np.ndarray
    field: np.ndarray
    pieces_kept: int
    pieces: int
    voxels_kept: int
    decisions: list[InputDecision]


def _label_counts(voxels: np.ndarray) -> np.ndarray | None:
    """Voxels per value (index = value) when the values look like labels (few, whole, 0 to 65535), else None. A
    strided sample is looked at first, so an image (thousands of values) costs a sample, not a pass over the grid;
    the grid is then counted a slab at a time (no whole-grid integer copy)."""
    sample = np.unique(voxels[::8, ::8, ::8])  # a 512 x 512 x 440 CTA: 0.2 M of its 115 M voxels
    if len(sample) > MAX_LABELS + 1 or sample[0] < 0 or np.any(sample != np.round(sample)):
        return None
    counts = np.zeros(1, np.int64)
    for start in range(0, voxels.shape[0], 16):
        slab = voxels[start:start + 16]
        if float(slab.min()) < 0 or float(slab.max()) > 65535 or np.any(slab != np.round(slab)):
            return None
        found = np.bincount(slab.astype(np.int64).ravel())
        counts = np.pad(counts, (0, max(len(found) - len(counts), 0)))
        counts[:len(found)] += found
    return counts if np.count_nonzero(counts[1:]) <= MAX_LABELS else None


def label_map(voxels: np.ndarray, reading: VolumeReading, field_name: str = "volume") -> LabelMap | None:
    """The volume's labels when it is read as a label map, else None (read by its kind).

    A volume is a label map with ``reading.labels`` given, or when ``reading`` leaves kind and window to be
    detected and its values are labels with 0 the background.

    Raises:
        DsaregInputError: ``reading.labels`` given, but the volume holds no such labels or is no label map.
    """
    given = reading.labels is not None
    if not given and (reading.kind != "auto" or reading.vessel_min is not None or reading.vessel_max is not None):
        return None
    counts = _label_counts(voxels)
    if counts is None:
        if given:
            raise DsaregInputError("options.volume_labels was given but the volume is not a label map (its values "
                                   f"are not up to {MAX_LABELS} whole numbers of 0 and up)",
                                   field=field_name, accepted="a label map or 0/1 mask; or leave volume_labels out")
        return None
    present = tuple(int(v) for v in np.flatnonzero(counts) if v > 0)
    if not given and (not present or counts[0] < MIN_BACKGROUND_SHARE * counts.sum()):
        return None
    if not given and len(present) > 1 and present[-1] > MAX_LABEL:  # 100, 200, ... 800: a quantized image
        return None
    chosen = tuple(v for v in present if v in reading.labels) if given else present
    if not chosen:
        raise DsaregInputError(f"holds none of the labels {list(reading.labels or ())}; it holds "
                               f"{', '.join(map(str, present)) or 'none above 0'}", field=field_name,
                               accepted=f"options.volume_labels among {list(present)}")
    return LabelMap(present, tuple(int(counts[v]) for v in present), chosen, "option" if given else "measured")


def label_pieces(voxels: np.ndarray, labels: LabelMap, spacing: np.ndarray, field_name: str = "volume") -> LabelPieces:
    """The chosen labels' voxels, every piece but specks kept, the field of their surface and the decisions."""
    from scipy import ndimage

    from .volume_io import bounding_box

    chosen = voxels > 0 if labels.chosen == labels.present else np.isin(voxels, labels.chosen)
    box = bounding_box(chosen, margin=2)
    if box is None:
        raise DsaregInputError("no voxel carries the chosen labels", field=field_name)
    pieces, count = ndimage.label(chosen[box], structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(pieces.ravel(), minlength=count + 1)
    least = max(MIN_PIECE_VOXELS, int(np.ceil(MIN_PIECE_MM3 / float(np.prod(spacing)))))
    keep = sizes >= least
    keep[0] = False
    if not keep.any():
        raise DsaregInputError(f"the labelled voxels are only specks (no piece of {least} voxels or more)",
                               field=field_name, accepted="a label map or mask of vessels")
    mask = np.zeros(voxels.shape, bool)
    mask[box] = keep[pieces]
    field = np.zeros(voxels.shape, np.float32)
    field[box] = ndimage.gaussian_filter(mask[box].astype(np.float32), SMOOTHING_SIGMA_VOX)
    kept, total = int(sizes[keep].sum()), labels.labelled
    decisions = [
        InputDecision("volume", "vessel labels", labels.text(), f"a label map ({len(labels.present)} label(s) above "
                      "0: " + ", ".join(f"{v}: {c} voxels" for v, c in zip(labels.present, labels.counts)) + ")"
                      + ("; the labels given" if labels.source == "option" else "; every label above 0 is vessel"),
                      source=labels.source),
        InputDecision("volume", "vessel pieces", f"{int(keep.sum())} of {count} pieces",
                      f"share of the labelled voxels kept (pieces of {least} voxels or more; smaller ones are specks)",
                      round(kept / max(total, 1), 4))]
    return LabelPieces(mask, field, int(keep.sum()), count, kept, decisions)


__all__ = ["MAX_LABELS", "LabelMap", "LabelPieces", "label_map", "label_pieces"]
