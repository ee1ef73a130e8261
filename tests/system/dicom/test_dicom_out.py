"""DICOM out: the Spatial Registration object and the Secondary Capture overlays."""

from __future__ import annotations

import io
import json

import numpy as np
import pydicom
import pytest
from PIL import Image

from dsareg_engine.geometry.pose import make_transform
from dsareg_engine.io.dicom_out import (
    REG_SOP_CLASS,
    SC_SOP_CLASS,
    DicomSources,
    read_registration_matrix,
    read_sources,
    write_dicom_outputs,
)


def _random_rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return make_transform(q, rng.uniform(-900, 900, 3))


def _pngs(folder, size=(48, 64)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in ("overlay_ap", "overlay_lat", "loss"):
        Image.fromarray(rng.integers(0, 255, (*size, 3), dtype=np.uint8)).save(folder / f"{name}.png")


def test_reg_and_overlays_validate_and_reference_the_study(study, dciodvfy, tmp_path):
    _pngs(tmp_path)
    pose = _random_rigid(1)
    sources = read_sources(study.ap, study.lat, study.volume)
    written = write_dicom_outputs(tmp_path, pose, sources, tmp_path / "dicom")
    assert set(written) == {"reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm"}
    for name in written:
        assert dciodvfy(tmp_path / "dicom" / name) == [], name

    reg = pydicom.dcmread(tmp_path / "dicom" / "reg.dcm")
    assert reg.SOPClassUID == REG_SOP_CLASS and reg.Modality == "REG"
    assert reg.StudyInstanceUID == study.study_uid  # joins the source study
    assert (reg.PatientName, reg.PatientID) == ("PHANTOM^DSAREG", "DSAREG-PHANTOM-1")  # copied, not invented
    # the volume's frame registered into the C-arm frame of this instance, then the XA images in that frame
    item, xa_item = reg.RegistrationSequence
    assert xa_item.FrameOfReferenceUID == reg.FrameOfReferenceUID
    assert [r.ReferencedSOPInstanceUID for r in xa_item.ReferencedImageSequence] == [
        pydicom.dcmread(io.BytesIO(x)).SOPInstanceUID for x in (study.ap, study.lat)]
    np.testing.assert_array_equal(read_registration_matrix(reg, reg.FrameOfReferenceUID), np.eye(4))
    assert item.FrameOfReferenceUID == study.uids["volume_frame"] != reg.FrameOfReferenceUID
    matrix = item.MatrixRegistrationSequence[0].MatrixSequence[0]
    assert matrix.FrameOfReferenceTransformationMatrixType == "RIGID"
    np.testing.assert_allclose(read_registration_matrix(reg, study.uids["volume_frame"]), pose, rtol=0, atol=1e-9)
    assert len(item.ReferencedImageSequence) == len(study.volume)
    series = {s.SeriesInstanceUID: len(s.ReferencedInstanceSequence) for s in reg.ReferencedSeriesSequence}
    assert series == {study.uids["ap_series"]: 1, study.uids["lat_series"]: 1, study.uids["volume_series"]: len(study.volume)}
    assert reg.ContentLabel and reg.ContentDescription

    for view in ("ap", "lat"):
        sc = pydicom.dcmread(tmp_path / "dicom" / f"overlay_{view}.dcm")
        assert sc.SOPClassUID == SC_SOP_CLASS and sc.StudyInstanceUID == study.study_uid
        assert sc.PatientID == "DSAREG-PHANTOM-1"
        np.testing.assert_array_equal(sc.pixel_array, np.asarray(Image.open(tmp_path / f"overlay_{view}.png")))
    # the C-arm frame is stable for one XA pair (every registration of it shares the frame)
    again = write_dicom_outputs(tmp_path, pose, sources, tmp_path / "again")
    assert pydicom.dcmread(tmp_path / "again" / "reg.dcm").FrameOfReferenceUID == reg.FrameOfReferenceUID
    assert again["reg.dcm"]["sop_instance_uid"] != written["reg.dcm"]["sop_instance_uid"]


@pytest.mark.parametrize("seed", range(5))
def test_matrix_round_trip_is_exact(seed, tmp_path):
    pose = _random_rigid(seed)
    pose[:3, 3] *= 10.0 ** (seed - 2)  # 0.01 mm … 100 m translations
    write_dicom_outputs(tmp_path, pose, DicomSources(), tmp_path)
    back = read_registration_matrix(pydicom.dcmread(tmp_path / "reg.dcm"))
    np.testing.assert_allclose(back, pose, rtol=0, atol=1e-9 * max(1.0, np.abs(pose).max() / 1000))


def test_mesh_model_reg_references_the_xa_images(study, dciodvfy, tmp_path):
    """A mesh model (no DICOM volume): every instance in Common Instance Reference is referenced (dciodvfy 0 errors)."""
    _pngs(tmp_path)
    pose = _random_rigid(3)
    write_dicom_outputs(tmp_path, pose, read_sources(study.ap, study.lat, None), tmp_path / "dicom")
    for name in ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm"):
        assert dciodvfy(tmp_path / "dicom" / name) == [], name
    reg = pydicom.dcmread(tmp_path / "dicom" / "reg.dcm")
    model_item, xa_item = reg.RegistrationSequence
    assert "ReferencedImageSequence" not in model_item
    np.testing.assert_allclose(read_registration_matrix(reg, model_item.FrameOfReferenceUID), pose, rtol=0, atol=1e-9)
    referenced = {r.ReferencedSOPInstanceUID for r in xa_item.ReferencedImageSequence}
    listed = {i.ReferencedSOPInstanceUID for s in reg.ReferencedSeriesSequence for i in s.ReferencedInstanceSequence}
    assert referenced == listed and len(listed) == 2


def test_overlay_derivation_names_the_drawn_colours(study, tmp_path):
    """The Secondary Capture's Derivation Description names the colours the contours really have."""
    from dsareg_engine.overlay import overlay_image

    mask = np.zeros((80, 80), bool)
    mask[20:60, 30:50] = True
    initial, final = np.roll(mask, 12, axis=1), mask.copy()
    bgr = overlay_image(mask, initial, None, box=False, min_side=1)
    rgb_initial = bgr[:80, :, ::-1].reshape(-1, 3).astype(int)
    bgr = overlay_image(mask, None, final, box=False, min_side=1)
    rgb_final = bgr[:80, :, ::-1].reshape(-1, 3).astype(int)

    def coloured(rgb):  # the contour pixels: far from grey
        return rgb[(rgb.max(axis=1) - rgb.min(axis=1)) > 80].mean(axis=0)

    r, g, b = coloured(rgb_initial)
    assert b > r + 80 and b > g  # blue
    r, g, b = coloured(rgb_final)
    assert r > g + 60 > b + 60  # orange: red high, green half, little blue
    _pngs(tmp_path)
    write_dicom_outputs(tmp_path, np.eye(4), read_sources(study.ap, study.lat, None), tmp_path / "d")
    for view in ("ap", "lat"):
        text = pydicom.dcmread(tmp_path / "d" / f"overlay_{view}.dcm").DerivationDescription
        assert "initial (blue)" in text and "registered (orange)" in text and "not fitted" not in text, text
    # a single-plane track of AP (issue 42): the LAT overlay shows an earlier run's image and says so
    write_dicom_outputs(tmp_path, np.eye(4), read_sources(study.ap, study.lat, None), tmp_path / "t", unfitted=("lat",))
    text = pydicom.dcmread(tmp_path / "t" / "overlay_lat.dcm").DerivationDescription
    assert "not fitted" in text and "earlier run's, not this run's" in text and len(text) <= 1024, text
    assert "not fitted" not in pydicom.dcmread(tmp_path / "t" / "overlay_ap.dcm").DerivationDescription


def test_without_dicom_inputs_nothing_is_invented(dciodvfy, tmp_path):
    _pngs(tmp_path)
    write_dicom_outputs(tmp_path, np.eye(4), read_sources(b"\x89PNG" + b"0" * 200, b"", None), tmp_path / "d")
    for name in ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"):
        assert dciodvfy(tmp_path / "d" / name) == [], name
        ds = pydicom.dcmread(tmp_path / "d" / name)
        assert ds.PatientName == "" and ds.PatientID == "" and ds.StudyInstanceUID.startswith("2.25.")
    reg = pydicom.dcmread(tmp_path / "d" / "reg.dcm")
    assert reg.RegistrationSequence[0].FrameOfReferenceUID != reg.FrameOfReferenceUID


def test_cli_register_volume_with_dicom_out(study, tmp_path, capsys):
    import shutil
    import subprocess

    from dsareg_engine.cli import main

    series = tmp_path / "cta"
    series.mkdir()
    for index, part in enumerate(study.volume):
        (series / f"{index:03d}.dcm").write_bytes(part)
    (tmp_path / "ap.dcm").write_bytes(study.ap)
    (tmp_path / "lat.dcm").write_bytes(study.lat)
    (tmp_path / "truth.json").write_text(json.dumps({"mesh_to_world": study.mesh_to_world.tolist()}))
    code = main(["register", "--volume", str(series), "--ap", str(tmp_path / "ap.dcm"), "--lat", str(tmp_path / "lat.dcm"),
                 "--ground-truth", str(tmp_path / "truth.json"), "--options", '{"starts": 1}',
                 "--out", str(tmp_path / "out"), "--dicom-out", str(tmp_path / "dicom")])
    assert code == 0
    assert "DICOM: " in capsys.readouterr().err  # notes go to stderr, the summary to stdout
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["metrics"]["ground_truth"]["add_mm"] < 0.5
    for name in ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm"):
        if shutil.which("dciodvfy"):  # validated here when installed; this test also runs without it
            done = subprocess.run(["dciodvfy", str(tmp_path / "dicom" / name)], check=False, capture_output=True,
                                  text=True, timeout=60)
            assert not [x for x in (done.stdout + done.stderr).splitlines() if x.startswith("Error")], name
    reg = pydicom.dcmread(tmp_path / "dicom" / "reg.dcm")
    matrix = read_registration_matrix(reg, study.uids["volume_frame"])
    np.testing.assert_allclose(matrix, np.asarray(result["mesh_to_world"]), rtol=0, atol=1e-9)
    rotation = np.degrees(np.arccos(np.clip((np.trace(matrix[:3, :3].T @ study.mesh_to_world[:3, :3]) - 1) / 2, -1, 1)))
    assert rotation < 1.0


def test_no_object_sent_back_carries_an_empty_laterality(tmp_path):
    """dciodvfy warned on every returned object: "Laterality … should be absent (not empty) if an unpaired body
    part" (head arteries are unpaired). dciodvfy's own word on it when installed."""
    import shutil
    import subprocess

    _pngs(tmp_path)
    written = write_dicom_outputs(tmp_path, _random_rigid(4), DicomSources(), tmp_path / "dicom")
    for name in written:
        assert "Laterality" not in pydicom.dcmread(tmp_path / "dicom" / name), name
    if (tool := shutil.which("dciodvfy")) is not None:
        for name in written:
            done = subprocess.run([tool, str(tmp_path / "dicom" / name)], capture_output=True, text=True, timeout=60,
                                  check=False)
            assert "Laterality" not in done.stdout + done.stderr, (name, done.stderr)
