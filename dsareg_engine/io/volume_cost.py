"""What reading a volume will cost, from its header alone: the declared shape, and the memory and CPU time the
first read (vessels extracted, surface made) is expected to take.

Why: a service parses every submission in a process with a memory and time allowance sized for images and models;
a whole-head CTA (512 × 512 × 440) needs more than that allowance, a 3D-RA crop far less. The header tells which
before any voxel is decoded, so the allowance can be sized for this volume (and a volume beyond what the server
allows refused at once, not after a minute of work).

* :func:`declared_volume`: the shape every reader declares (and checks against ``max_volume_bytes``) before it
  decodes a voxel, got by running the reader itself under a :class:`~.limits.ShapeProbe` (the same parsing and the
  same refusals as a full read, up to that point: a broken header is refused here already).
* :func:`expected_read_cost`: address-space growth (MB) and CPU s of the first read of ``voxels`` voxels,
  interpolated in :data:`MEASURED` (CTA) or :data:`MEASURED_MRA` (TOF-MRA), by the volume's kind (a warmed-up
  process, as the service's validator is; measured with ``python -m benchmarks.engine whole-head --intake
  [--kind mra]``), extrapolated past the largest at its last slope.
* :func:`volume_read_cost`: both for a case's volume files, zero when its model is already kept
  (:mod:`.model_cache`: a hit reads headers only).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .limits import DEFAULT_LIMITS, DeclaredShape, InputLimits, ShapeProbe
from .model_cache import ModelStore, model_key
from .volume_io import read_volume
from .volume_kind import VolumeReading

MEASURED: tuple[tuple[float, float, float], ...] = (
    # voxels, address-space growth MB, CPU s of the first read of a case (the volume's files already in memory, the
    # process warmed up as the service's validator is: ``python -m benchmarks.engine whole-head --intake``);
    # 2 CPU cores x86_64, loaded by other engineers, at 7a41475. Reads at 49c1c15 cost 60-86 % of these in memory and
    # 44-49 % in CPU (docs/benchmarks/clinical.md): kept as upper bounds for costlier heads and slower CPUs
    (0.0, 40.0, 0.4),  # headers and the volume reader's first imports (a kept model's case: 39-42 MB, 0.3 s)
    (0.53e6, 49.0, 0.4),  # 75 x 75 x 95 at 1.2 mm (the service tests' small CTA: a small head)
    (3.6e6, 446.0, 7.4),  # 160 x 160 x 140 at 1.2 mm (a whole head, coarse voxels)
    (14.4e6, 665.0, 11.0),  # 256 x 256 x 220 at 0.9 mm
    (48.7e6, 956.0, 21.5),  # 384 x 384 x 330 at 0.6 mm
    (115.3e6, 1089.0, 40.4),  # 512 x 512 x 440 at 0.45 mm (whole-head CTA; 193 s of wall-clock on the loaded machine)
)
"""Measured first reads of the layered CTA head (:mod:`benchmarks.engine.whole_head`): one field of view (a
whole head) at five voxel sizes, and the service tests' small head. The cost is not proportional to the voxels:
the plate/tube measure resamples the candidate mask's box to 0.5 mm, at most 16 M voxels
(:mod:`.medial_shape`), so a coarse-voxel head costs as much working grid as a fine one and the cost per voxel
falls as the voxels grow. Between two measured reads of whole heads the cost rises by at most 1.5 x in memory and
2 x in CPU (446 → 665 MB, 11 → 21.5 s), so an interpolated estimate times the service's margins (1.5 x memory,
3 x CPU: :mod:`service.intake.allowance`) covers every size between them; below 3.6 M voxels the estimate can be
low for coarse voxels, where the service's base limits (512 MB, 60 s) hold the read anyway."""


MEASURED_MRA: tuple[tuple[float, float, float], ...] = (
    # the same, of TOF-MRA slabs of generator B's layered head (``whole-head --intake --kind mra``: read by
    # :func:`benchmarks.engine.whole_head.read_as_validator`; here the ``--sweep`` cells' cases), 2 cores, at 8ff4d22
    (0.0, 40.0, 0.4),
    (41.9e6, 1382.0, 24.7),  # 512 x 512 x 160 at 0.4 x 0.4 x 0.5 mm (a TOF slab, 80 mm)
    (78.6e6, 1969.0, 39.0),  # 512 x 512 x 300 at 0.35 x 0.35 x 0.3 mm
)
"""A TOF-MRA read takes more address space per voxel than a CTA's (the head's interior and its 7-mm scalp band
over the whole grid, numba's runtime for the band's distance transform: ~190 MB of address space, 100 MB resident):
the 160-slice slab 1.4 GB where a CTA of its voxels takes 0.9. A DICOM series' Modality (MR) or ``volume_kind``
tells which curve a volume's read follows (:func:`expected_read_cost`)."""


