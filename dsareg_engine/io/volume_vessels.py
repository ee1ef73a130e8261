"""The vessel surface of a volume, read by its kind (CTA, TOF-MRA, 3D-DSA), and a record of what was read.

:func:`extract_vessels` is the one entry point: kind (detected or given, :mod:`.volume_kind`) → the kept
vessel voxels → a shape check (:mod:`.vessel_shape`) → marching cubes (:func:`.volume_io.surface_from_mask`).

* **3D-DSA** (already subtracted): Otsu threshold of the lightly smoothed volume, largest components —
  exactly :func:`.volume_io.volume_to_mesh`.
* **CTA** (HU): bone = above ``vessel_max`` (700 HU); voxels within a partial-volume band of bone
  (``PV_BAND_MM`` plus a voxel) seed vessels only where they are a plateau in the window (a lumen: the
  carotid in its canal), never on the steep ramp of a bone surface; vessels = the HU window above the
  surface level (halfway between soft tissue and the vessels' own HU), connected components from the
  largest, then regrown into the band through voxels with no tissue-level voxel within two (the lumen's wall
  where a vessel touches bone, not the partial-volume layer of a bone surface). For the surface, voxels in the band are read as a blend
  of vessel and bone (their vessel fraction), so bone never makes a surface and a vessel in a bony
  canal keeps its wall.
* **TOF-MRA**: the head (above an Otsu air level, holes filled slice by slice); a shell
  ``MRA_SHELL_MM`` deep under the head's outer surface (skin, scalp fat, skull) is excluded; vessels =
  the bright voxels above the level halfway between brain and vessels, seeded by the brightest, with
  connected components from the largest.

CTA and MRA: when the kept voxels are largely plate-shaped (:mod:`.medial_shape`, in mm: a diploë or a
cancellous skull base inside the HU window, skull-base marrow fat in a TOF-MRA), the plate parts and what
touches them are set aside before the shape check; the shape check refuses only when nothing tube-like remains.
Then separate pieces that are not arteries (blocks of bone, venous sinuses: :mod:`.separate_pieces`) are set aside,
and the volume read again without them in the level's estimate. The decisions (kind, vessel window, bone threshold,
pieces in bone, venous sinuses, vessel shape) go to ``VolumeReadout.decisions``.

A label map or 0/1 mask (:mod:`.volume_labels`) is read as its labels, not by intensity: kind ``labels``, every
piece but specks kept, the decisions the labels read as vessels and the pieces kept.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..errors import DsaregInputError
from ..mesh import TriangleMesh
from .bone_plates import BONE_CONTACT_SHARE, PLATE_RIM_MM, plates_found, without_plates
from .input_decisions import InputDecision
from .separate_pieces import without_pieces
from .venous_sinuses import ALONG_BONE_BAND, ALONG_BONE_SHARE
from .vessel_shape import MAX_PLATE_FRACTION, PLATE_BAND, check_vessel_shape, crop_to
from .volume_io import Volume, bounding_box, largest_components, surface_from_mask
from .volume_kernels import kernels_in_use, load_kernels_for
from .volume_kind import AIR_HU, MIN_AIR_FRACTION, VolumeReading, detect_volume_kind
from .volume_labels import SURFACE_LEVEL, LabelMap, label_map, label_pieces
from .voxel_band import within_mm
from .voxel_steps import cube_minimum, filled_holes, grown, labelled, map_labels

DEFAULT_BONE_HU = 700.0
PV_BAND_MM = 1.0
PLATEAU_FRACTION = 0.3  # CTA: near bone, a lumen's gradient stays below this × (vessel − tissue) per mm
SOFT_TISSUE_HU = (-150.0, 150.0)
MRA_SHELL_MM = 7.0
MRA_EXTENT = 0.4  # MRA: vessel voxels reach down to tissue + this × (vessel − tissue)
LOCAL_PEAK_MM = 5.0
SMOOTHING_SIGMA_VOX = 0.5
VESSEL_CONTRAST_MIN = {"cta": 100.0, "mra": 6.0}  # vessel over tissue: HU (CTA), noise spreads (MRA)
VESSEL_CONTRAST_BAND = {"cta": 50.0, "mra": 1.5}  # closer to the least contrast than this: a close call
DARK_SPREADS = 3.0  # MRA: darker than the tissue by this many of its noise spreads: bone, air (CSF too)
VOID_SHARE = 0.3  # MRA: bone and air give no signal: within this share of the way from the noise floor to the tissue
BONE_MARGIN_HU = 150.0  # the vessels' estimated level within this of the bone threshold: a close call
PIECE_CONTACT_BAND = 0.15  # a separate piece this close to BONE_CONTACT_SHARE of its surface against bone: a close call
GATHER_CHUNK = 1 << 20  # voxels whose neighbours are gathered at a time (their index arrays: ~50 MB)
PIECE_DECISIONS = (  # (record, decision, basis, threshold, close-call band) of :mod:`.separate_pieces`
    ("bone", "pieces in bone", ("share of a separate piece's surface against bone (a block of bone ~1, a vessel "
                                "tree ~0.3); the piece nearest the threshold"), BONE_CONTACT_SHARE, PIECE_CONTACT_BAND),
    ("sinuses", "venous sinuses", ("share of a separate piece's medial axis whose lumen touches bone (dural sinuses "
                                   "~1, a vessel tree ~0.1-0.2); the piece nearest the threshold"), ALONG_BONE_SHARE,
     ALONG_BONE_BAND))
HEAD_MARGIN_VOX = 6  # CTA: the head's box (above air) grown by this: past the smoothing (2 voxels) and the skin


@dataclass
class VolumeReadout:
    """What was read from a volume (reported by ``dsareg inspect``, ``dsareg mesh`` and the result).

    Attributes:
        kind: ``"cta"``, ``"mra"``, ``"3d-dsa"`` or ``"labels"`` (a label map or mask); ``kind_source``: why (the
            tags, or ``options``).
        unit: ``"HU"`` (CTA), ``"intensity"`` or ``"label"``.
        vessel_min: the lowest vessel level kept; ``vessel_max``: CTA's bone level (else None).
        surface: where the surface lies: ``"level"`` (at ``vessel_min``) or ``"local half maximum"``
            (MRA: each vessel's own half maximum over the tissue).
        tissue_level, vessel_level: the estimated background tissue and vessel levels.
        voxels_kept, voxels_total: vessel voxels kept, voxels in the volume; components kept.
        faces: faces of the extracted surface (before any decimation).
        plate_share: the plate share of the kept voxels' medial axis (:mod:`.medial_shape`; vessels ~0-0.2).
        labels: a label map's labels read as vessels (else None).
        decisions: the decisions taken (kind, vessel window, bone threshold, shape), for ``Case.decisions``;
            not part of :meth:`to_dict`.
    """

    kind: str
    kind_source: str
    unit: str
    vessel_min: float
    vessel_max: float | None
    tissue_level: float | None
    vessel_level: float | None
    voxels_kept: int
    voxels_total: int
    components: int
    surface: str = "level"
    faces: int = 0
    plate_share: float | None = None
    labels: list[int] | None = None
    decisions: list[InputDecision] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        out = asdict(self)
        out.pop("decisions")
        if out["plate_share"] is not None:
            out["plate_share"] = round(float(out["plate_share"]), 3)
        for key in ("vessel_min", "vessel_max", "tissue_level", "vessel_level"):
            if out[key] is not None:
                out[key] = round(float(out[key]), 1)
        return out

    def window(self) -> str:
        """The vessel window in words: ``300 to 700 HU``, ``120 and up intensity``, ``labels 1, 2, 3``."""
        if self.labels is not None:
            return "labels " + ", ".join(str(v) for v in self.labels)
        return (f"{self.vessel_min:.0f}" + (f" to {self.vessel_max:.0f}" if self.vessel_max is not None else " and up")
                + f" {self.unit}")

    def text(self) -> str:
        surface = "" if self.surface == "level" else f", surface at each vessel's {self.surface}"
        return (f"{self.kind} ({self.kind_source}); vessel window {self.window()}{surface}; "
                f"{self.voxels_kept} of {self.voxels_total} voxels kept in {self.components} component(s)")


@dataclass
class VesselExtraction:
    """A volume's vessel surface and readout, and its masks in the box that was read. ``kept`` / ``excluded`` on the
    volume's whole grid are made when asked for (a whole head's are 0.12 GB each; a job needs neither)."""

    mesh: TriangleMesh
    readout: VolumeReadout
    kept_in_box: np.ndarray  # bool, ``box`` of the grid: the vessel voxels the surface encloses
    excluded_in_box: np.ndarray | None = None  # bool, ``box``: what was set aside (CTA bone + band, MRA scalp shell)
    box: tuple[slice, ...] | None = None  # where the masks lie in the volume's grid; None: they are the whole grid
    shape: tuple[int, ...] | None = None  # the volume's grid

    @property
    def kept(self) -> np.ndarray:
        """bool, the volume's shape: the vessel voxels the surface encloses."""
        return self._on_grid(self.kept_in_box)

    @property
    def excluded(self) -> np.ndarray | None:
        """bool, the volume's shape: what was set aside (CTA bone + band, the MRA scalp shell), or None."""
        return None if self.excluded_in_box is None else self._on_grid(self.excluded_in_box)

    def _on_grid(self, mask: np.ndarray) -> np.ndarray:
        if self.box is None or self.shape is None or mask.shape == tuple(self.shape):
            return mask
        out = np.zeros(self.shape, bool)
        out[self.box] = mask
        return out


