"""Views named by their DICOM headers: a swapped pair swapped back or refused, runs acquired minutes apart found."""

import io

import numpy as np
import pydicom
import pytest
import trimesh

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.case import load_case
from dsareg_engine.io.dicom_xa import view_from_angles
from dsareg_engine.io.image_io import read_image
from dsareg_engine.io.view_roles import RunHeader, acquisition_of, beam_obliquity_deg, run_header
from dsareg_engine.simulation.phantom import make_vessel_phantom


@pytest.fixture(scope="module")
def mesh_bytes():
    phantom = make_vessel_phantom(depth=1)
    return trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(file_type="stl")


def _xa(build, primary: float, *, seed: int = 0, image_type=None, time: str | None = None, frame: str | None = None):
    image, _ = build.dsa(height=64, width=80, seed=seed)
    dataset = pydicom.dcmread(io.BytesIO(build.xa(image.astype(np.uint16), primary=primary)))
    if image_type is not None:
        dataset.ImageType = image_type
    if time is not None:
        dataset.AcquisitionDate, dataset.AcquisitionTime = "20260102", time
    if frame is not None:
        dataset.FrameOfReferenceUID = frame
    buffer = io.BytesIO()
    dataset.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _decision(case, what):
    return next(d for d in case.decisions if d.what == what)


@pytest.mark.parametrize("primary, secondary", [(0.0, 0.0), (88.0, -2.0), (-30.0, 20.0), (135.0, 10.0), (-100.0, -25.0)])
def test_obliquity_is_the_axial_angle_from_the_anterior_posterior_axis(primary, secondary):
    view = view_from_angles(primary, secondary, 1200.0, 800.0, (0.3, 0.3), (64, 64))
    # independent: the source sits on the patient's posterior side at AP and turns about the head-foot axis by
    # the primary angle, so the beam's axial direction is (sin α, −cos α) up to its length: |α| folded to 0–90°
    folded = abs((primary + 90.0) % 180.0 - 90.0)
    assert beam_obliquity_deg(view) == pytest.approx(folded, abs=1e-9)


def test_a_swapped_pair_is_swapped_back_and_named_by_what_each_file_is(build, mesh_bytes):
    lateral = _xa(build, 88.0, seed=1, image_type=["ORIGINAL", "PRIMARY", "BIPLANE B"])
    frontal = _xa(build, 4.0, seed=2, image_type=["ORIGINAL", "PRIMARY", "BIPLANE A"])
    case = load_case(mesh=mesh_bytes, mesh_name="tree.stl", ap=lateral, ap_name="ap.dcm", lat=frontal, lat_name="lat.dcm")
    decision = _decision(case, "view roles")
    assert decision.chosen == "swapped" and decision.measure == pytest.approx(84.0)
    assert beam_obliquity_deg(case.rig.views["ap"]) == pytest.approx(4.0)
    assert beam_obliquity_deg(case.rig.views["lat"]) == pytest.approx(88.0)
    np.testing.assert_array_equal(case.images["ap"], read_image(frontal, "lat.dcm").pixels)
    assert case.sources.ap.sop_instance_uid == pydicom.dcmread(io.BytesIO(frontal)).SOPInstanceUID
    assert any("swapped" in w for w in case.warnings)


def test_an_ambiguous_swap_is_refused_unless_the_planes_confirm_the_roles(build, mesh_bytes):
    with pytest.raises(DsaregInputError, match="swapped") as info:
        load_case(mesh=mesh_bytes, mesh_name="tree.stl", ap=_xa(build, 50.0), lat=_xa(build, 20.0))
    assert info.value.field == "ap"
    case = load_case(mesh=mesh_bytes, mesh_name="tree.stl",
                     ap=_xa(build, 50.0, image_type=["ORIGINAL", "PRIMARY", "BIPLANE A"]),
                     lat=_xa(build, 20.0, image_type=["ORIGINAL", "PRIMARY", "BIPLANE B"]))
    assert _decision(case, "view roles").chosen.startswith("as given")


def test_oblique_and_given_geometry_pairs_keep_their_roles(build, mesh_bytes):
    case = load_case(mesh=mesh_bytes, mesh_name="tree.stl", ap=_xa(build, -20.0), lat=_xa(build, 20.0))
    assert _decision(case, "view roles").chosen == "as given" and case.acquisition is None


def test_runs_minutes_apart_are_sequential(build, mesh_bytes):
    single = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    case = load_case(mesh=mesh_bytes, mesh_name="tree.stl", ap=_xa(build, 2.0, image_type=single, time="101500"),
                     lat=_xa(build, 91.0, image_type=single, time="101705"))
    assert case.acquisition.sequential and case.acquisition.interval_s == pytest.approx(125.0)
    assert "10:15:00" in case.acquisition.basis and _decision(case, "acquisition").chosen == "sequential runs"
    header = run_header(read_image(_xa(build, 2.0, image_type=single, time="101500", frame="1.2.3"), "ap.dcm").dicom)
    assert header.plane == "single" and header.frame_uid == "1.2.3"


def test_biplane_planes_firing_together_are_not_sequential_and_frames_of_reference_count():
    start = pydicom.valuerep.DT("20260102101500").replace(tzinfo=None)
    together, _ = acquisition_of({"ap": RunHeader("A", start), "lat": RunHeader("B", start)})
    assert not together.sequential
    apart, decisions = acquisition_of({"ap": RunHeader("single", None, "1.2.3"), "lat": RunHeader("single", None, "1.2.4")})
    assert apart.sequential and decisions[0].chosen == "sequential runs"
    assert acquisition_of({"ap": RunHeader("single"), "lat": RunHeader("single")}) == (None, [])


def test_times_without_their_dates_count_by_time_of_day(build):
    single = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    files = []
    for primary, time in ((2.0, "101500"), (91.0, "102500.5")):
        dataset = pydicom.dcmread(io.BytesIO(_xa(build, primary, image_type=single)))
        dataset.ContentTime = time  # no date anywhere
        buffer = io.BytesIO()
        dataset.save_as(buffer, enforce_file_format=True)
        files.append(read_image(buffer.getvalue(), "run.dcm").dicom)
    dated = RunHeader("single", pydicom.valuerep.DT("20260102101600").replace(tzinfo=None))
    acquisition, _ = acquisition_of({"ap": run_header(files[0]), "lat": run_header(files[1])})
    assert acquisition.sequential and acquisition.interval_s == pytest.approx(600.5)
    assert acquisition_of({"ap": run_header(files[0]), "lat": dated})[0].interval_s == pytest.approx(60.0)
