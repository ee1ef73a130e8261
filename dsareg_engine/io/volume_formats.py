"""Volume file formats, as voxels and a voxel → LPS mm affine (:mod:`.volume_io` makes them a ``Volume``).

NIfTI (nibabel) and NRRD with attached data (pynrrd) are read from memory. ITK's formats are read by SimpleITK:
MetaImage (``.mha``; ``.mhd`` + its data file), detached NRRD (``.nhdr`` + its data file) and legacy VTK
``STRUCTURED_POINTS`` (``.vtk``).

ITK's physical space is patient LPS millimetres, the engine's world frame (:mod:`.volume_io`): the image's
direction × spacing and origin are its affine as they are (ITK's NRRD reader has already turned a
``right-anterior-superior`` space into LPS). A legacy VTK image has no patient space: its coordinates are taken
as LPS mm and a warning says so.

SimpleITK reads files, not bytes: the header and its data are written to a private temporary folder under names
chosen here. A detached header's data-file line is rewritten to that name, so a header can never reach another
file (``../``, an absolute path); multi-file data (``LIST``, a ``%d`` pattern) is refused. The header's
shape × sample size is checked against ``limits.max_volume_bytes`` (:func:`ReadImageInformation`, no voxel read)
before any voxel is decoded; compressed data decodes into that declared buffer, never beyond it.
"""

from __future__ import annotations

import gzip
import io
import locale
import re
import tempfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import DsaregInputError
from .limits import DEFAULT_LIMITS, DeclaredShape, InputLimits, ShapeProbe

RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
ITK_FORMATS = ("metaimage", "vtk-image")
_META_KEY = re.compile(rb"(?m)^[ \t]*(NDims|ObjectType|DimSize|ElementType)[ \t]*=")
_META_DATA_FILE = re.compile(rb"(?m)^([ \t]*ElementDataFile[ \t]*=[ \t]*)([^\r\n]*)")
_NRRD_DATA_FILE = re.compile(rb"(?m)^(data ?file:[ \t]*)([^\r\n]*)")
_SUFFIX = {"metaimage": ".mha", "vtk-image": ".vtk", "nrrd": ".nrrd"}
_DETACHED_SUFFIX = {"metaimage": ".mhd", "nrrd": ".nhdr"}
ACCEPTED = ("MetaImage (.mha, or .mhd with its data file), NRRD (.nrrd, or .nhdr with its data file), "
            "NIfTI (.nii/.nii.gz), legacy VTK structured points (.vtk), a DICOM series, enhanced multi-frame DICOM, "
            "or .rad + .raw")


@contextmanager
def kept_locale() -> Iterator[None]:
    """The process's locale as it was before the block: ITK's VTK image reader sets it to "C" for its numbers and
    leaves it so (every later ``open()`` without an encoding would then read ASCII)."""
    saved = locale.setlocale(locale.LC_ALL, None)
    try:
        yield
    finally:
        if locale.setlocale(locale.LC_ALL, None) != saved:
            locale.setlocale(locale.LC_ALL, saved)


def detect_itk_format(head: bytes) -> str | None:
    """``"metaimage"`` (a MetaImage header, attached or detached) or ``"vtk-image"`` (legacy VTK STRUCTURED_POINTS)."""
    head = head[:4096]
    if len(_META_KEY.findall(head)) >= 2 and b"ElementDataFile" in head:
        return "metaimage"
    if head.lstrip()[:22] == b"# vtk DataFile Version" and re.search(rb"(?m)^\s*DATASET\s+STRUCTURED_POINTS", head):
        return "vtk-image"
    return None


def detached_data_file(header: bytes, fmt: str) -> str | None:
    """The data file a detached header names (``.mhd``'s ``ElementDataFile``, ``.nhdr``'s ``data file``), or None
    when the data is in the same file (``LOCAL``; NRRD without the line)."""
    pattern = {"metaimage": _META_DATA_FILE, "nrrd": _NRRD_DATA_FILE}.get(fmt)
    text = header[:65536]
    if fmt == "nrrd":  # the header ends at its first blank line (attached data follows)
        text = re.split(rb"\r?\n\r?\n", text, maxsplit=1)[0]
    found = pattern.search(text) if pattern is not None else None
    if found is None:
        return None
    value = found.group(2).strip().decode("utf-8", "replace")
    return None if value.upper() == "LOCAL" else value