def extract_vessels(volume: Volume, reading: VolumeReading | None = None, *, field_name: str = "volume",
                    release: bool = False) -> VesselExtraction:
    """The vessel surface (world mm) of ``volume`` read as its kind, with the readout. ``release``: the caller
    needs ``volume.data`` no more: it is let go (``None``) once the head's box is smoothed (a whole-head CTA's
    float32 grid, 0.46 GB, is not held through the reading).

    Raises:
        DsaregInputError: no vessels in the window, or a kept shape implausible for vessels (``field_name``).
    """
    from scipy import ndimage

    reading = reading or VolumeReading()
    load_kernels_for(int(np.size(volume.data)))  # a whole head: the kernels in any process (:mod:`.volume_kernels`)
    voxels = _finite(volume.data, field_name)
    labels = label_map(voxels, reading, field_name)
    if labels is not None:
        return _labelled(volume, voxels, labels, field_name)
    if reading.kind == "auto":
        kind, source = detect_volume_kind(volume.tags, voxels)
    else:
        kind, source = reading.kind, "given: volume_kind"
    spacing, shape, air = np.asarray(volume.spacing_mm), voxels.shape, _air_share(voxels)
    head = _head_box(voxels) if kind == "cta" else tuple(slice(0, n) for n in voxels.shape)
    affine = _cropped_affine(volume.affine, head)
    smooth = _smoothed(voxels[head])
    if release:
        volume.data = voxels = None  # type: ignore[assignment]
    if kind == "3d-dsa":
        (field, mask, levels), excluded, plate_share = _dsa3d(smooth, reading, field_name), None, None
    else:
        field, mask, levels, excluded, plate_share = _tubes(kind, smooth, affine, spacing, reading, field_name)
    del smooth
    total = int(np.prod(shape))
    unit = "HU" if kind == "cta" else "intensity"
    labels_count = int(ndimage.label(crop_to(mask))[1])
    readout = VolumeReadout(kind, source, unit, levels.get("low", levels["min"]), levels.get("max"),
                            levels.get("tissue"), levels.get("vessel"), int(np.count_nonzero(mask)), total,
                            labels_count, "local half maximum" if "low" in levels else "level")
    measures = check_vessel_shape(mask, spacing, readout, field_name=field_name, plate_share=plate_share,
                                  total_voxels=total)
    readout.plate_share = measures["plate_fraction"]
    readout.decisions = _decisions(readout, reading, air, levels)
    mesh = surface_from_mask(field, mask, levels["min"], affine, field_name=field_name)
    del field
    readout.faces = mesh.n_faces
    return VesselExtraction(mesh, readout, mask, excluded, head, tuple(shape))


