"""3D volumes (3D-RA / CTA) and their conversion to a vessel surface mesh.

**World frame** (one choice, used by every reader here): *patient LPS millimetres*,
as DICOM defines it (+x toward the patient's Left, +y Posterior, +z Superior).

* DICOM series / enhanced multi-frame: ``ImagePositionPatient``,
  ``ImageOrientationPatient`` and ``PixelSpacing`` are already LPS.
* NIfTI: the sform/qform affine is RAS; it is converted with ``diag(-1, -1, 1, 1) · A``.
* NRRD: ``space`` ``left-posterior-superior`` is used as is; ``right-anterior-superior``
  is converted like NIfTI; files without a space use their directions as given.
* MetaImage (``.mha``, ``.mhd`` + data), detached NRRD (``.nhdr`` + data), legacy VTK structured points: read by
  SimpleITK (:mod:`.volume_formats`), whose physical space is LPS (a VTK image has none: used as LPS, with a warning).
* 3D-2D-GS-CA ``.rad`` + ``.raw``: the data set's own world frame (``TPosition``),
  which its 2D ``.rad`` headers share, so mesh and views agree without conversion.

A :class:`Volume` holds ``data`` indexed ``[i, j, k]`` and ``affine`` mapping
``(i, j, k, 1)`` to world mm. Every reader checks the header's shape × sample size
against ``limits.max_volume_bytes`` before any voxel is decoded.
"""

from __future__ import annotations

import gzip
import io
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..mesh import TriangleMesh
from . import rad as rad_format
from .dicom_identity import DicomIdentity, identity_or_none, parse_dicom, series_headers
from .file_parts import PART_LISTS, volume_parts
from .image_io import dicom_number
from .limits import DEFAULT_LIMITS, InputLimits
from .volume_formats import ACCEPTED as _ACCEPTED
from .volume_formats import (
    RAS_TO_LPS,
    detached_data_file,
    detect_itk_format,
    nifti_arrays,
    nrrd_arrays,
    read_itk_volume,
)
from .volume_formats import check_affine as _check_affine
from .volume_formats import check_bytes as _check_bytes
from .volume_series import pick_volume_series
from .voxel_steps import bounding_box, components, filled_holes

__all__ = ["RAS_TO_LPS", "Volume", "read_volume", "read_volume_identities", "volume_to_mesh"]


@dataclass
class Volume:
    """Voxels ``data[i, j, k]`` (float32) and the voxel → world (LPS mm) ``affine``."""

    data: np.ndarray
    affine: np.ndarray
    kind: str
    warnings: list[str] = field(default_factory=list)
    tags: dict[str, str] = field(default_factory=dict)  # DICOM: what tells CTA / MRA / 3D-DSA apart
    dicom: tuple[DicomIdentity, ...] = ()  # DICOM: the instances, in the order given (for the DICOM outputs)
    dicom_unreadable: bool = False  # a DICOM instance whose identity attributes could not be converted

    @property
    def spacing_mm(self) -> tuple[float, float, float]:
        return tuple(float(x) for x in np.linalg.norm(self.affine[:3, :3], axis=0))


# ---- detection ------------------------------------------------------------------------


def detect_volume_format(data: bytes) -> str | None:
    head = data[:1024]
    if head[:2] == b"\x1f\x8b":
        try:
            head = gzip.GzipFile(fileobj=io.BytesIO(data)).read(544)
        except (OSError, EOFError, zlib.error):
            return None
    if head[:4] == b"NRRD":
        return "nrrd"
    if len(head) >= 348 and (head[344:348] in (b"n+1\x00", b"ni1\x00")):
        return "nifti"
    if len(head) >= 540 and head[4:8] in (b"n+2\x00", b"ni2\x00"):
        return "nifti"
    if head[128:132] == b"DICM":
        return "dicom"
    itk = detect_itk_format(data[:4096])
    if itk is not None:
        return itk
    if rad_format.looks_like_rad(head):
        return "rad"
    return None


