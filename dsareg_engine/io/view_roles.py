"""Which file is which view, and were the two runs acquired together? Read from the DICOM XA headers.

**Beam obliquity.** A view's +z axis is its central ray, source → detector (docs/concepts/geometry.md),
so row 2 of ``world_to_view`` is the beam direction ``d`` in the world. For geometry read from DICOM XA
tags the world is patient LPS (:mod:`.dicom_xa`), so the angle between the beam's projection on the axial
plane and the patient's anterior–posterior axis is ``atan2(|d_x|, |d_y|)``: 0° for an AP or PA beam,
90° for a lateral one, whatever the signs of the positioner angles (LAO/RAO, CRA/CAU). The AP view is the
one whose beam is nearer the anterior–posterior axis, the LAT the one nearer left–right.

**Roles** (:func:`views_by_role`), only when both views' geometry comes from DICOM headers (an explicit
geometry names the views itself): the pair looks *swapped* when the file given as AP is at least
:data:`SWAP_MARGIN_DEG` more oblique than the file given as LAT. When each file is then unambiguous (the
given AP within :data:`CLEAR_DEG` of left–right, the given LAT within it of anterior–posterior) the roles are
swapped back, recorded as an :class:`InputDecision` ("view roles": "swapped") and every later output is
labelled by the corrected role. When they are not, and the plane labels (ImageType ``BIPLANE A`` / ``B``:
plane A frontal, B lateral) do not confirm the roles as given, the case is refused with a reason saying
"swapped".

**Acquisition** (:func:`acquisition_of`): two runs whose start times (Acquisition DateTime, else Acquisition
Date + Time, else Content Date + Time) lie more than :data:`SEQUENTIAL_S` apart were not acquired together
(a monoplane C-arm, or two single-plane runs): the head may have moved between them. Two single-plane runs
(ImageType ``SINGLE PLANE``) with different frames of reference are sequential too. Nothing else is taken as
evidence: synthetic and some vendor biplane pairs say ``SINGLE PLANE`` on both planes with one time.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import ViewGeometry
from .dicom_identity import TIME_ONLY_DAY
from .input_decisions import InputDecision

SWAP_MARGIN_DEG = 20.0
"""The file given as AP this much more oblique than the one given as LAT: the pair looks swapped."""
CLEAR_DEG = 30.0
"""A beam within this of an axis has an unambiguous role (AP within it of anterior–posterior, LAT of left–right)."""
SEQUENTIAL_S = 10.0
"""Start times farther apart than this: two runs, not one biplane acquisition (biplane planes fire within
a second or two; a second injection takes minutes)."""
ROLE_BASIS = "beam angle from the anterior-posterior axis (degrees) of the file given as AP minus the LAT's"


def beam_obliquity_deg(view: ViewGeometry) -> float:
    """Angle (0–90°) between the view's beam, projected on the axial plane, and the anterior–posterior axis."""
    beam = np.asarray(view.world_to_view, dtype=np.float64)[2, :3]
    return float(np.degrees(np.arctan2(abs(beam[0]), abs(beam[1]))))


@dataclass(frozen=True)
class RunHeader:
    """What the headers say about one run: ``plane`` (``"A"`` / ``"B"`` of a biplane run, ``"single"``, or None),
    its ``start`` time and frame of reference UID."""

    plane: str | None = None
    start: datetime | None = None
    frame_uid: str | None = None


def run_header(identity) -> RunHeader | None:
    """The :class:`RunHeader` of an image's :class:`~.dicom_identity.DicomIdentity` (taken when it was read: no
    parse again), or None when it is not DICOM."""
    if identity is None:
        return None
    values = identity.image_type
    plane = "A" if "BIPLANE A" in values else "B" if "BIPLANE B" in values else (
        "single" if "SINGLE PLANE" in values else None)
    return RunHeader(plane=plane, start=identity.start, frame_uid=identity.frame_of_reference_uid)


def _relabelled(image, role: str, given: str):
    """``image`` (a LoadedImage given as ``given``) with its warnings and decisions named ``role``."""
    prefix = f"{given}:"
    warnings = [f"{role}:{w[len(prefix):]}" if w.startswith(prefix) else w for w in image.warnings]
    decisions = [dataclasses.replace(d, input=role) if d.input == given else d for d in image.decisions]
    return dataclasses.replace(image, warnings=warnings, decisions=decisions)