def _smoothed(voxels: np.ndarray) -> np.ndarray:
    """``ndimage.gaussian_filter(voxels, SMOOTHING_SIGMA_VOX)``: the numba kernel's bits where this process has numba
    loaded (:mod:`.volume_kernels`, :mod:`.smoothing_kernels`), else scipy's."""
    if not kernels_in_use():
        from scipy import ndimage

        return ndimage.gaussian_filter(voxels, SMOOTHING_SIGMA_VOX)
    from .smoothing_kernels import smoothed

    return smoothed(voxels, SMOOTHING_SIGMA_VOX)


def _air_share(voxels: np.ndarray) -> float:
    """The share of voxels below ``AIR_HU`` (every second voxel per axis): the air around a head in HU."""
    return float(np.mean(voxels[::2, ::2, ::2] < AIR_HU))


def _head_box(voxels: np.ndarray) -> tuple[slice, ...]:
    """A CTA's head: the box of the voxels above air (``AIR_HU``), grown by ``HEAD_MARGIN_VOX`` (past the smoothing's
    reach and the skin's partial volume). The air around a head holds no vessel, tissue or bone level, so reading
    the box reads the same; a whole-head series is half air (memory and time follow the box, not the grid)."""
    return bounding_box(voxels > AIR_HU, margin=HEAD_MARGIN_VOX) or tuple(slice(0, n) for n in voxels.shape)


def _cropped_affine(affine: np.ndarray, box: tuple[slice, ...]) -> np.ndarray:
    """The affine of the sub-grid ``box`` (its voxel 0 is the grid's voxel ``box.start``)."""
    out = np.array(affine, float)
    out[:3, 3] = affine[:3, :3] @ np.array([b.start for b in box], float) + affine[:3, 3]
    return out


def _labelled(volume: Volume, voxels: np.ndarray, labels: LabelMap, field_name: str) -> VesselExtraction:
    """A label map's or mask's vessels (:mod:`.volume_labels`), shape-checked like any other reading."""
    spacing = np.asarray(volume.spacing_mm)
    pieces = label_pieces(voxels, labels, spacing, field_name)
    source = "given: volume_labels" if labels.source == "option" else (
        f"a label map: whole values, {len(labels.present)} label(s) above 0 on a background of 0")
    readout = VolumeReadout("labels", source, "label", float(min(labels.chosen)), None, None, None,
                            pieces.voxels_kept, int(voxels.size), pieces.pieces_kept, labels=list(labels.chosen))
    readout.plate_share = check_vessel_shape(pieces.mask, spacing, readout, field_name=field_name)["plate_fraction"]
    readout.decisions = pieces.decisions + [InputDecision(
        "volume", "vessel shape", "tubes", "plate share of the kept voxels' medial axis", readout.plate_share,
        MAX_PLATE_FRACTION, PLATE_BAND)]
    mesh = surface_from_mask(pieces.field, pieces.mask, SURFACE_LEVEL, volume.affine, field_name=field_name)
    readout.faces = mesh.n_faces
    return VesselExtraction(mesh, readout, pieces.mask, None)


def _tubes(kind: str, smooth: np.ndarray, affine: np.ndarray, spacing: np.ndarray, reading: VolumeReading,
           field_name: str):
    """CTA / MRA: ``(field, mask, levels, excluded, plate_share)``, read by :func:`_tubes_pass`. When that set
    separate pieces aside (bone, venous sinuses) and the vessels' level was estimated (not given), the level was
    estimated with the pieces' voxels among the vessels' (a venous system outweighs a carotid territory: the window
    starts low enough to take noise in): the reading is done again with the pieces and their rim left out of the
    estimate and of the seeds."""
    ground = (_cta_ground if kind == "cta" else _mra_ground)(smooth, affine, spacing, reading, field_name)
    field, mask, levels, excluded, plate_share, read_mask = _tubes_pass(kind, smooth, spacing, reading, field_name,
                                                                        ground, None)
    first = levels["pieces"]
    if reading.vessel_min is None and any(found.set_aside is not None for found in first.values()):
        shape, rim = mask.shape, max(1, int(np.ceil(PLATE_RIM_MM / float(spacing.min()))))
        pieces = np.zeros(shape, bool)
        for found in first.values():
            if found.set_aside is not None:
                pieces |= found.set_aside
        around, box = np.zeros(shape, bool), bounding_box(pieces, margin=rim)
        around[box] = grown(pieces[box], rim)
        left_out = (_Packed.of(around), _Packed.of(pieces))  # (memory: 1 bit a voxel through the second reading)
        first = {name: replace(found, set_aside=None) for name, found in first.items()}
        del field, mask, levels, excluded, read_mask, around, pieces  # the first reading's: not held through the second
        _unpack(ground)
        field, mask, levels, excluded, plate_share, read_mask = _tubes_pass(kind, smooth, spacing, reading,
                                                                            field_name, ground, left_out)
        excluded[left_out[1].grid()] = True
        del left_out
        levels["pieces"] = {name: first[name].then(found) for name, found in levels["pieces"].items()}
    if kind == "cta":  # the surface's field, of the last reading, made in ``smooth`` (no longer read)
        held = _Packed.of(excluded)  # (memory: 1 bit a voxel while the field is made)
        del excluded
        _unpack(ground)
        field = _cta_field(smooth, ground, read_mask.grid(), levels)
        ground.near_bone = None  # type: ignore[assignment]
        excluded = held.grid()
    return field, mask, levels, excluded, plate_share