def read_volume(
    data: bytes | Sequence[bytes],
    name: str | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
    *,
    field_name: str = "volume",
) -> Volume:
    """Read any accepted volume: one file's bytes, or a list (DICOM series; ``.rad`` + ``.raw`` pair) or
    :class:`.file_parts.FileParts` of them (read here, and let go when this returns)."""
    if isinstance(data, PART_LISTS):
        if len(data) > 2:  # a DICOM series: its files read one by one (:func:`read_dicom_series`)
            return read_dicom_series(data, limits, field_name=field_name)
        parts = [bytes(part) for part in data]
        if not parts or not any(parts):
            raise DsaregInputError("no files were given", field=field_name, accepted=_ACCEPTED)
        if len(parts) == 1:
            return read_volume(parts[0], name, limits, field_name=field_name)
        detached = [p for p in parts if _detached_format(p) is not None]
        if len(parts) == 2 and len(detached) == 1:  # .mhd / .nhdr + its data file, in either order
            header = detached[0]
            return _itk_volume(header, parts[1] if parts[0] is header else parts[0], _detached_format(header),
                               limits, field_name)
        rad_parts = [p for p in parts if rad_format.looks_like_rad(p[:4096])]
        if len(parts) == 2 and len(rad_parts) == 1:
            header = rad_parts[0]
            raw = parts[1] if parts[0] is header else parts[0]
            return read_rad_volume(header, raw, limits, field_name=field_name)
        return read_dicom_series(parts, limits, field_name=field_name)
    if not data:
        raise DsaregInputError("the file is empty", field=field_name, accepted=_ACCEPTED)
    fmt = detect_volume_format(data)
    if fmt is None and name:
        lowered = name.lower()
        if lowered.endswith((".dcm", ".dicom", ".ima")):
            fmt = "dicom"
    if fmt == "nifti":
        return read_nifti(data, limits, field_name=field_name)
    if fmt in ("metaimage", "vtk-image") or _detached_format(data) is not None:
        return _itk_volume(data, None, fmt, limits, field_name)
    if fmt == "nrrd":
        return read_nrrd(data, limits, field_name=field_name)
    if fmt == "dicom":
        return read_dicom_series([data], limits, field_name=field_name)
    if fmt == "rad":
        raise DsaregInputError("a .rad header needs its .raw file too (send both)", field=field_name)
    raise DsaregInputError("content is not a recognised volume format", field=field_name, accepted=_ACCEPTED)


def read_volume_identities(data: bytes | Sequence[bytes], name: str | None = None, *,
                           field_name: str = "volume") -> tuple[tuple[DicomIdentity, ...], bool]:
    """The DICOM identities of a volume's files and whether one was unreadable, as :func:`read_volume` gives them
    (``Volume.dicom``, ``Volume.dicom_unreadable``), from the headers alone: no pixel decoded (a model cache hit,
    :mod:`.model_cache`). ``((), False)`` for a volume that is not DICOM."""
    series = isinstance(data, PART_LISTS) and len(data) > 2  # its headers read one file at a time
    parts = data if series else volume_parts(data)
    if len(parts) == 1:
        fmt = detect_volume_format(parts[0]) or ("dicom" if (name or "").lower().endswith((".dcm", ".dicom", ".ima"))
                                                 else None)
        if fmt != "dicom":
            return (), False
    elif len(parts) == 2 and any(_detached_format(p) or rad_format.looks_like_rad(p[:4096]) for p in parts):
        return (), False
    headers = series_headers(parts, field_name)
    if len(parts) > 1:
        headers = [headers[i] for i in pick_volume_series(headers, field_name=field_name)[0]]
    identities = [identity_or_none(header) for header in headers]
    return (tuple(identity for identity, _ in identities if identity is not None),
            any(unreadable for _, unreadable in identities))


def _detached_format(data: bytes) -> str | None:
    """``"metaimage"`` / ``"nrrd"`` when ``data`` is a detached header (``.mhd``, ``.nhdr``) naming a data file."""
    fmt = detect_volume_format(data[:4096]) if data[:2] != b"\x1f\x8b" else None
    return fmt if fmt in ("metaimage", "nrrd") and detached_data_file(data, fmt) is not None else None


def _itk_volume(header: bytes, data: bytes | None, fmt: str, limits: InputLimits, field_name: str) -> Volume:
    voxels, affine, warnings = read_itk_volume(header, data, fmt, limits, field_name=field_name)
    return Volume(voxels, affine, fmt, warnings)


# ---- NIfTI, NRRD (:mod:`.volume_formats`) -------------------------------------------------


def read_nifti(data: bytes, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "volume") -> Volume:
    voxels, affine, warnings = nifti_arrays(data, limits, field_name=field_name)
    return Volume(voxels, affine, "nifti", warnings)


