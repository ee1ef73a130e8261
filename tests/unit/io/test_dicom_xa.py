import io

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.dicom_xa import rig_from_xa, view_from_angles, view_from_xa

SID, SOD, DU, DV, W, H = 1200.0, 800.0, 0.3, 0.25, 80, 64
U0, V0 = (W - 1) / 2, (H - 1) / 2


def expected_pixel(point, primary, secondary):
    """Independent projection: ray from the source through the point, hit on the detector plane.

    Written from the clinical description only: the detector is anterior at AP, LAO moves
    it toward the patient's left, CRA toward the head; image columns run horizontally
    (patient left at AP), rows downward (toward the feet at AP).
    """
    a, b = np.radians(primary), np.radians(secondary)
    toward_detector = np.array([np.cos(b) * np.sin(a), -np.cos(b) * np.cos(a), np.sin(b)])
    column_direction = np.array([np.cos(a), np.sin(a), 0.0])  # horizontal, perpendicular to the beam
    row_direction = np.cross(column_direction, toward_detector)  # "down" on the monitor
    source = -SOD * toward_detector
    detector_centre = (SID - SOD) * toward_detector
    ray = np.asarray(point, float) - source
    t = np.dot(detector_centre - source, toward_detector) / np.dot(ray, toward_detector)
    hit = source + t * ray - detector_centre
    return np.array([U0 + hit @ column_direction / DU, V0 + hit @ row_direction / DV])


def view(primary, secondary):
    return view_from_angles(primary, secondary, SID, SOD, (DU, DV), (W, H))


def test_ap_directions_by_hand():
    ap = view(0, 0)
    magnification = SID / SOD
    np.testing.assert_allclose(ap.source_position_world, [0, SOD, 0])  # posterior of the patient
    np.testing.assert_allclose(ap.project(np.array([[0.0, 0, 0]]))[0], [U0, V0])
    np.testing.assert_allclose(
        ap.project(np.array([[10.0, 0, 0]]))[0], [U0 + magnification * 10 / DU, V0]
    )  # left → right
    np.testing.assert_allclose(ap.project(np.array([[0.0, 0, 10]]))[0], [U0, V0 - magnification * 10 / DV])  # head → up
    near_source = ap.project(np.array([[10.0, 100, 0]]))[0]  # 100 mm posterior: larger magnification
    np.testing.assert_allclose(near_source, [U0 + SID / (SOD - 100) * 10 / DU, V0])
    assert ap.is_mirrored  # displayed as seen from the detector side


def test_lao90_is_left_lateral():
    lateral = view(90, 0)
    np.testing.assert_allclose(lateral.source_position_world, [-SOD, 0, 0], atol=1e-9)  # source at patient's right
    u, v = lateral.project(np.array([[0.0, 10.0, 0.0]]))[0]  # posterior (spine) → right of the image
    assert u > U0 + 10 and abs(v - V0) < 1e-9
    u, v = lateral.project(np.array([[0.0, 0.0, 10.0]]))[0]  # head still up
    assert v < V0 - 10


@pytest.mark.parametrize("primary, secondary", [(0, 0), (30, 0), (-45, 20), (90, -25), (-17, 35), (120, 10)])
def test_projection_matches_independent_computation(primary, secondary):
    points = np.array([[10.0, -20.0, 5.0], [-35.0, 12.0, 40.0], [0.0, 0.0, -30.0], [25.0, 25.0, 25.0]])
    got = view(primary, secondary).project(points)
    want = np.array([expected_pixel(p, primary, secondary) for p in points])
    np.testing.assert_allclose(got, want, atol=1e-7)


def test_cranial_source_is_caudal():
    source = view(0, 30).source_position_world
    assert source[2] < 0 and source[1] > 0  # tube below the feet side, posterior


def test_xa_headers_to_rig_with_true_angle(build):
    ap = build.xa(primary=-17.0, secondary=0.0, sid=SID, sod=SOD, spacing=(DV, DU), rows=H, cols=W)
    lat = build.xa(primary=90.0, secondary=0.0, sid=1100.0, sod=750.0, spacing=(0.2, 0.2), rows=H, cols=W)
    rig = rig_from_xa(ap, lat)
    assert rig.angle_between_views_deg() == pytest.approx(107.0, abs=1e-6)
    np.testing.assert_allclose(rig.views["ap"].pixel_spacing_mm, (DU, DV))  # DICOM [row, column] order
    assert rig.views["lat"].sid_mm == 1100.0 and rig.views["ap"].image_size == (W, H)
    point = np.array([[10.0, -20.0, 5.0]])
    np.testing.assert_allclose(rig.views["ap"].project(point)[0], expected_pixel(point[0], -17, 0), atol=1e-7)


def test_missing_geometry_tags(build):
    data = build.xa(primary=None, sid=None, rows=H, cols=W)
    dataset = pydicom.dcmread(io.BytesIO(data), force=True)
    geometry, warnings = view_from_xa(dataset)
    assert geometry is None and "PositionerPrimaryAngle" in warnings[0] and "DistanceSourceToDetector" in warnings[0]
    assert "PHANTOM" not in warnings[0] and "Anonymous" not in warnings[0]
    with pytest.raises(DsaregInputError, match="give a geometry"):
        rig_from_xa(data, build.xa(rows=H, cols=W))


def test_inconsistent_distances(build):
    dataset = pydicom.dcmread(io.BytesIO(build.xa(sid=700.0, sod=800.0)), force=True)
    with pytest.raises(DsaregInputError, match="DistanceSourceToPatient"):
        view_from_xa(dataset)


def test_enhanced_xa_functional_groups():
    """Geometry tags inside the shared / per-frame functional groups, as enhanced XA stores them."""
    dataset = Dataset()
    dataset.Rows, dataset.Columns, dataset.NumberOfFrames = H, W, 2
    shared = Dataset()
    pixel_props = Dataset()
    pixel_props.ImagerPixelSpacing = [DV, DU]
    shared.FramePixelDataPropertiesSequence = Sequence([pixel_props])
    geometry = Dataset()
    geometry.DistanceSourceToIsocenter = SOD
    geometry.DistanceSourceToDetector = SID
    shared.XRayGeometrySequence = Sequence([geometry])
    dataset.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for primary in (10.0, 25.0):
        item = Dataset()
        positioner = Dataset()
        positioner.PositionerPrimaryAngle = primary
        positioner.PositionerSecondaryAngle = -5.0
        item.PositionerPositionSequence = Sequence([positioner])
        frames.append(item)
    dataset.PerFrameFunctionalGroupsSequence = Sequence(frames)
    second, _ = view_from_xa(dataset, frame=1)
    np.testing.assert_allclose(second.world_to_view, view(25.0, -5.0).world_to_view, atol=1e-12)
    first, _ = view_from_xa(dataset, frame=0)
    np.testing.assert_allclose(first.world_to_view, view(10.0, -5.0).world_to_view, atol=1e-12)