def _tubes_pass(kind: str, smooth: np.ndarray, spacing: np.ndarray, reading: VolumeReading, field_name: str, ground,
                left_out: tuple[_Packed, _Packed] | None):
    """One CTA / MRA reading: ``(field, mask, levels, excluded, plate_share, read_mask)``; ``left_out``: the
    pieces an earlier pass set aside, ``(with their rim, themselves)``: out of the level's estimate and out of the
    seeds; or None.

    Bone in the window (a diploë, a cancellous skull base, marrow fat) is a plate: set aside
    (:func:`.bone_plates.without_plates`); when plates were set aside and the level was estimated, it was estimated
    with their voxels among the vessels' (a cancellous skull base outweighs the vessels: the level lands above thin
    vessels, and the distal tree falls apart at coarse voxels): read again with the plates and their rim left out of
    the estimate. Then separate pieces of bone and venous sinuses are set aside (:func:`_without_pieces`).
    ``read_mask``: CTA, the voxels read before any was set aside, packed (the surface's field, :func:`_cta_field`);
    the ``ground``'s grid is left packed (:func:`_pack`: not held whole through the last labelling)."""
    field, mask, levels, excluded, found, earlier = _plates_read(kind, smooth, spacing, reading, field_name, ground,
                                                                 left_out)
    read_mask = None
    if kind == "cta":
        excluded = ground.near_bone & ~mask  # bone and its band beyond the reading's voxels (⊇ bone)
        read_mask = _Packed.of(mask)
    _pack(ground)  # (memory: bone's band is not held whole through the last labelling)
    excluded |= found.plates
    if earlier is not None:
        excluded |= earlier.grid()
    del earlier
    bone_of = _bone_of(kind, smooth, spacing, excluded, levels, ground)
    mask, plate_share = without_plates(mask, found, field_name, spacing, bone_of)
    del found
    mask, levels["pieces"] = without_pieces(mask, spacing, bone_of)
    for pieces in levels["pieces"].values():
        if pieces.set_aside is not None:
            excluded |= pieces.set_aside
    if any(found.set_aside is not None for found in levels["pieces"].values()):
        plate_share = None  # measured again on what is kept
    return field, mask, levels, excluded, plate_share, read_mask


def _plates_read(kind: str, smooth: np.ndarray, spacing: np.ndarray, reading: VolumeReading, field_name: str, ground,
                 left_out: tuple[_Packed, _Packed] | None):
    """A reading and its plates (:func:`.bone_plates.plates_found`), read again without the plates in the estimate
    when there are any and the level was estimated: ``(field, mask, levels, excluded, found, earlier)``; ``earlier``:
    the first reading's plates, packed (only the picture needs them), or None."""

    around, pieces = (None, None) if left_out is None else left_out

    def read(not_vessels):  # the ground (bone and its band; the head's interior) is the same in both readings
        reader = _cta if kind == "cta" else _mra
        return reader(smooth, spacing, reading, field_name, ground, not_vessels, pieces)

    def bone_of(excluded, levels, mask):  # what a plate of bone lies against (:func:`.bone_plates.bone_plates`), in a box
        if kind == "cta":  # bone and its band beyond the reading's voxels (not held as a grid of its own)
            return lambda box: ground.near_bone[box] & ~mask[box]
        return lambda box: _dark_or_surface(smooth, excluded, levels, spacing, box, ground.air)

    field, mask, levels, excluded = read(around)  # CTA: excluded None; MRA: the scalp shell
    found = plates_found(mask, spacing, bone_of(excluded, levels, mask))
    earlier = None
    if found.plates.any() and reading.vessel_min is None:
        rim = max(1, int(np.ceil(PLATE_RIM_MM / float(spacing.min()))))
        set_aside, box = np.zeros(mask.shape, bool), bounding_box(found.plates, margin=rim)
        set_aside[box] = grown(found.plates[box], rim)
        if around is not None:
            set_aside |= around.grid()
        earlier = _Packed.of(found.plates)
        del field, mask, excluded, found  # the first reading's: not held through the second
        set_aside = _Packed.of(set_aside)  # (memory: 1 bit a voxel through the reading)
        field, mask, levels, excluded = read(set_aside)
        del set_aside
        found = plates_found(mask, spacing, bone_of(excluded, levels, mask))
    return field, mask, levels, excluded, found, earlier


def _bone_of(kind: str, smooth: np.ndarray, spacing: np.ndarray, excluded: np.ndarray, levels: dict, ground):
    """What bone lies where a box of the reading lies (``bone_of(box)``, bool): CTA, bone and its band beyond the
    reading's voxels and the plates (``excluded``, which the pieces set aside then join); MRA, the voids and the
    scalp shell (:func:`_dark_or_surface`)."""
    if kind == "cta":
        return lambda box: excluded[box]
    return lambda box: _dark_or_surface(smooth, excluded, levels, spacing, box, ground.air)


def _pack(ground) -> None:
    """Packs ``ground``'s grid (CTA: ``near_bone``; MRA: ``interior``) as a :class:`_Packed`, in place."""
    name = "near_bone" if isinstance(ground, _CtaGround) else "interior"
    if not isinstance(getattr(ground, name), _Packed):
        setattr(ground, name, _Packed.of(getattr(ground, name)))


def _unpack(ground) -> None:
    """Unpacks ``ground``'s grid (:func:`_pack`), in place."""
    name = "near_bone" if isinstance(ground, _CtaGround) else "interior"
    setattr(ground, name, _grid(getattr(ground, name)))


@dataclass(frozen=True)
class _Packed:
    """A bool grid packed 8 voxels to a byte (``np.packbits``), held through a reading and unpacked where used."""

    bits: np.ndarray
    shape: tuple[int, ...]

    @classmethod
    def of(cls, grid: np.ndarray) -> _Packed:
        return cls(np.packbits(grid), tuple(grid.shape))

    def grid(self) -> np.ndarray:
        return np.unpackbits(self.bits, count=int(np.prod(self.shape))).reshape(self.shape).view(bool)


