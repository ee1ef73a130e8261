"""Size limits applied to every input before (and while) it is decoded."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class InputLimits:
    """Ceilings that protect the engine from oversized or hostile inputs.

    Attributes:
        max_faces: A mesh with more faces is refused outright.
        working_faces: Meshes above this are decimated (shape-preserving) to about this many faces.
        max_image_pixels: Largest accepted 2D image (width × height of one frame), checked
            from the header before any pixel is decoded (decompression bombs).
        max_volume_bytes: Largest accepted decoded volume (or multi-frame image stack),
            checked from the header's shape × dtype before voxels are read.
        max_image_pages: Most pages of a multi-page image (TIFF), counted from the header
            before any page is decoded (only the first, or the chosen one, is used).
    """

    max_faces: int = 500_000
    working_faces: int = 20_000
    max_image_pixels: int = 64_000_000
    max_volume_bytes: int = 1 << 30
    max_image_pages: int = 1000

    def __post_init__(self) -> None:
        for name in ("max_faces", "working_faces", "max_image_pixels", "max_volume_bytes", "max_image_pages"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be positive")


DEFAULT_LIMITS = InputLimits()


@dataclass(frozen=True)
class ShapeProbe(InputLimits):
    """Limits that stop a volume reader at its declared shape: the shape check every reader makes before any
    voxel is decoded (:func:`.volume_formats.check_bytes`) raises :class:`DeclaredShape` once the shape passes
    ``max_volume_bytes`` (:func:`.volume_cost.declared_volume`)."""


class DeclaredShape(Exception):  # noqa: N818 - a result carried out of the reader, not an error
    """A volume's declared ``shape``, sample size (``itemsize``, bytes) and DICOM ``modality`` (empty where the
    format has none), raised under a :class:`ShapeProbe`."""

    def __init__(self, shape: tuple[int, ...], itemsize: int, modality: str = ""):
        super().__init__(shape, itemsize)
        self.shape, self.itemsize = tuple(int(s) for s in shape), int(itemsize)
        self.modality = modality  # a DICOM series' Modality (CT, MR, …) where its reader knows it: the reading's kind
