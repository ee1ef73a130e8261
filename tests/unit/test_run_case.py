"""run_case: files in, every output out, the warnings joined once (what the service's workers call)."""

import json

import pytest
import trimesh

from dsareg_engine.geometry.spec import parse_geometry
from dsareg_engine.io.case import CaseFiles
from dsareg_engine.pipeline import RegistrationCanceled, run_case
from dsareg_engine.simulation.phantom import make_vessel_phantom

QUICK = {"starts": 1, "max_iterations": 5, "mirror_check": False}  # the images are not of the mesh: no mirror fit


@pytest.fixture(scope="module")
def files(build):
    phantom = make_vessel_phantom(depth=2)
    mesh = trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(file_type="stl")
    image, _ = build.dsa(height=100, width=100)
    png = build.png(image)
    return CaseFiles(ap=png, ap_name="ap.png", lat=png, lat_name="lat.png", mesh=mesh, mesh_name="tree.stl",
                     geometry=parse_geometry("paper"), warnings=("fetched: the first of 3 instances was used",))


def test_the_warnings_join_the_result_once_and_result_json_has_them(files, tmp_path):
    events = []
    data = run_case(files, QUICK, tmp_path, progress=events.append, dicom="off")
    warnings = data["warnings"]
    assert warnings[0] == files.warnings[0]  # the fetch's notes first, then the case's
    assert sum("rescaled" in w for w in warnings) == 2  # the 800-px preset on 100-px images, once per view
    assert len(warnings) == len(set(warnings))
    assert json.loads((tmp_path / "result.json").read_text())["warnings"] == warnings
    assert events[0]["stage"] == "start" and "dicom" not in data


def test_dicom_results_are_written_and_listed(files, tmp_path):
    data = run_case(files, QUICK, tmp_path, dicom="required")
    assert {"reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"} <= set(data["dicom"]["instances"])
    assert (tmp_path / "reg.dcm").is_file()


def test_a_stop_before_the_start_cancels(files, tmp_path):
    with pytest.raises(RegistrationCanceled):
        run_case(files, QUICK, tmp_path, should_stop=lambda: True)
    assert not (tmp_path / "result.json").exists()


# ---- the DICOM inputs are parsed once (issue 25) -------------------------------------------------------------

@pytest.fixture(scope="module")
def dicom_files():
    """A DICOM XA pair and a DICOM CT series of the synthetic phantom study (no patient data)."""
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    study = make_biplane_study(image_px=96, pixel_spacing_mm=1.4, depth=2)
    return CaseFiles(ap=study.ap, ap_name="ap.dcm", lat=study.lat, lat_name="lat.dcm", volume=list(study.volume))


def test_each_dicom_input_is_parsed_once_in_a_registration(dicom_files, tmp_path, monkeypatch):
    """Each XA run is parsed once; each slice of the volume's series twice: its header (the series is chosen and
    ordered from the headers alone) and then its pixels, so that the files are never all held at once."""
    import pydicom

    parsed: list[tuple[bytes, bool]] = []
    real = pydicom.dcmread

    def counting(source, *args, **kwargs):
        data = source.getvalue() if hasattr(source, "getvalue") else bytes(source)
        parsed.append((data, bool(kwargs.get("stop_before_pixels"))))
        return real(source, *args, **kwargs)

    monkeypatch.setattr(pydicom, "dcmread", counting)
    data = run_case(dicom_files, QUICK, tmp_path, dicom="required")
    assert {"reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"} <= set(data["dicom"]["instances"])
    runs, slices = [dicom_files.ap, dicom_files.lat], list(dicom_files.volume)

    def counts(given, header_only):
        return [sum(one == item and only == header_only for one, only in parsed) for item in given]

    assert counts(runs, False) == [1, 1] and counts(runs, True) == [0, 0], "parses per XA run"
    assert counts(slices, True) == [1] * len(slices), "header parses per slice"
    assert counts(slices, False) == [1] * len(slices), "full parses per slice"
    assert len(parsed) == len(runs) + 2 * len(slices)  # and nothing else is parsed again