def _grid(mask) -> np.ndarray:
    """A bool grid of ``mask``: itself, or a :class:`_Packed` unpacked."""
    return mask.grid() if isinstance(mask, _Packed) else mask


def _dark_or_surface(smooth: np.ndarray, shell: np.ndarray, levels: dict, spacing: np.ndarray,
                     box: tuple[slice, ...], air: float) -> np.ndarray:
    """TOF-MRA: what fat and marrow lie against: the scalp ``shell`` and the signal voids (cortical bone, air: no
    signal, at the noise floor ``air``), with a partial-volume band of ``PV_BAND_MM`` plus a voxel around them (a
    plate's surface voxels are a blend of it and the bone beside it); within ``box``. A void is darker than the
    tissue by ``DARK_SPREADS`` of its spreads and within ``VOID_SHARE`` of the way from the floor to the tissue: CSF
    is dark too, but it has a signal (~0.4 of the brain's), and vessels run through CSF cisterns."""
    band = PV_BAND_MM + float(spacing.max())
    reach = np.ceil(band / spacing).astype(int) + 1
    grown = tuple(slice(max(b.start - r, 0), min(b.stop + r, n)) for b, r, n in zip(box, reach, smooth.shape))
    tissue = levels["tissue"]
    void = min(tissue - DARK_SPREADS * levels["spread"], air + VOID_SHARE * (tissue - air))
    dark = shell[grown] | (smooth[grown] < void)
    inner = tuple(slice(b.start - g.start, b.stop - g.start) for b, g in zip(box, grown))
    return within_mm(dark, spacing, band)[inner]


def _decisions(readout: VolumeReadout, reading: VolumeReading, air: float, levels: dict) -> list[InputDecision]:
    """What was decided about the volume, each with its measure and close-call band (:mod:`.input_decisions`);
    ``air``: :func:`_air_share`."""
    decisions = [_kind_decision(readout, reading, air)]
    if readout.kind != "3d-dsa":
        given = reading.vessel_min is not None
        contrast = (levels["vessel"] - levels["tissue"]) if levels.get("vessel") is not None else None
        basis = "vessel over tissue contrast (HU); the window starts halfway"
        if readout.kind == "mra" and contrast is not None:
            contrast, basis = contrast / max(levels["spread"], 1e-6), ("vessel over tissue contrast in the "
                                                                          "tissue's noise spreads; the window starts halfway")
        window = f"{readout.vessel_min:.0f}" + (f" to {readout.vessel_max:.0f}" if readout.vessel_max is not None
                                                  else " and up") + f" {readout.unit}"
        least, band = VESSEL_CONTRAST_MIN[readout.kind], VESSEL_CONTRAST_BAND[readout.kind]
        decisions.append(InputDecision("volume", "vessel window", window, basis, contrast, least, band,
                                       "option" if given else "measured"))
    if readout.kind == "cta":
        decisions.append(InputDecision(
            "volume", "bone threshold", f"{readout.vessel_max:.0f} HU",
            "the vessels' level (HU) against the bone threshold", levels.get("vessel"), readout.vessel_max,
            BONE_MARGIN_HU, "option" if reading.vessel_max is not None else "measured"))
    for name, what, basis, threshold, band in PIECE_DECISIONS:
        found = levels.get("pieces", {}).get(name)
        if found is not None and (found.count or found.nearest_share is not None):
            decisions.append(InputDecision("volume", what, f"{found.count} set aside" if found.count else "none",
                                           basis, found.nearest_share, threshold, band))
    decisions.append(InputDecision(
        "volume", "vessel shape", "tubes", "plate share of the kept voxels' medial axis", readout.plate_share,
        MAX_PLATE_FRACTION, PLATE_BAND))
    return decisions


def _kind_decision(readout: VolumeReadout, reading: VolumeReading, air: float) -> InputDecision:
    if reading.kind != "auto":
        return InputDecision("volume", "volume kind", readout.kind, readout.kind_source, source="option")
    if readout.kind_source.startswith(("Modality MR", "Image Type", "Modality XA", "Modality ")) and \
            "air" not in readout.kind_source:
        return InputDecision("volume", "volume kind", readout.kind, readout.kind_source, source="tag")
    return InputDecision("volume", "volume kind", readout.kind, f"{readout.kind_source}; share of voxels below "
                         f"{AIR_HU:.0f} (air around a head in HU)", air, MIN_AIR_FRACTION, MIN_AIR_FRACTION / 2.0)


def _finite(data: np.ndarray, field_name: str) -> np.ndarray:
    voxels = np.asarray(data, dtype=np.float32)
    if voxels.ndim != 3 or min(voxels.shape) < 2:
        raise DsaregInputError(f"needs a 3D volume, got shape {list(voxels.shape)}", field=field_name)
    high, low = float(voxels.max()), float(voxels.min())
    if not (np.isfinite(high) and np.isfinite(low)):  # NaN and ±inf reach the extremes
        fill = float(np.nanmin(voxels)) if np.isfinite(voxels).any() else 0.0
        voxels = np.nan_to_num(voxels, nan=fill, posinf=0.0, neginf=0.0)
        high, low = float(voxels.max()), float(voxels.min())
    if high - low <= 0:
        raise DsaregInputError("is constant: no vessels in it", field=field_name,
                               accepted="a CTA, TOF-MRA or 3D-DSA volume (vessels brighter than their surroundings)")
    return voxels


def _no_vessels(what: str, field_name: str, kind: str) -> DsaregInputError:
    return DsaregInputError(f"no vessels found: {what}", field=field_name,
                            accepted=f"a {kind} volume with contrast-filled vessels; or set options.volume_kind / "
                                     "options.volume_vessel_min / options.volume_vessel_max")


def _dsa3d(smooth: np.ndarray, reading: VolumeReading, field_name: str):
    from skimage.filters import threshold_otsu

    level = float(reading.vessel_min) if reading.vessel_min is not None else float(threshold_otsu(smooth))
    mask = largest_components(smooth > level, field_name=field_name)
    return smooth, mask, {"min": level}


