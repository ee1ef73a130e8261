"""XA pixel data in every transfer syntax archives hold, made here with the field's encoders (pydicom, GDCM,
DCMTK's dcmcjpeg when installed), and the modality check."""

from __future__ import annotations

import io
import shutil
import subprocess
import warnings

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian, RLELossless, generate_uid

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.image_io import read_image

XA = "1.2.840.10008.5.1.4.1.1.12.1"
MR = "1.2.840.10008.5.1.4.1.1.4"
ENHANCED_MR = "1.2.840.10008.5.1.4.1.1.4.1"
CT = "1.2.840.10008.5.1.4.1.1.2"
RF = "1.2.840.10008.5.1.4.1.1.12.2"


def _frames(bits: int, n_frames: int = 2, shape=(48, 64)) -> np.ndarray:
    """Smooth anatomy-like frames with a dark vessel, ``bits`` deep, ``(N, H, W)`` (lossy codecs keep them close)."""
    rows, columns = np.mgrid[: shape[0], : shape[1]]
    top = 2 ** bits - 1
    base = 0.55 + 0.25 * np.sin(rows / 9.0) * np.cos(columns / 13.0)
    frames = []
    for k in range(n_frames):
        frame = base.copy()
        frame[20 + k: 26 + k, 8:56] *= 0.5
        frames.append(np.round(frame * top))
    return np.asarray(frames, np.uint16 if bits > 8 else np.uint8)


def _dataset(frames: np.ndarray, bits: int, sop_class: str = XA, modality: str = "XA") -> Dataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = sop_class, generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    ds.Modality = modality
    ds.Rows, ds.Columns = frames.shape[1:]
    if len(frames) > 1:
        ds.NumberOfFrames = len(frames)
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated = 8 if bits <= 8 else 16
    ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits, bits - 1, 0
    ds.RecommendedViewingMode = ""
    ds.ImageType = ["DERIVED", "PRIMARY", "SUBTRACTION"]  # read as stored: the frames compare one to one
    ds.PixelData = frames.tobytes()
    return ds


def _bytes(ds: Dataset) -> bytes:
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _read_frame(data: bytes, frame: int = 1) -> np.ndarray:
    return read_image(data, "run.dcm", frame=frame, field_name="ap").pixels


def _close(read: np.ndarray, truth: np.ndarray, mean_tolerance: float) -> bool:
    """Equal (lossless, ``mean_tolerance`` 0) or, lossy, within ``mean_tolerance`` grey levels on average."""
    error = np.abs(read - truth.astype(np.float32))
    return bool(error.max() == 0) if mean_tolerance == 0 else bool(error.mean() <= mean_tolerance)


def _gdcm_encoded(tmp_path, frames: np.ndarray, bits: int, syntax_name: str) -> bytes:
    """The run re-encoded by GDCM's own codecs (as gdcmconv writes them)."""
    gdcm = pytest.importorskip("gdcm")
    source, target = tmp_path / "in.dcm", tmp_path / f"{syntax_name}.dcm"
    source.write_bytes(_bytes(_dataset(frames, bits)))
    reader = gdcm.ImageReader()
    reader.SetFileName(str(source))
    assert reader.Read()
    change = gdcm.ImageChangeTransferSyntax()
    change.SetTransferSyntax(gdcm.TransferSyntax(getattr(gdcm.TransferSyntax, syntax_name)))
    change.SetInput(reader.GetImage())
    assert change.Change()
    writer = gdcm.ImageWriter()
    writer.SetFileName(str(target))
    writer.SetFile(reader.GetFile())
    writer.SetImage(change.GetOutput())
    assert writer.Write()
    return target.read_bytes()


@pytest.mark.parametrize("syntax_name, uid, bits, tolerance", [
    ("JPEGBaselineProcess1", "1.2.840.10008.1.2.4.50", 8, 2),
    ("JPEGExtendedProcess2_4", "1.2.840.10008.1.2.4.51", 12, 32),  # libjpeg: error -1038 (16-bit precision)
    ("JPEGLosslessProcess14_1", "1.2.840.10008.1.2.4.70", 12, 0),
    ("JPEGLSLossless", "1.2.840.10008.1.2.4.80", 12, 0),
    ("JPEG2000Lossless", "1.2.840.10008.1.2.4.90", 12, 0),
    ("JPEG2000", "1.2.840.10008.1.2.4.91", 12, 32),
])
def test_jpeg_family_encoded_by_gdcm(tmp_path, syntax_name, uid, bits, tolerance):
    frames = _frames(bits)
    data = _gdcm_encoded(tmp_path, frames, bits, syntax_name)
    assert str(pydicom.dcmread(io.BytesIO(data)).file_meta.TransferSyntaxUID) == uid
    assert _close(_read_frame(data), frames[1], tolerance)


