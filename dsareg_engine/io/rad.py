"""The ``.rad`` text header of the 3D-2D-GS-CA data set (paired with a ``.raw`` file).

A header is a list of ``Key: value`` lines, for example::

    Size[pixels]: 1024 1024
    Step[mm]: 0.3 0.3
    DataType: float
    SourcePosition[mm]: 12.5 -800.0 3.1
    TPosition:
    1 0 0 -153.6
    0 1 0 -153.6
    0 0 1 400.0
    0 0 0 1

For a 2D image, ``TPosition`` maps detector mm (pixel (col i, row j) centred at
``(i·du, j·dv, 0)``, +z toward the source) to world mm; for a volume it maps volume mm
(voxel (i, j, k) at ``(i·sx, j·sy, k·sz)``) to world mm. The ``.raw`` file holds the
samples, little-endian, the first index (column / x) varying fastest.

The parser is tolerant: key case, the bracketed unit, ``:`` or ``=`` separators, CRLF,
a UTF-8 BOM, ``#`` comments, commas between numbers, and ``TPosition`` given either on
the following 4 (or 3) lines or as 16 (or 12) numbers on its own line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import ViewGeometry, view_from_detector_pose
from ..geometry.pose import validate_rigid

_DTYPES = {
    "float": "<f4",
    "float32": "<f4",
    "single": "<f4",
    "real": "<f4",
    "double": "<f8",
    "float64": "<f8",
    "uchar": "u1",
    "unsignedchar": "u1",
    "uint8": "u1",
    "byte": "u1",
    "char": "i1",
    "int8": "i1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "unsignedshort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "unsignedint": "<u4",
    "uint32": "<u4",
}
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_KEY = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_ ]*?)\s*(?:\[[^\]]*\])?\s*[:=]\s*(.*)$")


@dataclass(frozen=True)
class RadHeader:
    """What a ``.rad`` header says.

    Attributes:
        size: ``(cols, rows)`` for an image or ``(nx, ny, nz)`` for a volume.
        step_mm: spacing per axis, same length as ``size``.
        dtype: numpy dtype of the ``.raw`` samples.
        tposition: 4x4 detector/volume mm → world mm, or ``None`` when absent.
        source_position: source in world mm ``(3,)``, or ``None`` (volumes have none).
        extra: the other keys, lower-cased, as raw strings.
    """

    size: tuple[int, ...]
    step_mm: tuple[float, ...]
    dtype: np.dtype
    tposition: np.ndarray | None = field(default=None, repr=False)
    source_position: np.ndarray | None = None
    extra: dict = field(default_factory=dict, repr=False)

    @property
    def ndim(self) -> int:
        return len(self.size)

    @property
    def n_bytes(self) -> int:
        return int(np.prod(self.size, dtype=np.int64)) * self.dtype.itemsize


def looks_like_rad(data: bytes) -> bool:
    """True when ``data`` reads as a ``.rad`` header (text with a Size and a Step key)."""
    head = data[:4096]
    if b"\x00" in head:
        return False
    text = head.decode("latin-1").lower()
    return "size" in text and "step" in text and ("tposition" in text or "datatype" in text)


def _numbers(text: str) -> list[float]:
    return [float(x) for x in _NUMBER.findall(text)]


def parse_rad_header(data: bytes, *, field_name: str = "rad") -> RadHeader:
    """Parse a ``.rad`` header.

    Raises:
        DsaregInputError: not text, a required key missing (Size, Step), bad numbers.
    """
    if not data or not data.strip():
        raise DsaregInputError("the .rad header is empty", field=field_name)
    if b"\x00" in data[:65536]:
        raise DsaregInputError("is binary data, not a .rad text header", field=field_name)
    text = data.decode("utf-8", errors="replace").lstrip("\ufeff")
    lines = [line.split("#", 1)[0].strip() for line in text.replace("\r", "\n").split("\n")]
    lines = [line for line in lines if line]
    values: dict[str, str] = {}
    tposition = None
    index = 0
    while index < len(lines):
        match = _KEY.match(lines[index])
        index += 1
        if not match:
            continue
        key = match.group(1).replace(" ", "").lower()
        value = match.group(2).strip()
        if key == "tposition":
            numbers = _numbers(value)
            while len(numbers) < 12 and index < len(lines) and not _KEY.match(lines[index]):
                numbers.extend(_numbers(lines[index]))
                index += 1
            if len(numbers) == 12:
                numbers.extend([0.0, 0.0, 0.0, 1.0])
            if len(numbers) != 16:
                raise DsaregInputError(
                    f"TPosition has {len(numbers)} numbers",
                    field=f"{field_name}.TPosition",
                    accepted="a 4x4 matrix (16 numbers, row by row)",
                )
            tposition = np.array(numbers, dtype=np.float64).reshape(4, 4)
        else:
            values[key] = value
    size_text = values.pop("size", None)
    step_text = values.pop("step", None) or values.pop("spacing", None)
    if size_text is None or step_text is None:
        missing = [
            name for name, text_value in (("Size[pixels]", size_text), ("Step[mm]", step_text)) if text_value is None
        ]
        raise DsaregInputError(f"missing key(s) {missing}", field=field_name, accepted="a 3D-2D-GS-CA .rad header")
    size_values = _numbers(size_text)
    step = tuple(_numbers(step_text))
    if len(size_values) not in (2, 3) or any(v != int(v) or v < 1 for v in size_values):
        raise DsaregInputError(f"Size '{size_text}' is not 2 or 3 positive integers", field=f"{field_name}.Size")
    size = tuple(int(v) for v in size_values)
    if len(step) == 1:
        step = step * len(size)
    if len(step) != len(size) or not all(np.isfinite(step)) or min(step) <= 0:
        raise DsaregInputError(
            f"Step '{step_text}' must give {len(size)} positive spacings", field=f"{field_name}.Step"
        )
    type_text = values.pop("datatype", "float").replace(" ", "").replace("_", "").lower()
    if type_text not in _DTYPES:
        raise DsaregInputError(
            f"unsupported DataType '{type_text}'", field=f"{field_name}.DataType", accepted=", ".join(sorted(_DTYPES))
        )
    source = None
    source_text = values.pop("sourceposition", None)
    if source_text is not None:
        numbers = _numbers(source_text)
        if len(numbers) != 3:
            raise DsaregInputError("needs 3 numbers (x y z mm)", field=f"{field_name}.SourcePosition")
        source = np.array(numbers, dtype=np.float64)
    return RadHeader(size, tuple(float(s) for s in step), np.dtype(_DTYPES[type_text]), tposition, source, values)


def view_from_rad(header: RadHeader, *, field_name: str = "rad") -> ViewGeometry:
    """The :class:`ViewGeometry` a 2D ``.rad`` header describes."""
    if header.ndim != 2:
        raise DsaregInputError(f"describes a {header.ndim}D volume, not an image", field=field_name)
    if header.tposition is None or header.source_position is None:
        raise DsaregInputError("needs TPosition and SourcePosition[mm] to give the imaging geometry", field=field_name)
    try:
        return view_from_detector_pose(header.size, header.step_mm, header.tposition, header.source_position)
    except DsaregInputError as exc:
        raise exc.with_field_prefix(field_name) from None


def volume_affine_from_rad(header: RadHeader, *, field_name: str = "rad") -> np.ndarray:
    """Voxel index → world mm affine of a 3D ``.rad`` header (``TPosition`` · diag(step))."""
    if header.ndim != 3:
        raise DsaregInputError("describes a 2D image, not a volume", field=field_name)
    pose = np.eye(4) if header.tposition is None else header.tposition
    pose = validate_rigid(pose, field=f"{field_name}.TPosition", allow_mirror=True)
    return pose @ np.diag([*header.step_mm, 1.0])


def read_raw(header: RadHeader, raw: bytes, *, max_bytes: int, field_name: str = "raw") -> np.ndarray:
    """The ``.raw`` samples as float32, shaped ``(rows, cols)`` or ``(nx, ny, nz)`` (index order i, j, k)."""
    expected = header.n_bytes
    if expected > max_bytes:
        raise DsaregInputError(
            f"declares {expected / 2**20:.0f} MiB of samples, above the limit of {max_bytes / 2**20:.0f} MiB",
            field=field_name,
        )
    if len(raw) != expected:
        raise DsaregInputError(
            f"holds {len(raw)} bytes; the .rad header ({'x'.join(map(str, header.size))} {header.dtype.name}) "
            f"needs {expected}",
            field=field_name,
        )
    samples = np.frombuffer(raw, dtype=header.dtype).astype(np.float32)
    if header.ndim == 2:
        cols, rows = header.size
        return samples.reshape(rows, cols)
    nx, ny, nz = header.size
    return np.ascontiguousarray(samples.reshape(nz, ny, nx).transpose(2, 1, 0))


def format_rad_header(size, step_mm, data_type: str = "float", tposition=None, source_position=None) -> bytes:
    """Write a ``.rad`` header (used by tests and exporters)."""
    lines = [
        f"Size[pixels]: {' '.join(str(int(s)) for s in size)}",
        f"Step[mm]: {' '.join(repr(float(s)) for s in step_mm)}",
        f"DataType: {data_type}",
    ]
    if source_position is not None:
        lines.append("SourcePosition[mm]: " + " ".join(repr(float(x)) for x in source_position))
    if tposition is not None:
        lines.append("TPosition:")
        lines.extend(" ".join(repr(float(x)) for x in row) for row in np.asarray(tposition))
    return ("\n".join(lines) + "\n").encode()