def _refuse_split_data(value: str, field_name: str) -> None:
    """Refuse a data-file line naming several files (``LIST``, a ``%d`` pattern), or none."""
    if not value or value.upper().startswith("LIST") or "%" in value:  # a name may hold spaces; a pattern has a %
        raise DsaregInputError(f"the header's data is split over several files ('{value[:80]}')", field=field_name,
                               accepted="a header with one data file")


def _named_data(header: bytes, fmt: str, field_name: str) -> bytes:
    """``header`` with its data-file line naming ``volume.data`` (the file written beside it)."""
    value = detached_data_file(header, fmt) or ""
    _refuse_split_data(value, field_name)
    pattern = {"metaimage": _META_DATA_FILE, "nrrd": _NRRD_DATA_FILE}[fmt]
    return pattern.sub(lambda m: m.group(1) + b"volume.data", header[:65536], count=1) + header[65536:]


def check_bytes(shape, itemsize: int, limits: InputLimits, field_name: str, modality: str = "") -> None:
    """Refuse a declared shape × sample size above ``limits.max_volume_bytes`` (before any voxel is decoded);
    ``modality``: a DICOM series' Modality, carried by a header probe's :class:`.limits.DeclaredShape`."""
    shape = [int(s) for s in shape]
    if any(s < 1 for s in shape):
        raise DsaregInputError(f"declares an empty shape {shape}", field=field_name)
    total = int(np.prod(shape, dtype=np.int64)) * int(itemsize)
    if total > limits.max_volume_bytes:
        raise DsaregInputError(
            f"declares {'x'.join(map(str, shape))} samples of {itemsize} bytes ({total / 2**20:.0f} MiB), "
            f"above the limit of {limits.max_volume_bytes / 2**20:.0f} MiB",
            field=field_name,
        )
    if isinstance(limits, ShapeProbe):  # the header alone was asked for: stop before any voxel is decoded
        raise DeclaredShape(tuple(shape), int(itemsize), modality)


def check_affine(affine: np.ndarray, field_name: str) -> np.ndarray:
    """``affine`` as a float 4 × 4 voxel → world matrix, refused when singular or not finite."""
    affine = np.asarray(affine, dtype=np.float64)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DsaregInputError("has a singular or non-finite voxel-to-world matrix", field=field_name)
    return affine


def read_itk_volume(header: bytes, data: bytes | None, fmt: str, limits: InputLimits = DEFAULT_LIMITS, *,
                    field_name: str = "volume") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(voxels [i, j, k] float32, affine voxel → LPS mm, warnings)`` of an ITK-format file (``data`` None) or of
    a detached header and its data (:func:`.volume_io.read_volume` makes them a ``Volume``).

    Raises:
        DsaregInputError: a header without its data file, unreadable or truncated data, not 3D, vector pixels,
            a declared size above ``limits.max_volume_bytes``.
    """
    import SimpleITK as sitk

    detached = detached_data_file(header, fmt)
    if detached is not None:
        _refuse_split_data(detached, field_name)  # before asking for "its data file" (a list names several)
    if detached is not None and data is None:
        raise DsaregInputError(f"a detached {_DETACHED_SUFFIX[fmt]} header needs its data file '{detached[:80]}' too "
                               "(send both)", field=field_name, accepted=ACCEPTED)
    if detached is None and data is not None:
        raise DsaregInputError("the header holds its own data; the second file is not needed", field=field_name)
    with tempfile.TemporaryDirectory(prefix="dsareg-volume-") as folder:
        path = Path(folder) / ("volume" + (_DETACHED_SUFFIX[fmt] if detached else _SUFFIX[fmt]))
        path.write_bytes(_named_data(header, fmt, field_name) if detached else header)
        if detached:
            (Path(folder) / "volume.data").write_bytes(data)
        reader = sitk.ImageFileReader()
        reader.SetFileName(str(path))
        try:
            with kept_locale():
                reader.ReadImageInformation()
        except RuntimeError as exc:
            raise DsaregInputError(f"{_name(fmt)} header is unreadable ({_itk_message(exc)})", field=field_name,
                                   accepted=ACCEPTED) from None
        _check_information(reader, limits, field_name)
        try:
            with kept_locale():
                image = reader.Execute()
        except RuntimeError as exc:
            raise DsaregInputError(f"{_name(fmt)} data is unreadable or truncated ({_itk_message(exc)})",
                                   field=field_name) from None
    return _arrays(image, fmt, header, field_name)


def _name(fmt: str) -> str:
    return {"metaimage": "MetaImage", "vtk-image": "legacy VTK image", "nrrd": "NRRD"}[fmt]


def _itk_message(exc: Exception) -> str:
    """The last meaningful line of an ITK exception (its first lines name C++ source files)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return (lines[-1] if lines else type(exc).__name__)[:200]


