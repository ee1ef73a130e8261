import json

import nibabel as nib
import numpy as np
import pytest
import trimesh
from PIL import Image

from dsareg_engine.cli import main
from dsareg_engine.geometry.file import paper_rig
from dsareg_engine.io.rad import format_rad_header
from dsareg_engine.io.volume_io import RAS_TO_LPS
from dsareg_engine.simulation.phantom import make_vessel_phantom


@pytest.fixture(scope="module")
def files(tmp_path_factory, build, phantom_volume):
    folder = tmp_path_factory.mktemp("inputs")
    phantom = make_vessel_phantom(depth=1)
    trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(str(folder / "tree.stl"))
    image, _ = build.dsa()
    (folder / "dsa.png").write_bytes(build.png(image))
    (folder / "ap.dcm").write_bytes(build.xa(image.astype(np.uint16), primary=-17.0))
    volume, affine, _ = phantom_volume
    nib.save(nib.Nifti1Image(volume, RAS_TO_LPS @ affine), str(folder / "cta.nii.gz"))
    series = folder / "series"
    series.mkdir()
    for index, part in enumerate(build.ct_series(volume, affine)):
        (series / f"slice{index:03d}.dcm").write_bytes(part)
    (folder / "lat.rad").write_bytes(format_rad_header((40, 30), (0.3, 0.3), "float", np.eye(4), [6.0, 4.5, 1000.0]))
    (folder / "lat.raw").write_bytes(np.linspace(0, 1, 1200, dtype="<f4").tobytes())
    (folder / "rig.json").write_text(json.dumps(paper_rig().to_dict()))
    (folder / "noise.bin").write_bytes(b"\x01\x02" * 100)
    return folder


def test_inspect_every_kind(files, capsys):
    names = ["tree.stl", "dsa.png", "ap.dcm", "cta.nii.gz", "series", "lat.rad", "rig.json"]
    assert main(["inspect", *[str(files / n) for n in names]]) == 0
    out = capsys.readouterr().out
    assert "kind: mesh (stl)" in out and "faces: " in out
    assert "kind: image (png)" in out and "geometry: none in the file" in out
    assert "kind: image (dicom-xa)" in out and "SID 1200.0 mm" in out
    assert "kind: volume (nifti)" in out and "spacing mm: [0.5, 0.5, 0.5]" in out
    assert "kind: volume (dicom-series)" in out
    assert "kind: image (rad)" in out and "SID 1000.0 mm" in out
    assert "kind: geometry" in out and "angle between views: 90.0 deg" in out
    assert "PHANTOM" not in out and "Anonymous" not in out


def test_inspect_shows_the_unit_and_the_extent_in_mm(files, tmp_path, capsys):
    phantom = make_vessel_phantom(depth=1)
    in_metres = trimesh.Trimesh(phantom.vertices / 1000.0, phantom.faces, process=False)
    in_metres.export(str(tmp_path / "tree.glb"))
    in_metres.export(str(tmp_path / "tree_m.stl"))
    assert main(["inspect", str(tmp_path / "tree.glb"), str(tmp_path / "tree_m.stl")]) == 0
    glb, stl = capsys.readouterr().out.split("tree_m.stl:")
    extent = np.round(np.ptp(phantom.vertices, axis=0), 2).tolist()
    assert "unit: m (the format's unit)" in glb and f"extent mm: {extent}" in glb and "refused" not in glb
    assert "unit: mm (no unit in the format" in stl and "units: refused" in stl and "probably m" in stl


def test_inspect_bad_file_exits_2(files, capsys):
    assert main(["inspect", str(files / "noise.bin")]) == 2
    assert "not a recognised" in capsys.readouterr().err
    assert main(["inspect", str(files / "missing.png")]) == 2