def read_nrrd(data: bytes, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "volume") -> Volume:
    if _detached_format(data) is not None:  # a .nhdr alone: says it needs its data file
        return _itk_volume(data, None, "nrrd", limits, field_name)
    voxels, affine, warnings = nrrd_arrays(data, limits, field_name=field_name)
    return Volume(voxels, affine, "nrrd", warnings)


# ---- DICOM ------------------------------------------------------------------------------


def _dicom_pixels(parsed: tuple, field_name: str) -> np.ndarray:
    """The rescaled pixels of a :func:`.dicom_identity.parse_dicom` result (decoded here, from that parse)."""
    dataset, failure = parsed
    try:
        if failure is not None:
            raise ValueError(failure)
        if "PixelData" not in dataset:
            raise DsaregInputError("DICOM file has no pixel data", field=field_name)
        pixels = dataset.pixel_array.astype(np.float32)
        del dataset.PixelData  # the parse stays for the identity; its pixel bytes and decoded cache go
    except DsaregInputError:
        raise
    except Exception as exc:
        raise DsaregInputError(f"DICOM pixel data is unreadable ({str(exc)[:200]})", field=field_name) from None
    slope = dicom_number(dataset, "RescaleSlope", 1.0, field_name, kind=float)
    intercept = dicom_number(dataset, "RescaleIntercept", 0.0, field_name, kind=float)
    if slope != 1.0:  # in place: the same float32 values as ``pixels * slope + intercept``, no temporaries
        pixels *= slope
    if intercept != 0.0:
        pixels += intercept
    return pixels


def _nested(dataset, keyword: str, frame: int | None = None):
    """A tag from the top level, the shared or the per-frame functional groups."""
    if keyword in dataset:
        return dataset.data_element(keyword).value
    groups = []
    if frame is not None and "PerFrameFunctionalGroupsSequence" in dataset:
        per_frame = dataset.PerFrameFunctionalGroupsSequence
        if frame < len(per_frame):
            groups.append(per_frame[frame])
    if "SharedFunctionalGroupsSequence" in dataset and len(dataset.SharedFunctionalGroupsSequence):
        groups.append(dataset.SharedFunctionalGroupsSequence[0])
    for group in groups:
        for element in group:
            if element.VR == "SQ":
                for item in element.value:
                    if keyword in item:
                        return item.data_element(keyword).value
    return None


def _frame_geometry(dataset, frame: int | None, field_name: str):
    position = _nested(dataset, "ImagePositionPatient", frame)
    orientation = _nested(dataset, "ImageOrientationPatient", frame)
    spacing = _nested(dataset, "PixelSpacing", frame)
    if position is None or orientation is None or spacing is None:
        missing = [
            n
            for n, v in (
                ("ImagePositionPatient", position),
                ("ImageOrientationPatient", orientation),
                ("PixelSpacing", spacing),
            )
            if v is None
        ]
        raise DsaregInputError(f"DICOM slice lacks {missing}; cannot place it in space", field=field_name)
    try:
        position = np.array([float(x) for x in position])
        orientation = np.array([float(x) for x in orientation])
        spacing = np.array([float(x) for x in spacing])
    except (TypeError, ValueError):
        raise DsaregInputError("DICOM geometry tags are not numeric", field=field_name) from None
    if position.shape != (3,) or orientation.shape != (6,) or spacing.shape != (2,) or np.any(spacing <= 0):
        raise DsaregInputError("DICOM geometry tags have the wrong length or sign", field=field_name)
    return position, orientation[:3], orientation[3:], spacing


def _series_affine(positions: np.ndarray, row_dir, col_dir, spacing, field_name: str) -> np.ndarray:
    """Voxel (i = column, j = row, k = slice) → LPS mm."""
    normal = np.cross(row_dir, col_dir)
    affine = np.eye(4)
    affine[:3, 0] = np.asarray(row_dir) * spacing[1]  # along a row: column index i, column spacing
    affine[:3, 1] = np.asarray(col_dir) * spacing[0]  # down a column: row index j, row spacing
    if len(positions) > 1:
        step = (positions[-1] - positions[0]) / (len(positions) - 1)
        gaps = np.diff(positions @ normal)
        if np.any(gaps <= 1e-6):
            raise DsaregInputError("DICOM series has duplicate slice positions", field=field_name)
        if gaps.max() - gaps.min() > 0.01 * abs(gaps.mean()) + 1e-3:
            raise DsaregInputError("DICOM slices are not evenly spaced (missing slices?)", field=field_name)
        affine[:3, 2] = step
    else:
        affine[:3, 2] = normal
    affine[:3, 3] = positions[0]
    return _check_affine(affine, field_name)


