"""Biplane pairs and the volume of a received study (service/pacs/dimse/grouping.py), from headers only."""

from __future__ import annotations

import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from service.pacs.dimse.dispatcher import angle_between
from service.pacs.dimse.grouping import plan_study

pytestmark = pytest.mark.filterwarnings("ignore:Invalid value for VR UI")  # readable names as UIDs

XA, ENHANCED_XA, CT = "1.2.840.10008.5.1.4.1.1.12.1", "1.2.840.10008.5.1.4.1.1.12.1.1", "1.2.840.10008.5.1.4.1.1.2"


def xa(uid: str, primary: float, secondary: float = 0.0, time: str = "120000", sop_class: str = XA, **extra):
    ds = Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID, ds.SeriesInstanceUID = sop_class, uid, "s" + uid
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = primary, secondary
    ds.AcquisitionDate, ds.AcquisitionTime = "20260101", time
    for key, value in extra.items():
        setattr(ds, key, value)
    return ds


def ct(series: str, count: int) -> list:
    out = []
    for k in range(count):
        ds = Dataset()
        ds.SOPClassUID, ds.SOPInstanceUID, ds.SeriesInstanceUID, ds.InstanceNumber = CT, f"{series}.{k}", series, k + 1
        out.append(ds)
    return out


def pairs(plan) -> list[tuple[str, str, str]]:
    return sorted((job.ap, job.lat, job.rule) for job in plan.jobs)


def test_exactly_two_xa_are_one_pair_and_ap_is_nearest_zero():
    plan = plan_study([xa("1", 85.0), xa("2", -10.0, 20.0, time="130000"), *ct("v", 3)], angle_between)
    assert pairs(plan) == [("2", "1", "the study's only two XA")]  # 1 h apart and only 80° → still the one pair
    assert plan.jobs[0].volume == ["v.0", "v.1", "v.2"]


def test_two_biplane_runs_pair_by_angle_and_time():
    views = [xa("a1", 0.0, time="120000"), xa("b1", 90.0, time="120001"),
             xa("a2", 30.0, 20.0, time="121000"), xa("b2", 120.0, 0.0, time="121002"),
             xa("single", 45.0, time="123000")]  # a third, lone run
    plan = plan_study([*views, *ct("v", 2)], angle_between)
    assert pairs(plan) == [("a1", "b1", "angles and time"), ("a2", "b2", "angles and time")]


def test_close_views_are_not_a_biplane_pair():
    plan = plan_study([xa("1", 0.0), xa("2", 20.0), xa("3", 40.0, time="120005"), *ct("v", 2)], angle_between)
    assert plan.jobs == [] and "none pairs" in plan.notes[0]


def test_other_image_of_biplane_pair_references_win():
    code = Dataset()
    code.CodeValue, code.CodingSchemeDesignator, code.CodeMeaning = "121314", "DCM", "Other image of biplane pair"
    ref = Dataset()
    ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = XA, "far"
    ref.PurposeOfReferenceCodeSequence = Sequence([code])
    views = [xa("near", 0.0, ReferencedImageSequence=Sequence([ref])), xa("lat", 90.0), xa("far", 70.0, time="120500")]
    plan = plan_study([*views, *ct("v", 2)], angle_between)
    assert pairs(plan) == [("near", "far", "other image of biplane pair")]


def test_enhanced_xa_plane_identification():
    views = [xa("pa", 10.0, sop_class=ENHANCED_XA, PlaneIdentification="PLANE A"),
             xa("pb", 50.0, sop_class=ENHANCED_XA, PlaneIdentification="PLANE B", time="120002"),
             xa("x", 100.0, time="120003")]
    plan = plan_study([*views, *ct("v", 2)], angle_between)
    assert pairs(plan) == [("pa", "pb", "plane identification")]  # only 40° apart, but the planes say so


def test_no_volume_no_job_and_the_largest_series_is_the_model():
    assert plan_study([xa("1", 0.0), xa("2", 90.0)], angle_between).jobs == []
    plan = plan_study([xa("1", 0.0), xa("2", 90.0), *ct("small", 2), *ct("big", 5)], angle_between)
    assert [uid.split(".")[0] for uid in plan.jobs[0].volume] == ["big"] * 5
