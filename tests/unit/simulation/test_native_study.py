"""``dsareg phantom-study``: one study a PACS accepts (dciodvfy finds no error), native runs with a recipe and a
CT series, one patient that is obviously synthetic."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pydicom
import pytest

from dsareg_engine.cli import main


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    assert main(["phantom-study", "--out", str(out), "--size-px", "128"]) == 0
    return out


def _headers(study):
    return {path.relative_to(study).as_posix(): pydicom.dcmread(path, stop_before_pixels=True)
            for path in sorted(study.rglob("*.dcm"))}


def test_one_study_of_one_synthetic_patient_runs_with_a_recipe_and_a_ct_series(study, capsys):
    headers = _headers(study)
    assert len({ds.StudyInstanceUID for ds in headers.values()}) == 1
    assert {(str(ds.PatientName), ds.PatientID) for ds in headers.values()} == {("PHANTOM^DSAREG", "DSAREG-PHANTOM-1")}
    runs = [headers["XA/AP.dcm"], headers["XA/LAT.dcm"]]
    assert all(ds.Modality == "XA" and int(ds.NumberOfFrames) > 4 and "MaskSubtractionSequence" in ds for ds in runs)
    assert {ds.SeriesNumber for ds in runs} == {1, 2}
    ct = [ds for name, ds in headers.items() if name.startswith("CT/")]
    assert len(ct) > 20 and {ds.Modality for ds in ct} == {"CT"} and len({ds.SeriesInstanceUID for ds in ct}) == 1
    truth = json.loads((study / "truth.json").read_text())
    assert truth["study_instance_uid"] == runs[0].StudyInstanceUID and np.asarray(truth["mesh_to_world"]).shape == (4, 4)


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dciodvfy (dicom3tools) is not installed")
@pytest.mark.parametrize("name", ["XA/AP.dcm", "XA/LAT.dcm", "CT/CT0001.dcm"])
def test_dciodvfy_finds_no_error(study, name):
    report = subprocess.run(["dciodvfy", str(study / name)], capture_output=True, text=True, timeout=60)
    errors = [line for line in (report.stdout + report.stderr).splitlines() if line.startswith("Error")]
    assert not errors, errors