def test_segment(files, tmp_path, capsys):
    out = tmp_path / "mask.png"
    assert main(["segment", str(files / "dsa.png"), "--out", str(out), "--method", "otsu"]) == 0
    mask = np.asarray(Image.open(out))
    assert mask.shape == (96, 128) and set(np.unique(mask)) == {0, 255}
    assert "vessel pixels" in capsys.readouterr().out
    again = tmp_path / "again.png"
    assert main(["segment", str(out), "--out", str(again)]) == 0  # a mask stays the same mask
    np.testing.assert_array_equal(np.asarray(Image.open(again)), mask)
    assert main(["segment", str(files / "ap.dcm"), "--out", str(tmp_path / "x.png"), "--frame", "two"]) == 2


def test_segment_a_real_like_angiogram_by_default(tmp_path, capsys):
    """An unsubtracted angiogram with a round field (issue 40, item 7): the default finds the vessels, not the
    field's edge ring (the old default's mask was the ring plus the background)."""
    from dsareg_engine.vision.angiogram.field_of_view import inner_field
    from tests.support.angiogram_images import unsubtracted_angiogram

    pixels, vessels, field = unsubtracted_angiogram(size=320, seed=11)
    Image.fromarray(pixels.astype(np.uint8)).save(tmp_path / "angio.png")
    assert main(["segment", str(tmp_path / "angio.png"), "--out", str(tmp_path / "mask.png")]) == 0
    mask = np.asarray(Image.open(tmp_path / "mask.png")) > 0
    assert "auto: network" in capsys.readouterr().out
    assert 2 * (mask & vessels).sum() / (mask.sum() + vessels.sum()) > 0.6
    assert (mask & field & ~inner_field(field, 4)).sum() <= 0.03 * mask.sum()


@pytest.mark.parametrize("source", ["cta.nii.gz", "series"])
def test_mesh(files, tmp_path, capsys, source):
    out = tmp_path / "vessels.obj"
    assert main(["mesh", str(files / source), "--out", str(out), "--faces", "3000"]) == 0
    mesh = trimesh.load(str(out), force="mesh")
    assert 1000 < len(mesh.faces) <= 3000
    assert "patient LPS" in capsys.readouterr().out


def test_mesh_of_an_image_fails_cleanly(files, tmp_path, capsys):
    assert main(["mesh", str(files / "dsa.png"), "--out", str(tmp_path / "m.obj")]) == 2
    assert "volume" in capsys.readouterr().err


@pytest.fixture(scope="module")
def cta_folder(tmp_path_factory):
    from dsareg_engine.simulation.synthetic_volumes import make_cta_head

    folder = tmp_path_factory.mktemp("cta")
    head = make_cta_head("a", voxel_mm=1.2, depth=2, min_head_mm=(30.0, 30.0, 40.0))
    for index, part in enumerate(head.parts):
        (folder / f"slice{index:03d}.dcm").write_bytes(part)
    return folder