@dataclass
class _CtaGround:
    """What a CTA reading stands on, whatever the vessels' level: bone (above ``bone_hu``), the voxels within
    its partial-volume band (``PV_BAND_MM`` plus a voxel; bone included) and the soft tissue's level (HU)."""

    bone_hu: float
    tissue: float
    near_bone: np.ndarray  # (bone itself, ``smooth > bone_hu``, is not held: :func:`_cta_field` takes it again)


def _cta_ground(smooth: np.ndarray, affine: np.ndarray, spacing: np.ndarray, reading: VolumeReading,
                field_name: str) -> _CtaGround:
    bone_hu = float(reading.vessel_max) if reading.vessel_max is not None else DEFAULT_BONE_HU
    bone = smooth > bone_hu
    soft = (smooth > SOFT_TISSUE_HU[0]) & (smooth < SOFT_TISSUE_HU[1])
    if np.count_nonzero(soft) < 100:
        raise _no_vessels(f"no soft tissue between {SOFT_TISSUE_HU[0]:.0f} and {SOFT_TISSUE_HU[1]:.0f} HU "
                          "(is this a CT in HU?)", field_name, "CTA")
    tissue = float(np.median(smooth[soft]))
    near_bone = within_mm(bone, spacing, PV_BAND_MM + float(spacing.max()))
    return _CtaGround(bone_hu, tissue, near_bone)


def _cta(smooth: np.ndarray, spacing: np.ndarray, reading: VolumeReading, field_name: str, ground: _CtaGround,
         not_vessels=None, not_seeds=None):
    """``not_vessels``: voxels left out of the vessels' level estimate (plates set aside), or None; ``not_seeds``:
    voxels that seed no vessel (pieces set aside by an earlier pass), or None; each a bool grid or :class:`_Packed`."""
    bone_hu, tissue, near_bone = ground.bone_hu, ground.tissue, ground.near_bone
    candidates = (smooth > tissue + 100.0) & (smooth < bone_hu) & ~near_bone
    if not_vessels is not None:
        candidates[_grid(not_vessels)] = False
    if reading.vessel_min is not None:
        level = float(reading.vessel_min)
        vessel = None
    else:
        if np.count_nonzero(candidates) < 8:
            raise _no_vessels(f"no voxels between {tissue + 100:.0f} and {bone_hu:.0f} HU away from bone",
                              field_name, "CTA")
        vessel = float(np.percentile(smooth[candidates], 75))
        level = (tissue + vessel) / 2.0
    del candidates  # (memory: a head's box)
    window = (smooth > level) & (smooth < bone_hu)
    if np.count_nonzero(window & ~near_bone) < 8:
        raise _no_vessels(f"no voxels in the window {level:.0f} to {bone_hu:.0f} HU away from bone", field_name, "CTA")
    peak = vessel if vessel is not None else float(np.percentile(smooth[window & ~near_bone], 75))
    # near bone, only a plateau in the window is a lumen (a vessel in a bony canal); a partial-volume voxel
    # at a bone surface sits on a steep ramp from tissue to bone
    seeds = window & ~near_bone
    seeds |= _plateau(smooth, window & near_bone, spacing, PLATEAU_FRACTION * (peak - tissue))
    if not_seeds is not None:
        seeds[_grid(not_seeds)] = False
    core = largest_components(seeds, field_name=field_name)
    del seeds
    # regrow into the band only through voxels with no tissue-level voxel near: the lumen and wall of a vessel
    # in a bony canal (vessel and bone around), not the partial-volume layer of a bone surface (tissue beside)
    steps = int(np.ceil(PV_BAND_MM / float(spacing.min()))) + 1  # the wall beside bone: the lumen is seeded
    mask = _regrown(core, window, smooth, level, steps)
    # the surface's field: :func:`_cta_field` (made by the caller once the reading is final)
    return None, mask, {"min": level, "max": bone_hu, "tissue": tissue, "vessel": peak}, None  # (excluded: the caller's)


def _cta_field(smooth: np.ndarray, ground: _CtaGround, read_mask: np.ndarray, levels: dict) -> np.ndarray:
    """The field a CTA's surface is marched in: :func:`_partial_volume_field`, and no surface at bone and its band
    outside the voxels the reading kept (``read_mask``, before plates were set aside). Made in ``smooth`` itself: its
    last use (a whole head's float32 box, 0.23 GB, is not copied at the reading's peak)."""
    near = ground.near_bone  # bone is in its own band
    field = _partial_volume_field(smooth, near, levels["tissue"], levels["vessel"], smooth > ground.bone_hu,
                                  levels["max"], in_place=True)
    outside = near & ~read_mask
    field[outside] = np.minimum(field[outside], levels["tissue"])  # no surface there
    return field


def _regrown(core: np.ndarray, window: np.ndarray, smooth: np.ndarray, level: float, steps: int) -> np.ndarray:
    """``core`` grown by ``steps`` voxels through ``window`` voxels with no tissue-level voxel within two (the
    minimum of their 5³ neighbourhood above ``level``), within ``core``'s box grown by ``steps`` (the growth cannot
    leave it; the minimum is taken with a 2-voxel halo, so it is the full grid's)."""

    hits = bounding_box(core)  # the core is never empty (its largest components)
    low = np.maximum(np.array([h.start for h in hits]) - steps, 0)
    high = np.minimum(np.array([h.stop for h in hits]) + steps, core.shape)
    outer_low, outer_high = np.maximum(low - 2, 0), np.minimum(high + 2, core.shape)
    inner = tuple(slice(a - b, c - b) for a, b, c in zip(low, outer_low, high))
    box, outer = (tuple(slice(a, b) for a, b in zip(lo, hi)) for lo, hi in ((low, high), (outer_low, outer_high)))
    through = cube_minimum(smooth[outer] > level, 5, in_place=True)[inner]  # no tissue within 2 voxels (all above)
    np.logical_and(through, window[box], out=through)  # (in place: a whole head's box is 0.13 GB a mask)
    np.logical_or(through, core[box], out=through)
    mask = np.zeros(core.shape, bool)
    mask[box] = grown(core[box], steps, through)
    return mask


