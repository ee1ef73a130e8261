"""From the instances of one study to registration jobs: biplane XA pairs and the vessel model.

Pairs, first rule that applies wins for an instance:

1. **explicit references**: an XA whose Referenced Image Sequence item has the purpose
   "Other image of biplane pair" (DCM 121314) names its partner;
2. **Plane Identification** (enhanced XA, ``PLANE A`` / ``PLANE B``): one A and one B of the
   study, closest in acquisition time, are a pair;
3. **angles and time**: two XA runs whose view directions differ by at least
   ``MIN_PAIR_ANGLE_DEG`` and whose acquisition times differ by at most ``MAX_PAIR_SECONDS``
   (closest first);
4. a study with **exactly two** XA instances is one pair, whatever their angles.

In each pair the AP view is the one whose primary angle is nearest 0°. The model is the
volume series of the study (CT, MR, enhanced CT/MR, X-Ray 3D Angiographic) with the most
instances (a multi-frame series counts its frames). No volume: no job yet (the study is
kept; a volume sent later makes the job), and the pairs are listed in ``StudyPlan.unmodelled``:
the dispatcher may fetch the patient's latest volume from ``dicom_query_peer`` (:mod:`.query`).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Any

XA_CLASSES = {"1.2.840.10008.5.1.4.1.1.12.1": "XA", "1.2.840.10008.5.1.4.1.1.12.1.1": "enhanced XA"}
VOLUME_CLASSES = {
    "1.2.840.10008.5.1.4.1.1.2": "CT", "1.2.840.10008.5.1.4.1.1.2.1": "enhanced CT",
    "1.2.840.10008.5.1.4.1.1.4": "MR", "1.2.840.10008.5.1.4.1.1.4.1": "enhanced MR",
    "1.2.840.10008.5.1.4.1.1.13.1.1": "X-Ray 3D angiographic",
}
OTHER_PLANE_CODE = "121314"  # DCM "Other image of biplane pair"
MIN_PAIR_ANGLE_DEG = 60.0
MAX_PAIR_SECONDS = 30.0


@dataclass(frozen=True)
class XaView:
    sop_instance_uid: str
    primary_deg: float | None
    secondary_deg: float | None
    plane: str | None  # "A" / "B" from Plane Identification
    acquired: float | None  # seconds (date + time), for "close in time"
    partners: tuple[str, ...]  # SOP Instance UIDs referenced as the other image of the biplane pair


@dataclass
class PlannedJob:
    ap: str
    lat: str
    volume: list[str]
    rule: str
    volume_origin: dict | None = None  # where a volume not in the study came from (C-MOVE)

    @property
    def instances(self) -> list[str]:
        return [self.ap, self.lat, *self.volume]


@dataclass
class StudyPlan:
    jobs: list[PlannedJob] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    unmodelled: list[tuple[str, str, str]] = field(default_factory=list)  # (AP, LAT, rule) pairs without a volume


def _first(ds: Any, keyword: str) -> Any:
    """The first value of ``keyword`` at any depth (enhanced objects keep it in functional groups)."""
    if keyword in ds:
        return ds.data_element(keyword).value
    for element in ds.iterall():
        if element.keyword == keyword:
            return element.value
    return None


def _float(value: Any) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _acquired(ds: Any) -> float | None:
    stamp = _first(ds, "AcquisitionDateTime")
    if not stamp:
        date, time = _first(ds, "AcquisitionDate") or _first(ds, "ContentDate"), (
            _first(ds, "AcquisitionTime") or _first(ds, "ContentTime"))
        if not date or not time:
            return None
        stamp = f"{date}{time}"
    text = str(stamp).split("+")[0].split("-")[0]
    try:
        whole, _, fraction = text.partition(".")
        moment = _dt.datetime.strptime(whole[:14].ljust(14, "0"), "%Y%m%d%H%M%S")
        return moment.replace(tzinfo=_dt.UTC).timestamp() + (float(f"0.{fraction}") if fraction else 0.0)
    except ValueError:
        return None


def _partners(ds: Any) -> tuple[str, ...]:
    found = []
    for item in _first(ds, "ReferencedImageSequence") or []:
        codes = getattr(item, "PurposeOfReferenceCodeSequence", None) or []
        if any(str(getattr(code, "CodeValue", "")) == OTHER_PLANE_CODE for code in codes):
            uid = getattr(item, "ReferencedSOPInstanceUID", None)
            if uid:
                found.append(str(uid))
    return tuple(found)


def xa_view(ds: Any) -> XaView:
    plane = str(_first(ds, "PlaneIdentification") or "").upper()
    return XaView(
        sop_instance_uid=str(ds.SOPInstanceUID),
        primary_deg=_float(_first(ds, "PositionerPrimaryAngle")),
        secondary_deg=_float(_first(ds, "PositionerSecondaryAngle")),
        plane="A" if plane.endswith(" A") else "B" if plane.endswith(" B") else None,
        acquired=_acquired(ds), partners=_partners(ds))


def _ordered(a: XaView, b: XaView) -> tuple[XaView, XaView]:
    """(AP, LAT): AP is the view whose primary angle is nearest 0°."""
    def key(view: XaView) -> float:
        return abs(view.primary_deg) if view.primary_deg is not None else math.inf
    return (a, b) if key(a) <= key(b) else (b, a)


def _close_in_time(a: XaView, b: XaView) -> float:
    if a.acquired is None or b.acquired is None:
        return MAX_PAIR_SECONDS  # unknown: allowed, ranked last
    return abs(a.acquired - b.acquired)


def pair_views(views: list[XaView], angle_between) -> list[tuple[XaView, XaView, str]]:
    """Biplane pairs among ``views``; ``angle_between(a, b)``: degrees between their view directions."""
    by_uid = {v.sop_instance_uid: v for v in views}
    free = dict(by_uid)
    pairs: list[tuple[XaView, XaView, str]] = []

    def take(a: XaView, b: XaView, rule: str) -> None:
        free.pop(a.sop_instance_uid, None)
        free.pop(b.sop_instance_uid, None)
        pairs.append((*_ordered(a, b), rule))

    for view in views:
        for uid in view.partners:
            if view.sop_instance_uid in free and uid in free and uid != view.sop_instance_uid:
                take(view, by_uid[uid], "other image of biplane pair")
    for rule, candidates in (("plane identification", _plane_candidates), ("angles and time", _angle_candidates)):
        for a, b in candidates(list(free.values()), angle_between):
            if a.sop_instance_uid in free and b.sop_instance_uid in free:
                take(a, b, rule)
    if not pairs and len(views) == 2:
        take(views[0], views[1], "the study's only two XA")
    return pairs


def _plane_candidates(views: list[XaView], _angle_between) -> list[tuple[XaView, XaView]]:
    a_views = [v for v in views if v.plane == "A"]
    b_views = [v for v in views if v.plane == "B"]
    found = [(a, b) for a in a_views for b in b_views if _close_in_time(a, b) <= MAX_PAIR_SECONDS]
    return sorted(found, key=lambda ab: _close_in_time(*ab))


def _angle_candidates(views: list[XaView], angle_between) -> list[tuple[XaView, XaView]]:
    found = []
    for i, a in enumerate(views):
        for b in views[i + 1:]:
            if None in (a.primary_deg, a.secondary_deg, b.primary_deg, b.secondary_deg):
                continue
            if angle_between(a, b) >= MIN_PAIR_ANGLE_DEG and _close_in_time(a, b) <= MAX_PAIR_SECONDS:
                found.append((a, b))
    return sorted(found, key=lambda ab: (_close_in_time(*ab), -angle_between(*ab)))


def _frames(ds: Any) -> int:
    try:
        return max(1, int(getattr(ds, "NumberOfFrames", 1) or 1))
    except (TypeError, ValueError):
        return 1


def choose_volume(headers: list[Any]) -> list[Any]:
    """The instances of the study's largest volume series, in Instance Number order (empty: none)."""
    series: dict[str, list[Any]] = {}
    for ds in headers:
        if str(ds.SOPClassUID) in VOLUME_CLASSES:
            series.setdefault(str(ds.SeriesInstanceUID), []).append(ds)
    if not series:
        return []
    best = max(series.values(), key=lambda items: sum(_frames(ds) for ds in items))
    return sorted(best, key=lambda ds: _float(getattr(ds, "InstanceNumber", None)) or 0.0)


def plan_study(headers: list[Any], angle_between) -> StudyPlan:
    """The jobs of one study from its instances' headers (pydicom datasets, no pixels)."""
    plan = StudyPlan()
    views = [xa_view(ds) for ds in headers if str(ds.SOPClassUID) in XA_CLASSES]
    volume = choose_volume(headers)
    if len(views) < 2:
        plan.notes.append(f"{len(views)} XA instance(s): a biplane pair needs two")
        return plan
    pairs = pair_views(views, angle_between)
    if not pairs:
        plan.notes.append(f"{len(views)} XA instances, none pairs as biplane (references, plane, "
                          f"≥ {MIN_PAIR_ANGLE_DEG:g}° within {MAX_PAIR_SECONDS:g} s)")
    if not volume:
        plan.notes.append("no CT / MR / 3D-RA volume series in the study: waiting for one")
        plan.unmodelled = [(ap.sop_instance_uid, lat.sop_instance_uid, rule) for ap, lat, rule in pairs]
        return plan
    uids = [str(ds.SOPInstanceUID) for ds in volume]
    plan.jobs = [PlannedJob(ap.sop_instance_uid, lat.sop_instance_uid, uids, rule) for ap, lat, rule in pairs]
    return plan