def test_rle_and_deflate_encoded_by_pydicom():
    frames = _frames(12)
    rle = _dataset(frames, 12)
    rle.compress(RLELossless, encoding_plugin="pydicom")
    deflated = _dataset(frames, 12)
    deflated.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    for data in (_bytes(rle), _bytes(deflated)):
        np.testing.assert_array_equal(_read_frame(data), frames[1])


@pytest.mark.skipif(shutil.which("dcmcjpeg") is None, reason="DCMTK's dcmcjpeg is not installed")
def test_jpeg_extended_12_bit_encoded_by_dcmtk(tmp_path):
    frames = _frames(12, n_frames=1)
    source, target = tmp_path / "in.dcm", tmp_path / "extended.dcm"
    source.write_bytes(_bytes(_dataset(frames, 12)))
    subprocess.run(["dcmcjpeg", "--encode-extended", str(source), str(target)], check=True, timeout=30)
    data = target.read_bytes()
    assert str(pydicom.dcmread(io.BytesIO(data)).file_meta.TransferSyntaxUID) == "1.2.840.10008.1.2.4.51"
    image = read_image(data, "run.dcm", field_name="ap")  # DCMTK maps the values to the 12 bits: DISP
    assert np.corrcoef(image.pixels.ravel(), frames[0].ravel())[0, 1] > 0.99
    assert image.reading["pixel_intensity_relationship"] == "DISP"


@pytest.mark.parametrize("sop_class, modality, named", [(MR, "MR", "MR"), (ENHANCED_MR, "MR", "MR"),
                                                         (CT, "", "CT"), (XA, "CT", "CT")])
def test_cross_sectional_frames_are_not_an_xa_run(sop_class, modality, named):
    data = _bytes(_dataset(_frames(12, n_frames=3), 12, sop_class, modality))
    with pytest.raises(DsaregInputError, match=f"is an? {named} file") as info:
        read_image(data, "series.dcm", field_name="ap")
    assert info.value.field == "ap" and "XA or RF" in info.value.accepted


def test_rf_and_secondary_capture_are_read():
    for sop_class, modality in ((RF, "RF"), ("1.2.840.10008.5.1.4.1.1.7", "OT")):
        image = read_image(_bytes(_dataset(_frames(8, n_frames=1), 8, sop_class, modality)), "rf.dcm")
        assert image.kind == "dicom-xa" and image.pixels.shape == (48, 64)


def test_pydicom_warnings_become_the_reading_s_warnings():
    ds = _dataset(_frames(8, n_frames=1), 8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.SeriesInstanceUID = "1.2.3.abc"  # not a UID: pydicom warns when it reads it
        data = _bytes(ds)
    with warnings.catch_warnings(record=True) as leaked:
        warnings.simplefilter("always")
        image = read_image(data, "ap.dcm", field_name="ap")
    assert any(w.startswith("ap: Invalid value for VR UI: '1.2.3.abc'") for w in image.warnings)
    assert not leaked


@pytest.mark.skipif(shutil.which("dcmcjpeg") is None, reason="DCMTK's dcmcjpeg is not installed")
def test_gdcm_fallback_keeps_its_native_stderr_in_the_warnings(tmp_path, monkeypatch, capfd):
    """When every pydicom plugin fails, GDCM decodes a true 12-bit JPEG extended stream; what its codec prints on
    the process's stderr ("Unsupported JPEG data precision 12") becomes a warning of the reading."""
    frames = _frames(12, n_frames=1)
    source, target = tmp_path / "in.dcm", tmp_path / "extended.dcm"
    source.write_bytes(_bytes(_dataset(frames, 12)))
    subprocess.run(["dcmcjpeg", "--encode-extended", str(source), str(target)], check=True, timeout=30)

    def no_plugin(self):
        raise RuntimeError("Unable to decode as exceptions were raised by all available plugins")

    monkeypatch.setattr(Dataset, "pixel_array", property(no_plugin))
    image = read_image(target.read_bytes(), "run.dcm", field_name="ap")
    assert np.corrcoef(image.pixels.ravel(), frames[0].ravel())[0, 1] > 0.99
    assert any(w.startswith("ap: GDCM decoded the pixel data and said: ") for w in image.warnings)
    assert "precision" not in capfd.readouterr().err