KIND_OF_MODALITY = {"CT": "cta", "MR": "mra"}
"""A DICOM series' Modality → the reading's kind, for its expected cost (an XA/3D-RA volume reads as a CTA does)."""


@dataclass(frozen=True)
class VolumeCost:
    """A volume's declared ``shape`` and its first read's expected ``memory_mb`` (address-space growth) and
    ``cpu_s``; ``cached``: its model is kept, the read costs headers only."""

    shape: tuple[int, ...]
    memory_mb: float
    cpu_s: float
    cached: bool = False

    @property
    def voxels(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))


def declared_volume(data: bytes | list[bytes], name: str | None = None, limits: InputLimits = DEFAULT_LIMITS, *,
                    field_name: str = "volume") -> tuple[int, ...] | None:
    """The volume's declared shape, from its header (no voxel decoded); ``None`` when its reader declared none
    before decoding (then it was read whole). Raises ``DsaregInputError`` as :func:`.volume_io.read_volume` does
    for everything it checks before the shape (format, series, declared size above ``limits``)."""
    declared = _declared(data, name, limits, field_name)
    return None if declared is None else declared.shape


def _declared(data, name, limits: InputLimits, field_name: str = "volume") -> DeclaredShape | None:
    try:
        read_volume(data, name, ShapeProbe(**asdict(limits)), field_name=field_name)
    except DeclaredShape as declared:
        return declared
    return None


def expected_read_cost(voxels: int, kind: str | None = None) -> tuple[float, float]:
    """``(memory MB, CPU s)`` the first read of ``voxels`` voxels is expected to take: a TOF-MRA's
    (:data:`MEASURED_MRA`) for ``kind`` ``"mra"``, a CTA's (:data:`MEASURED`) for any other kind; for a kind not
    known (``None``: no DICOM Modality, ``volume_kind`` auto) the larger of the CTA's and the largest TOF read
    measured (TOF is acquired as a slab: its curve is not extrapolated for a volume that may be a whole-head CTA).
    Each interpolated, past its largest measure at its last slope."""
    n = float(max(0, voxels))
    if kind == "mra":
        return _interpolated(np.array(MEASURED_MRA), n)
    cta = _interpolated(np.array(MEASURED), n)
    if kind is not None:
        return cta
    tof = _interpolated(np.array(MEASURED_MRA), min(n, MEASURED_MRA[-1][0]))
    return max(cta[0], tof[0]), max(cta[1], tof[1])


def _interpolated(points: np.ndarray, n: float) -> tuple[float, float]:
    if n <= points[-1, 0]:
        return float(np.interp(n, points[:, 0], points[:, 1])), float(np.interp(n, points[:, 0], points[:, 2]))
    (n0, m0, c0), (n1, m1, c1) = points[-2], points[-1]
    return float(m1 + (n - n1) * (m1 - m0) / (n1 - n0)), float(c1 + (n - n1) * (c1 - c0) / (n1 - n0))


def volume_read_cost(volume: bytes | list[bytes], name: str | None, limits: InputLimits = DEFAULT_LIMITS,
                     reading: VolumeReading | None = None, store: ModelStore | None = None) -> VolumeCost | None:
    """What reading ``volume`` (a case's volume files) will cost; ``None`` when its header declares no shape."""
    declared = _declared(volume, name, limits)
    if declared is None:
        return None
    shape = declared.shape
    given = reading.kind if reading is not None and reading.kind != "auto" else None
    kind = given or KIND_OF_MODALITY.get(declared.modality.upper(), "cta" if declared.modality else None)
    if store is not None and store.get(model_key(volume, name, reading, limits.working_faces)) is not None:
        return VolumeCost(shape, *expected_read_cost(0, "cta"), cached=True)
    voxels = int(np.prod(shape, dtype=np.int64))
    return VolumeCost(shape, *expected_read_cost(voxels, kind))


__all__ = ["MEASURED", "MEASURED_MRA", "VolumeCost", "declared_volume", "expected_read_cost", "volume_read_cost"]