def views_by_role(images: dict, headers: dict[str, RunHeader | None],
                  explicit_geometry: bool) -> tuple[dict, list[InputDecision]]:
    """``(images by their true role, decisions)`` for ``images`` (``{"ap", "lat"}`` LoadedImage as given).

    Raises:
        DsaregInputError: the pair looks swapped but the angles do not say so clearly enough to correct it.
    """
    if explicit_geometry or any(not images[n].kind.startswith("dicom") or images[n].geometry is None
                                for n in ("ap", "lat")):
        return images, []
    ap, lat = (beam_obliquity_deg(images[n].geometry) for n in ("ap", "lat"))
    margin = ap - lat
    planes = tuple((headers.get(n) or RunHeader()).plane for n in ("ap", "lat"))
    if margin < SWAP_MARGIN_DEG:
        return images, [InputDecision("ap", "view roles", "as given", ROLE_BASIS, round(margin, 2), SWAP_MARGIN_DEG,
                                      source="tag")]
    if ap >= 90.0 - CLEAR_DEG and lat <= CLEAR_DEG:
        swapped = {"ap": _relabelled(images["lat"], "ap", "lat"), "lat": _relabelled(images["ap"], "lat", "ap")}
        swapped["ap"].warnings.insert(0, f"views swapped: the file given as LAT is the frontal view (beam {lat:.0f}° "
                                         f"from anterior-posterior) and the file given as AP the lateral one "
                                         f"({ap:.0f}°); every output is named by the view each file is")
        return swapped, [InputDecision("ap", "view roles", "swapped", ROLE_BASIS, round(margin, 2), SWAP_MARGIN_DEG,
                                       source="tag")]
    if planes == ("A", "B"):
        return images, [InputDecision("ap", "view roles", "as given (planes A and B)", ROLE_BASIS, round(margin, 2),
                                      SWAP_MARGIN_DEG, source="tag")]
    raise DsaregInputError(
        f"the views look swapped: the file given as AP has its beam {ap:.0f}° from the anterior-posterior axis, "
        f"the file given as LAT {lat:.0f}° (the AP view is the more frontal one), and the angles are too oblique "
        "to correct it safely", field="ap",
        accepted="the frontal run as ap and the lateral run as lat, or a geometry naming each view")


@dataclass(frozen=True)
class Acquisition:
    """Whether the two runs were acquired together.

    Attributes:
        sequential: True: two runs at different times (the head may have moved between them).
        basis: what says so, in words (the start times, or the frames of reference).
        interval_s: seconds between the runs' starts (LAT − AP), or None when a time is missing.
    """

    sequential: bool
    basis: str
    interval_s: float | None = None

    def to_dict(self) -> dict:
        return {"sequential": self.sequential, "basis": self.basis,
                "interval_s": None if self.interval_s is None else round(self.interval_s, 3)}


def _seconds_between(first: datetime, second: datetime) -> float:
    """``second − first`` in seconds; by time of day alone when either lacks its date (:data:`TIME_ONLY_DAY`)."""
    if TIME_ONLY_DAY.date() in (first.date(), second.date()):
        first, second = (datetime.combine(TIME_ONLY_DAY.date(), t.time()) for t in (first, second))
    return (second - first).total_seconds()


def acquisition_of(headers: dict[str, RunHeader | None]) -> tuple[Acquisition | None, list[InputDecision]]:
    """The :class:`Acquisition` of the two runs and its decision, or ``(None, [])`` without DICOM headers on both."""
    ap, lat = headers.get("ap"), headers.get("lat")
    if ap is None or lat is None:
        return None, []
    if ap.start is not None and lat.start is not None:
        interval = _seconds_between(ap.start, lat.start)
        times = f"{ap.start:%H:%M:%S} and {lat.start:%H:%M:%S}"
        sequential = abs(interval) > SEQUENTIAL_S
        basis = f"the runs started at {times} ({abs(interval):.0f} s apart)"
        decision = InputDecision("lat", "acquisition", "sequential runs" if sequential else "together",
                                 "seconds between the AP and LAT runs' start times", round(abs(interval), 3),
                                 SEQUENTIAL_S, source="tag")
        return Acquisition(sequential, basis, interval), [decision]
    if ap.plane == lat.plane == "single" and ap.frame_uid and lat.frame_uid and ap.frame_uid != lat.frame_uid:
        basis = "two single-plane runs with different frames of reference"
        return Acquisition(True, basis), [InputDecision("lat", "acquisition", "sequential runs", basis, source="tag")]
    return None, []


def named_views(images: dict, explicit_geometry: bool, decisions: list[InputDecision],
                kinds: dict[str, str], warnings: list[str]) -> tuple[dict, Acquisition | None]:
    """The case reader's step: ``images`` (LoadedImage by the role given) by their true roles (:func:`views_by_role`)
    and the runs' :class:`Acquisition` (from the identities the readers took); appends the decisions to
    ``decisions``, each view's kind to ``kinds`` and its warnings to ``warnings``."""
    headers = {name: run_header(images[name].dicom) for name in ("ap", "lat")}
    images, roles = views_by_role(images, headers, explicit_geometry)
    if roles and roles[0].chosen == "swapped":
        headers = {"ap": headers["lat"], "lat": headers["ap"]}
    acquisition, acquired = acquisition_of(headers)
    decisions.extend(roles + acquired)
    for name in ("ap", "lat"):
        kinds[name] = images[name].kind
        warnings.extend(images[name].warnings)
    return images, acquisition


def views_swapped(decisions: list[InputDecision]) -> bool:
    """Whether the case's views were swapped back (:func:`views_by_role`): the AP view is the file given as LAT."""
    return any(d.what == "view roles" and d.chosen == "swapped" for d in decisions)
