"""A native XA run pair registers end to end (no geometry file, no initial pose), with per-view frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.case import CaseFiles, load_case_files
from dsareg_engine.io.xa_run import ImageReading
from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.pipeline import run_case
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run

SIZE = 96


@pytest.fixture(scope="module")
def run():
    return make_skull_run(0, SkullRunSettings(size_px=SIZE))


@pytest.fixture(scope="module")
def files(run, tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "tree.obj"
    run.mesh.save(path)
    return CaseFiles(ap=run.files["ap"], ap_name="ap.dcm", lat=run.files["lat"], lat_name="lat.dcm",
                     mesh=path.read_bytes(), mesh_name="tree.obj")


def test_native_run_pair_registers(run, files, tmp_path):
    data = run_case(files, {}, tmp_path, dicom="off")
    pose = np.asarray(data["mesh_to_world"])
    add = mean_distance_mm(pose, run.mesh_to_world, run.mesh.vertices)
    assert add < 0.3, add
    # The 96-px native segmentation keeps background the model does not explain (23 % / 14 % of the vessel pixels at
    # the pose found): below the quarter that makes a check (registration/confidence.py, missing_uncovered)
    assert data["metrics"]["confidence"]["verdict"] == "ok", data["metrics"]["confidence"]["reasons"]
    result = json.loads((tmp_path / "result.json").read_text())
    reading = result["image_reading"]
    kinds = {d["input"]: d for d in result["input_decisions"] if d["what"] == "run kind"}
    assert set(kinds) == {"ap", "lat"}  # each view's decision reaches the result, read from the recipe tag
    assert all(d["chosen"] == "native" and d["source"] == "tag" and not d["close"] for d in kinds.values())
    for name in ("ap", "lat"):
        assert reading[name]["run"] == "native" and reading[name]["frame_index"] == run.peak_frame
        assert reading[name]["mask_frame_numbers"] == [1, 2]
        np.testing.assert_allclose(reading[name]["mask_shift_px"]["found_px"], run.motion_px[name], atol=0.1)
    assert (tmp_path / "overlay_ap.png").is_file()


def test_per_view_frames(files, run):
    case = load_case_files(files, reading=ImageReading(ap_frame=6, lat_frame="minip"))
    assert case.readings["ap"]["frame_index"] == 6 and case.readings["ap"]["combined"] == "single"
    assert case.readings["lat"]["combined"] == "minip" and case.readings["lat"]["frame_index"] == run.peak_frame
    # the files' own choice (e.g. a DICOMweb reference) and the options' must agree per view
    referenced = CaseFiles(**{**vars(files), "reading": ImageReading(ap_frame=6)})
    assert load_case_files(referenced, reading=ImageReading(lat_frame=7)).readings["lat"]["frame_index"] == 7
    with pytest.raises(DsaregInputError, match="given twice") as info:
        load_case_files(referenced, reading=ImageReading(ap_frame=7))
    assert info.value.field == "options.frames.ap"