def read_dicom_series(
    parts: Sequence[bytes], limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "volume"
) -> Volume:
    """A volume from the files of one DICOM series (or one enhanced multi-frame file).

    A series' headers are read first, then its pixels file by file: ``parts`` may be a
    :class:`.file_parts.FileParts`, whose files are then never all in memory at once (a whole head's are 0.23 GB).
    """
    if len(parts) == 1:
        return _enhanced_volume(bytes(parts[0]), limits, field_name)
    headers = series_headers(parts, field_name)
    chosen, series_warnings = pick_volume_series(headers, field_name=field_name)
    if len(chosen) == 1:  # one enhanced multi-frame file beside other series (the XA runs, a scout)
        return _enhanced_volume(bytes(parts[chosen[0]]), limits, field_name, series_warnings)
    headers = [headers[i] for i in chosen]
    first = headers[0]
    rows, cols = _image_size(first, field_name)
    modality = str(getattr(first, "Modality", "") or "")  # a header probe's: the reading's kind (:mod:`.volume_cost`)
    _check_bytes((cols, rows, len(headers)), max(4, _bits(first) // 8), limits, field_name, modality)
    for header in headers[1:]:
        if (int(getattr(header, "Rows", 0) or 0), int(getattr(header, "Columns", 0) or 0)) != (rows, cols):
            raise DsaregInputError("DICOM slices differ in size", field=field_name)
    geometry = [_frame_geometry(header, None, field_name) for header in headers]
    positions, order = _slice_order(geometry, field_name)
    stored = np.empty((len(order), rows, cols), np.float32)  # slice by slice, each one contiguous
    for k, index in enumerate(order):  # each file read again (a FileParts) and decoded into its slice
        _store_slice(stored, k, _dicom_pixels(parse_dicom(parts[chosen[index]], field_name), field_name), field_name)
    return _series_volume(stored, positions, geometry[0], "dicom-series", headers, series_warnings, field_name)


def _enhanced_volume(data: bytes, limits: InputLimits, field_name: str, warnings: list[str] | None = None) -> Volume:
    """An enhanced multi-frame DICOM volume (one file holding every slice with its per-frame position)."""
    parsed = parse_dicom(data, field_name)
    first = parsed[0]
    rows, cols = _image_size(first, field_name)
    n_frames = int(getattr(first, "NumberOfFrames", 1) or 1)
    if n_frames < 2:
        raise DsaregInputError(
            "a single-slice DICOM is not a volume",
            field=field_name,
            accepted="all files of a DICOM series, or an enhanced multi-frame file",
        )
    modality = str(getattr(first, "Modality", "") or "")
    _check_bytes((cols, rows, n_frames), max(4, _bits(first) // 8), limits, field_name, modality)
    if "PerFrameFunctionalGroupsSequence" not in first:
        raise DsaregInputError("multi-frame DICOM lacks per-frame positions (not a volume)", field=field_name)
    geometry = [_frame_geometry(first, f, field_name) for f in range(n_frames)]
    pixels = _dicom_pixels(parsed, field_name)
    if pixels.ndim != 3 or pixels.shape[0] != n_frames:
        raise DsaregInputError("multi-frame pixel data does not match NumberOfFrames", field=field_name)
    positions, order = _slice_order(geometry, field_name)
    stored = np.empty((len(order), rows, cols), np.float32)
    for k, index in enumerate(order):
        _store_slice(stored, k, pixels[index], field_name)
    return _series_volume(stored, positions, geometry[0], "dicom-enhanced", [first], list(warnings or []), field_name)


def _image_size(header, field_name: str) -> tuple[int, int]:
    rows, cols = int(getattr(header, "Rows", 0) or 0), int(getattr(header, "Columns", 0) or 0)
    if rows < 1 or cols < 1:
        raise DsaregInputError("DICOM file has no Rows/Columns (not an image)", field=field_name)
    return rows, cols


def _bits(header) -> int:
    return int(getattr(header, "BitsAllocated", 16) or 16)


def _slice_order(geometry: list, field_name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(positions in slice order, order)``: the slices sorted along their normal (one orientation for all)."""
    row_dir, col_dir = geometry[0][1], geometry[0][2]
    for _, other_row, other_col, _ in geometry[1:]:
        if np.abs(other_row - row_dir).max() > 1e-3 or np.abs(other_col - col_dir).max() > 1e-3:
            raise DsaregInputError("DICOM slices have different orientations", field=field_name)
    positions = np.array([g[0] for g in geometry])
    order = np.argsort(positions @ np.cross(row_dir, col_dir))
    return positions[order], order


def _store_slice(stored: np.ndarray, k: int, pixels: np.ndarray, field_name: str) -> None:
    if pixels.shape != stored.shape[1:]:
        raise DsaregInputError("a DICOM slice has pixel data of the wrong size", field=field_name)
    stored[k] = pixels


def _series_volume(stored: np.ndarray, positions: np.ndarray, first_geometry: tuple, kind: str, headers: list,
                   warnings: list[str], field_name: str) -> Volume:
    """The volume of slices ``stored`` [k, row, col] at ``positions``, with the headers' DICOM identities."""
    _, row_dir, col_dir, spacing = first_geometry
    voxels = stored.transpose(2, 1, 0)  # [i=col, j=row, k], a view (Fortran order, as NIfTI volumes come)
    affine = _series_affine(positions, row_dir, col_dir, spacing, field_name)
    identities = [identity_or_none(header) for header in headers]
    return Volume(voxels, affine, kind, warnings=warnings, tags=_identity_tags(headers[0]),
                  dicom=tuple(identity for identity, _ in identities if identity is not None),
                  dicom_unreadable=any(unreadable for _, unreadable in identities))


IDENTITY_TAGS = ("Modality", "SOPClassUID", "ImageType", "SeriesDescription", "ContrastBolusAgent", "AngioFlag",
                 "SequenceName", "ScanningSequence", "RescaleType")
"""The tags :mod:`dsareg_engine.io.volume_kind` reads to tell the kind of a volume."""


def _identity_tags(dataset) -> dict[str, str]:
    tags = {}
    for keyword in IDENTITY_TAGS:
        value = _nested(dataset, keyword, 0)
        if value is None or value == "":
            continue
        is_list = isinstance(value, Sequence) and not isinstance(value, (str, bytes))
        text = "\\".join(str(v) for v in value) if is_list else str(value)
        tags[keyword] = text[:200]
    return tags


# ---- .rad + .raw ---------------------------------------------------------------------------


def read_rad_volume(
    header_bytes: bytes, raw: bytes, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "volume"
) -> Volume:
    header = rad_format.parse_rad_header(header_bytes, field_name=f"{field_name}.rad")
    if header.ndim != 3:
        raise DsaregInputError("the .rad header describes a 2D image, not a volume", field=field_name)
    _check_bytes(header.size, header.dtype.itemsize, limits, field_name)
    voxels = rad_format.read_raw(header, raw, max_bytes=limits.max_volume_bytes, field_name=f"{field_name}.raw")
    affine = rad_format.volume_affine_from_rad(header, field_name=f"{field_name}.rad")
    return Volume(voxels, affine, "rad")


# ---- surface extraction --------------------------------------------------------------------


def volume_to_mesh(
    volume: np.ndarray | Volume,
    affine_vox_to_world: np.ndarray | None = None,
    *,
    smoothing_sigma_vox: float = 0.5,
    min_component_fraction: float = 0.05,
    max_components: int = 8,
    field_name: str = "volume",
) -> TriangleMesh:
    """Vessel surface of a contrast-enhanced volume, in world mm.

    Otsu threshold of the lightly smoothed (Gaussian, ``smoothing_sigma_vox``) volume;
    the connected components bigger than ``min_component_fraction`` of the largest
    (at most ``max_components``) are kept; marching cubes at the threshold level
    gives a sub-voxel surface (enclosed cavities filled), mapped to world mm through the affine (faces re-oriented
    when the affine mirrors, so normals point outward).

    Raises:
        DsaregInputError: constant volume or nothing above the threshold.
    """
    from scipy import ndimage
    from skimage.filters import threshold_otsu

    if isinstance(volume, Volume):
        affine_vox_to_world = volume.affine if affine_vox_to_world is None else affine_vox_to_world
        volume = volume.data
    affine = _check_affine(np.eye(4) if affine_vox_to_world is None else affine_vox_to_world, field_name)
    voxels = np.asarray(volume, dtype=np.float32)
    if voxels.ndim != 3 or min(voxels.shape) < 2:
        raise DsaregInputError(f"needs a 3D volume, got shape {list(voxels.shape)}", field=field_name)
    if not np.all(np.isfinite(voxels)):
        voxels = np.nan_to_num(
            voxels, nan=float(np.nanmin(voxels)) if np.isfinite(voxels).any() else 0.0, posinf=0.0, neginf=0.0
        )
    if float(voxels.max()) - float(voxels.min()) <= 0:
        raise DsaregInputError(
            "is constant: nothing above the threshold",
            field=field_name,
            accepted="a contrast-enhanced volume (vessels brighter than background)",
        )
    smooth = ndimage.gaussian_filter(voxels, smoothing_sigma_vox) if smoothing_sigma_vox > 0 else voxels
    level = float(threshold_otsu(smooth))
    mask = largest_components(smooth > level, min_component_fraction, max_components, field_name=field_name)
    return surface_from_mask(smooth, mask, level, affine, field_name=field_name)


def largest_components(inside: np.ndarray, min_component_fraction: float = 0.05, max_components: int = 8, *,
                       field_name: str = "volume") -> np.ndarray:
    """The connected components of ``inside`` (6-connected) bigger than ``min_component_fraction`` of the
    largest, at most ``max_components`` of them."""
    box = bounding_box(inside)
    found = components(inside[box]) if box is not None else None
    if found is None or found.count == 0:
        raise DsaregInputError("nothing lies above the threshold", field=field_name)
    sizes = found.sizes()[1:]  # (0: the background)
    ranked = np.argsort(sizes)[::-1][:max_components]
    kept = [int(r) + 1 for r in ranked if sizes[r] >= min_component_fraction * sizes.max()]
    chosen = np.zeros(found.count + 1, bool)
    chosen[kept] = True
    mask = np.zeros(inside.shape, bool)
    found.write(mask[box], chosen)
    del found  # (its label grid, where there is one)
    if np.count_nonzero(mask) < 8:
        raise DsaregInputError("only a few isolated voxels lie above the threshold", field=field_name)
    return mask


def surface_from_mask(smooth: np.ndarray, mask: np.ndarray, level: float, affine: np.ndarray, *,
                      field_name: str = "volume") -> TriangleMesh:
    """Marching cubes of ``smooth`` at ``level`` around the kept voxels ``mask`` (elsewhere: the field's floor),
    enclosed cavities filled; vertices mapped through ``affine`` to world mm, normals outward. The field is built
    in the mask's box; the whole padded grid is marched (the vertices' float32 indices are the whole grid's)."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    floor = float(smooth.min())
    box = bounding_box(mask, margin=3) or tuple(slice(0, n) for n in mask.shape)  # the floor beyond 2 voxels
    padded = tuple(slice(b.start + 1, b.stop + 1) for b in box)
    field = np.full([n + 2 for n in mask.shape], floor, np.result_type(smooth, floor))  # padded by one voxel
    field[padded] = np.where(ndimage.binary_dilation(mask[box], iterations=2), smooth[box], floor)
    cavities = filled_holes(mask[box]) & ~mask[box]  # a vessel lumen has no enclosed voids
    field[padded][cavities] = max(float(smooth.max()), level + 1.0)
    vertices, faces, _, _ = marching_cubes(field, level=level, allow_degenerate=False)
    if len(faces) == 0:
        raise DsaregInputError("nothing lies above the threshold", field=field_name)
    vertices = vertices - 1.0  # undo the padding
    world = vertices @ affine[:3, :3].T + affine[:3, 3]
    faces = faces.astype(np.int64)
    if np.linalg.det(affine[:3, :3]) < 0:
        faces = faces[:, ::-1]
    # marching_cubes orients faces toward increasing values' complement; make normals point outward.
    faces = _orient_outward(world, faces)
    return TriangleMesh(np.ascontiguousarray(world, dtype=np.float64), np.ascontiguousarray(faces))


def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    triangles = vertices[faces]
    signed_volume = np.einsum("ij,ij->i", triangles[:, 0], np.cross(triangles[:, 1], triangles[:, 2])).sum()
    return faces[:, ::-1] if signed_volume < 0 else faces