def _check_information(reader, limits: InputLimits, field_name: str) -> None:
    size = list(reader.GetSize())
    if reader.GetDimension() != 3 and not (reader.GetDimension() == 4 and size[3] == 1):
        raise DsaregInputError(f"has size {size}; a 3D volume is needed", field=field_name)
    if reader.GetNumberOfComponents() != 1:
        raise DsaregInputError(f"has {reader.GetNumberOfComponents()} values per voxel; one (a scalar volume) is "
                               "needed", field=field_name)
    import SimpleITK as sitk

    bits = re.search(r"(\d+)-bit", sitk.GetPixelIDValueAsString(reader.GetPixelID()))
    check_bytes(size[:3], int(bits.group(1)) // 8 if bits else 8, limits, field_name)


def _arrays(image, fmt: str, header: bytes, field_name: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    import SimpleITK as sitk

    if image.GetDimension() == 4:
        image = image[:, :, :, 0]
    voxels = np.ascontiguousarray(sitk.GetArrayViewFromImage(image).transpose(2, 1, 0), dtype=np.float32)
    affine = np.eye(4)
    affine[:3, :3] = np.asarray(image.GetDirection(), float).reshape(3, 3) @ np.diag(image.GetSpacing())
    affine[:3, 3] = image.GetOrigin()
    warnings = []
    if fmt == "vtk-image":
        warnings.append(f"{field_name}: a legacy VTK image has no patient space; its coordinates are used as LPS mm")
    elif fmt == "nrrd" and not re.search(rb"(?m)^space:", header[:65536]):
        warnings.append(f"{field_name}: NRRD has no patient space; its coordinates are used as LPS mm")
    return voxels, check_affine(affine, field_name), warnings


# ---- NIfTI and attached NRRD (nibabel, pynrrd: in memory) -----------------------------------


def _gunzip_limited(data: bytes, max_bytes: int, field_name: str) -> bytes:
    decompressor = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = decompressor.decompress(data, max_bytes + 1)
    except zlib.error as exc:
        raise DsaregInputError(f"gzip data is corrupt ({exc})", field=field_name) from None
    if len(out) > max_bytes:
        raise DsaregInputError("decompresses beyond the volume size limit", field=field_name)
    if not decompressor.eof:
        raise DsaregInputError("gzip data is truncated", field=field_name)
    return out


def nifti_arrays(data: bytes, limits: InputLimits = DEFAULT_LIMITS, *,
                 field_name: str = "volume") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(voxels, affine voxel → LPS mm, warnings)`` of a NIfTI-1/2 file (gzipped or not); RAS turned to LPS."""
    import nibabel as nib

    head = data
    compressed = data[:2] == b"\x1f\x8b"
    if compressed:
        try:
            head = gzip.GzipFile(fileobj=io.BytesIO(data)).read(544)
        except (OSError, EOFError, zlib.error) as exc:
            raise DsaregInputError(f"gzip data is corrupt ({exc})", field=field_name) from None
    version2 = len(head) >= 8 and head[4:8] in (b"n+2\x00", b"ni2\x00")
    header_class, image_class = (nib.Nifti2Header, nib.Nifti2Image) if version2 else (nib.Nifti1Header, nib.Nifti1Image)
    try:
        header = header_class.from_fileobj(io.BytesIO(head[:540] if version2 else head[:348]))
        shape = header.get_data_shape()
        itemsize = header.get_data_dtype().itemsize
    except Exception as exc:
        raise DsaregInputError(f"NIfTI header is unreadable ({str(exc)[:200]})", field=field_name) from None
    if len(shape) < 3 or any(s != 1 for s in shape[3:]):
        raise DsaregInputError(f"has shape {list(shape)}; a 3D volume is needed", field=field_name)
    check_bytes(shape[:3], itemsize, limits, field_name)
    raw = _gunzip_limited(data, limits.max_volume_bytes + 65536, field_name) if compressed else data
    try:
        image = image_class.from_bytes(raw)
        voxels = np.asarray(image.dataobj, dtype=np.float32)
    except Exception as exc:
        raise DsaregInputError(f"NIfTI data is unreadable or truncated ({str(exc)[:200]})", field=field_name) from None
    voxels = voxels.reshape(voxels.shape[:3])
    return voxels, check_affine(RAS_TO_LPS @ image.affine, field_name), []


# ---- NRRD -------------------------------------------------------------------------------

_NRRD_SPACES = {
    "left-posterior-superior": np.eye(4),
    "lps": np.eye(4),
    "right-anterior-superior": RAS_TO_LPS,
    "ras": RAS_TO_LPS,
}


def nrrd_arrays(data: bytes, limits: InputLimits = DEFAULT_LIMITS, *,
                field_name: str = "volume") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(voxels, affine voxel → LPS mm, warnings)`` of a NRRD with attached data (its space turned to LPS)."""
    import nrrd

    stream = io.BytesIO(data)
    try:
        header = nrrd.read_header(stream)
    except Exception as exc:
        raise DsaregInputError(f"NRRD header is unreadable ({str(exc)[:200]})", field=field_name) from None
    if "data file" in header or "datafile" in header:
        raise DsaregInputError("a detached NRRD header needs its data file too (send both)", field=field_name)
    sizes = [int(s) for s in np.atleast_1d(header.get("sizes", []))]
    if int(header.get("dimension", len(sizes))) != 3 or len(sizes) != 3:
        raise DsaregInputError(f"has sizes {sizes}; a 3D volume is needed", field=field_name)
    try:
        itemsize = nrrd.reader._determine_datatype(header).itemsize
    except Exception as exc:
        raise DsaregInputError(f"NRRD type is unsupported ({str(exc)[:100]})", field=field_name) from None
    check_bytes(sizes, itemsize, limits, field_name)
    try:
        voxels = nrrd.read_data(header, stream, index_order="F")
    except Exception as exc:
        raise DsaregInputError(f"NRRD data is unreadable or truncated ({str(exc)[:200]})", field=field_name) from None
    if voxels.size != int(np.prod(sizes)):
        raise DsaregInputError("NRRD data is truncated", field=field_name)
    directions = header.get("space directions")
    affine = np.eye(4)
    if directions is not None:
        directions = np.asarray(directions, dtype=np.float64)
        affine[:3, :3] = directions.T
    elif "spacings" in header:
        affine[:3, :3] = np.diag(np.asarray(header["spacings"], dtype=np.float64))
    if "space origin" in header:
        affine[:3, 3] = np.asarray(header["space origin"], dtype=np.float64)
    space = str(header.get("space", "")).lower()
    warnings = []
    if space in _NRRD_SPACES:
        affine = _NRRD_SPACES[space] @ affine
    else:
        warnings.append(f"{field_name}: NRRD has no patient space; its coordinates are used as LPS mm")
    return np.asarray(voxels, dtype=np.float32), check_affine(affine, field_name), warnings


__all__ = ["ACCEPTED", "ITK_FORMATS", "RAS_TO_LPS", "check_affine", "check_bytes", "detached_data_file",
           "detect_itk_format", "kept_locale", "nifti_arrays", "nrrd_arrays", "read_itk_volume"]