def test_inspect_and_mesh_say_what_was_read_from_a_cta(cta_folder, tmp_path, capsys):
    assert main(["inspect", str(cta_folder)]) == 0
    text = capsys.readouterr().out
    assert "volume kind: cta (Modality CT with air" in text and "vessel window:" in text and "HU" in text
    kept = int(text.split("voxels kept: ")[1].split()[0])
    assert 300 < kept < 3000
    out = tmp_path / "vessels.obj"
    assert main(["mesh", str(cta_folder), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "volume: cta" in text and f"{kept} of" in text
    picture = np.asarray(Image.open(tmp_path / "vessels_mip.png"))
    red = (picture[..., 0] > 120) & (picture[..., 2] < 120) & (picture[..., 1] < 120)
    assert 200 < red.sum() < 0.2 * red.size  # the kept voxels are drawn, and only they
    # read as already subtracted (today's reading) the head is refused, with the way out named
    assert main(["mesh", str(cta_folder), "--out", str(tmp_path / "bad.obj"), "--volume-kind", "3d-dsa"]) == 2
    error = capsys.readouterr().err
    assert "far more than vessels" in error and "volume_kind" in error and "Traceback" not in error


def test_inspect_reports_every_file_and_fails_at_the_end(files, capsys):
    """A file that cannot be read says why (stderr, naming it); the next ones are still described; exit 2 at the end."""
    assert main(["inspect", str(files / "noise.bin"), str(files / "ap.dcm"), str(files / "missing.dcm")]) == 2
    captured = capsys.readouterr()
    assert "kind: image (dicom-xa)" in captured.out
    errors = captured.err.splitlines()
    assert "noise.bin: " in errors[0] and "not a recognised" in errors[0]
    assert "missing.dcm: " in errors[1] and "does not exist" in errors[1]
    assert "2 of 3 file(s) could not be read" in errors[2]


def test_inspect_shows_the_angles_when_distances_are_missing(build, tmp_path, capsys):
    image, _ = build.dsa()
    path = tmp_path / "angles.dcm"
    path.write_bytes(build.xa(image.astype(np.uint16), primary=77.0, secondary=-45.0, sid=None, sod=None, spacing=None))
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "geometry: incomplete in the file: C-arm angles primary 77.0 deg, secondary -45.0 deg" in out
    assert "missing DistanceSourceToDetector, DistanceSourceToPatient, ImagerPixelSpacing" in out
    assert "none in the file" not in out


def test_inspect_keeps_library_warnings_in_its_report(build, tmp_path, capsys):
    import io
    import warnings

    import pydicom

    image, _ = build.dsa()
    dataset = pydicom.dcmread(io.BytesIO(build.xa(image.astype(np.uint16))))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dataset.SeriesInstanceUID = "1.2.3.abc"  # not a UID: pydicom warns each time it reads it
        dataset.save_as(str(tmp_path / "bad_uid.dcm"))
    with warnings.catch_warnings(record=True) as leaked:
        warnings.simplefilter("always")
        assert main(["inspect", str(tmp_path / "bad_uid.dcm")]) == 0
    assert not leaked
    assert "warning: bad_uid.dcm: Invalid value for VR UI: '1.2.3.abc'" in capsys.readouterr().out


def test_inspect_describes_a_refused_run_as_stored(tmp_path, capsys):
    """A run registration refuses (here: the same frame 6 times, no contrast) is still described, with the reason."""
    import io

    import pydicom

    from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run

    dataset = pydicom.dcmread(io.BytesIO(make_skull_run(0, SkullRunSettings(size_px=64)).files["ap"]))
    frames = dataset.pixel_array.copy()
    frames[:] = frames[0]
    dataset.PixelData = frames.tobytes()
    dataset.save_as(str(tmp_path / "still.dcm"))
    assert main(["inspect", str(tmp_path / "still.dcm")]) == 2
    out = capsys.readouterr().out
    assert "still.dcm: (frames as stored)" in out and "kind: image (dicom-xa-multiframe)" in out
    assert "refused: " in out and "contrast" in out


def test_inspect_a_dual_personality_file_with_a_round_shutter(build, tmp_path, capsys):
    """A TIFF header in the preamble, DICM at 128: inspected as DICOM XA, its shutter named."""
    import io
    import struct

    import pydicom

    image, _ = build.dsa()
    dataset = pydicom.dcmread(io.BytesIO(build.xa(image.astype(np.uint16), primary=30.0)))
    dataset.preamble = (b"II*\x00" + struct.pack("<I", 8)).ljust(128, b"\x00")
    dataset.ShutterShape, dataset.CenterOfCircularShutter, dataset.RadiusOfCircularShutter = "CIRCULAR", [32, 40], 28
    dataset.save_as(str(tmp_path / "dual.dcm"), enforce_file_format=True)
    assert main(["inspect", str(tmp_path / "dual.dcm")]) == 0
    out = capsys.readouterr().out
    assert "kind: image (dicom-xa)" in out and "C-arm angles primary 30.0 deg" in out
    assert "field of view: shutter CIRCULAR" in out