def _plateau(smooth: np.ndarray, where: np.ndarray, spacing: np.ndarray, max_gradient_per_mm: float) -> np.ndarray:
    """The voxels of ``where`` whose gradient (central differences, per mm) is below ``max_gradient_per_mm``: by
    :func:`.voxel_kernels.flat_at` where numba is loaded (the same voxels), else gathered a chunk at a time."""
    out = np.zeros(smooth.shape, bool)
    every = np.flatnonzero(where)  # flat indices: one gather per neighbour, not three
    if smooth.dtype == np.float32 and kernels_in_use():
        from .voxel_kernels import flat_at

        out.reshape(-1)[every] = flat_at(smooth, every, np.asarray(spacing, np.float64),
                                         np.float32(max_gradient_per_mm))
        return out
    values = np.ravel(smooth)
    strides = np.cumprod((1,) + smooth.shape[:0:-1])[::-1]
    for start in range(0, len(every), GATHER_CHUNK):  # a chunk at a time: its index arrays stay small
        index = every[start:start + GATHER_CHUNK]
        position = np.unravel_index(index, smooth.shape)
        squared = np.zeros(len(index), np.float32)
        for axis, stride in enumerate(strides):
            up = np.where(position[axis] < smooth.shape[axis] - 1, index + stride, index)  # the border: its own value
            down = np.where(position[axis] > 0, index - stride, index)
            squared += ((values[up] - values[down]) / (2.0 * spacing[axis])) ** 2
        out.reshape(-1)[index] = np.sqrt(squared) < max_gradient_per_mm
    return out


def _partial_volume_field(smooth, near_bone, tissue: float, vessel: float, bone: np.ndarray, bone_hu: float,
                          in_place: bool = False):
    """Near bone, a voxel brighter than the vessels is read as vessel blended with bone: its vessel fraction
    mapped back onto the tissue → vessel scale; bone itself reads as tissue (it makes no surface). ``in_place``:
    written into ``smooth`` (else a copy)."""
    bone_level = float(np.median(smooth[bone])) if bone.any() else bone_hu
    blend = near_bone & (smooth > vessel)
    field = smooth if in_place else smooth.copy()
    bone_fraction = np.clip((smooth[blend] - vessel) / max(bone_level - vessel, 1.0), 0.0, 1.0)
    field[blend] = tissue + (1.0 - bone_fraction) * (vessel - tissue)
    return field


def _head_mask(smooth: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Inside the head: above an Otsu level between air and tissue, holes filled in 3D and slice by slice.

    The volume's faces are not the head's surface: a TOF slab or a crop cuts through the head, so the closing
    runs on the mask continued past its faces (padded with its edge) and does not erode the head from them; only
    real air makes an outside (the MRA scalp shell is measured from it)."""
    from skimage.filters import threshold_otsu

    sample = smooth[::2, ::2, ::2]
    level = float(threshold_otsu(sample[sample < np.percentile(sample, 99.0)]))
    pad = 2  # the closing's reach (its iterations)
    padded = np.pad(smooth > 0.5 * level, pad, mode="edge")
    closed = ~grown(~grown(padded, pad), pad)  # binary_closing's voxels pad and more inside the grid's faces
    head = closed[pad:-pad, pad:-pad, pad:-pad]
    axial = int(np.argmax(np.abs(affine[2, :3])))  # the voxel axis closest to patient z
    filled = filled_holes(head)
    moved = np.moveaxis(filled, axial, 0)
    for index in range(moved.shape[0]):
        moved[index] = filled_holes(moved[index])
    return filled


@dataclass
class _MraGround:
    """What a TOF-MRA reading stands on, whatever the vessels' level: the head's interior (deeper than
    ``MRA_SHELL_MM`` under its surface) and the tissue's level and noise spread there; ``air``: the noise floor
    (the median outside the head; else the volume's 1st percentile)."""

    interior: np.ndarray
    tissue: float
    spread: float
    air: float


def _mra_interior(head: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """The head deeper than ``MRA_SHELL_MM`` under its surface (the scalp's bright fat lies in that shell).

    Where the volume's faces cut the head, the cut is surface too (a whole head cut at the neck: its face holds the
    bottom of the scalp), unless measuring from the faces leaves less than half of the interior measured from the
    air alone: a TOF slab, whose faces cut through the brain across the whole head."""
    from_air = head & ~within_mm(~head, spacing, MRA_SHELL_MM)
    if not any(face.any() for axis in range(3) for face in (head.take(0, axis), head.take(-1, axis))):
        return from_air  # no face cuts the head: measuring from the faces too changes nothing
    from_faces = from_air & ~_near_faces(head.shape, spacing, MRA_SHELL_MM)
    return from_faces if np.count_nonzero(from_faces) >= 0.5 * np.count_nonzero(from_air) else from_air


def _near_faces(shape, spacing: np.ndarray, band_mm: float) -> np.ndarray:
    """bool, ``shape``: the voxels within ``band_mm`` of the grid's faces, a face being the layer of voxels just
    outside the grid (``d × spacing ≤ band_mm``, ``d`` = 1 for a voxel on the border): what
    :func:`.voxel_band.within_mm` adds to the air's band when the grid is padded by one outside layer (the nearest
    voxel of a whole face layer is the one straight across, at an offset along one axis only)."""
    out = np.zeros(shape, bool)
    for axis, size in enumerate(shape):
        steps = np.arange(1, size + 1, dtype=np.float64) * float(spacing[axis])  # to the face before index 0
        near = (steps <= band_mm) | (steps[::-1] <= band_mm)
        out |= near.reshape([-1 if b == axis else 1 for b in range(3)])
    return out


def _mra_ground(smooth: np.ndarray, affine: np.ndarray, spacing: np.ndarray, reading: VolumeReading,
                field_name: str) -> _MraGround:
    head = _head_mask(smooth, affine)
    interior = _mra_interior(head, spacing)
    if np.count_nonzero(interior) < 1000:
        raise _no_vessels(f"no head interior deeper than {MRA_SHELL_MM:.0f} mm under the surface", field_name, "MRA")
    tissue, spread = _mode_and_upper_spread(smooth[interior])
    outside = smooth[::2, ::2, ::2][~head[::2, ::2, ::2]]
    air = float(np.median(outside)) if outside.size >= 1000 else float(np.percentile(smooth[::2, ::2, ::2], 1.0))
    return _MraGround(interior, tissue, spread, air)


def _mra(smooth: np.ndarray, spacing: np.ndarray, reading: VolumeReading, field_name: str, ground: _MraGround,
         not_vessels=None, not_seeds=None):
    """``not_vessels``: voxels left out of the vessels' level estimate (plates set aside), or None; ``not_seeds``:
    voxels that are no vessel (pieces set aside by an earlier pass), or None; each a bool grid or :class:`_Packed`."""
    interior, tissue, spread = ground.interior, ground.tissue, ground.spread
    values = smooth[interior]
    if not_vessels is not None:
        values = smooth[interior & ~_grid(not_vessels)]
    bright = values[values > tissue + 6.0 * spread]
    if reading.vessel_min is not None:
        level, vessel = float(reading.vessel_min), None
    else:
        if bright.size < 8:
            raise _no_vessels(f"nothing inside the head brighter than the tissue ({tissue:.0f}) by 6 spreads "
                              f"({6 * spread:.0f})", field_name, "MRA")
        vessel = float(np.percentile(bright, 75))
        level = (tissue + vessel) / 2.0
    del values, bright  # (memory: the interior's values, 4 bytes a voxel of it, are not held through the labelling)
    low = level if reading.vessel_min is not None else tissue + MRA_EXTENT * (vessel - tissue)
    candidates = interior & (smooth > low)
    if not_seeds is not None:
        candidates[_grid(not_seeds)] = False
    if np.count_nonzero(candidates) < 8:
        raise _no_vessels(f"no voxels above {low:.0f} inside the head", field_name, "MRA")
    peak = vessel if vessel is not None else float(np.percentile(smooth[candidates], 75))
    seeds = candidates & (smooth > tissue + 0.75 * (peak - tissue))
    mask = largest_components(_seeded(candidates, seeds), field_name=field_name)
    del candidates  # (memory: a 300-slice slab's grids are the reading's peak here)
    if reading.vessel_min is not None:
        return smooth, mask, {"min": level, "tissue": tissue, "vessel": peak, "spread": spread}, ~interior
    field = _local_half_maximum(smooth, mask, tissue, spacing, level)
    # what crosses its own half maximum, connected to the bright vessels: drops texture blobs that reached
    # the vessels through voxels below half the vessels' own contrast
    mask = largest_components(_seeded(mask & (field > level), seeds), field_name=field_name)
    return field, mask, {"min": level, "low": low, "tissue": tissue, "vessel": peak, "spread": spread}, ~interior


def _seeded(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The components of ``mask`` (face neighbours) that hold a voxel of ``seeds``: labels in 16 bits where they
    fit, a table over them (not ``np.isin`` of the labels: a grid of int32 and its sort)."""
    labels, count = labelled(mask, narrow_above=0)
    keep = np.zeros(count + 1, bool)
    keep[labels[seeds]] = True
    keep[0] = False
    out = np.zeros(mask.shape, bool)
    map_labels(out, keep, labels)
    return out


def _mode_and_upper_spread(values: np.ndarray) -> tuple[float, float]:
    """The most common value (the brain; the skull and CSF left inside the shell are darker) and the
    spread of the values above it (σ of a Gaussian: 1.4826 × their median distance from the mode)."""
    low, high = np.percentile(values, [0.5, 99.5])
    counts, edges = np.histogram(values, bins=256, range=(float(low), float(high)))
    from scipy import ndimage

    mode_bin = int(np.argmax(ndimage.gaussian_filter1d(counts.astype(float), 2.0)))
    mode = float((edges[mode_bin] + edges[mode_bin + 1]) / 2.0)
    above = values[values > mode] - mode
    return mode, 1.4826 * float(np.median(above)) if above.size else 0.0


def _local_half_maximum(smooth: np.ndarray, mask: np.ndarray, tissue: float, spacing: np.ndarray,
                        level: float) -> np.ndarray:
    """A field whose ``level`` crossing is each vessel's own half maximum over the tissue (in-flow signal
    fades along the tree, and thin vessels peak lower after blur): the tissue → local-peak scale mapped
    onto tissue → 2 × (level − tissue), near the kept voxels (their bounding box)."""
    from scipy import ndimage

    box = np.argwhere(mask)
    pad = 4
    low, high = np.maximum(box.min(0) - pad, 0), np.minimum(box.max(0) + pad + 1, mask.shape)
    region = tuple(slice(a, b) for a, b in zip(low, high))
    size = np.maximum(3, np.round(LOCAL_PEAK_MM / spacing).astype(int) | 1)
    scale = np.where(mask[region], smooth[region], tissue)
    local = ndimage.maximum_filter(scale, size=tuple(size))
    ndimage.maximum_filter(local, size=3, output=scale)  # reach the voxels just outside the kept ones
    del local  # (memory: two of the region's float grids at a time, not five)
    np.maximum(np.subtract(scale, tissue, out=scale), 1e-3, out=scale)
    field = np.full(smooth.shape, tissue, np.float32)
    part = field[region]  # tissue + (smooth - tissue) / scale * 2 * (level - tissue), in place, in that order
    np.subtract(smooth[region], tissue, out=part)
    part /= scale
    part *= 2.0
    part *= level - tissue
    part += tissue
    return field


__all__ = ["VesselExtraction", "VolumeReadout", "extract_vessels"]
