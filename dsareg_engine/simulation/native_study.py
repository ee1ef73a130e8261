"""A synthetic study to send to a PACS: native biplane XA runs with a subtraction recipe and a CT angiography
series of the same vessel tree, one study of one obviously synthetic patient (no patient data).

The runs are generator A's (:func:`~.native_run_skull.make_skull_run`: a skull, Poisson noise, mask frames
before the contrast arrives, the Mask Subtraction Sequence a modality writes); the CT series is the one of the
DICOM phantom study (:func:`~.phantom_study.make_biplane_study`) made of the same phantom at the runs' true
pose, so dsareg registers the series to the runs and should return ``mesh_to_world``. Every instance is then
given the same patient, study and study date, and its own series number, as one examination would have.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .phantom_study import PATIENT_ID, PATIENT_NAME

STUDY_DESCRIPTION = "dsareg synthetic phantom study (not a patient)"
STUDY_ID = "DSAREG1"
RUN_SERIES = {"ap": 1, "lat": 2}
CT_SERIES = 3


@dataclass(frozen=True)
class NativeStudy:
    """The study's DICOM instances and what is true about them.

    Attributes:
        runs: ``{"ap", "lat"}`` multi-frame native XA runs (bytes).
        volume: the CT series, one instance (bytes) per slice.
        mesh_to_world: ``(4, 4)`` the true pose of the series' vessels (patient LPS mm) in the C-arm's frame.
        study_uid: the one StudyInstanceUID of every instance.
    """

    runs: dict[str, bytes]
    volume: list[bytes]
    mesh_to_world: np.ndarray
    study_uid: str


def make_native_study(seed: int = 3, size_px: int = 512, pitch_mm: float = 0.5) -> NativeStudy:
    """The study: runs ``size_px`` square (10 frames, 12 bits, LIN, AVG_SUB recipe over frames 1-2), and the CT
    series at ``pitch_mm`` isotropic of the same tree (phantom depth 3)."""
    from ..io.dicom_out import new_uid
    from .native_run_skull import SkullRunSettings, make_skull_run
    from .phantom_study import make_biplane_study

    run = make_skull_run(seed, SkullRunSettings(size_px=size_px, recipe=True))
    volume = make_biplane_study(run.mesh_to_world, image_px=64, pitch_mm=pitch_mm, depth=3, seed=seed)
    study_uid = new_uid()
    runs = {name: _into_study(_read(data), study_uid, RUN_SERIES[name]) for name, data in run.files.items()}
    _reference_each_other(runs["ap"], runs["lat"])
    for ds in runs.values():
        _complete_xa(ds)
    slices = []
    for data in volume.volume:
        ds = _into_study(_read(data), study_uid, CT_SERIES)
        ds.PatientPosition, ds.AcquisitionNumber = "HFS", 1
        slices.append(_bytes(ds))
    return NativeStudy(runs={name: _bytes(ds) for name, ds in runs.items()}, volume=slices,
                       mesh_to_world=run.mesh_to_world, study_uid=study_uid)


def _read(data: bytes):
    import pydicom

    return pydicom.dcmread(io.BytesIO(data))


def _bytes(ds) -> bytes:
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _into_study(ds, study_uid: str, series_number: int):
    """``ds`` with the study's patient, study identity and date, the equipment, and ``series_number``."""
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = PATIENT_NAME, PATIENT_ID, "", "O"
    ds.StudyInstanceUID, ds.StudyID, ds.StudyDescription = study_uid, STUDY_ID, STUDY_DESCRIPTION
    ds.StudyDate, ds.StudyTime = "20260101", "120000"
    ds.AccessionNumber, ds.ReferringPhysicianName = "", ""
    ds.SeriesNumber, ds.Laterality, ds.Manufacturer = series_number, "", "dsareg phantom"
    return ds


def _reference_each_other(a, b) -> None:
    """Each plane of a biplane acquisition references the other plane's image (Type 1C for BIPLANE A / B)."""
    from pydicom.dataset import Dataset

    for ds, other in ((a, b), (b, a)):
        item = Dataset()
        item.ReferencedSOPClassUID, item.ReferencedSOPInstanceUID = other.SOPClassUID, other.SOPInstanceUID
        ds.ReferencedImageSequence = [item]


def _complete_xa(ds) -> None:
    """The X-Ray acquisition and cine attributes a modality writes (frames indexed by the frame time)."""
    ds.FrameIncrementPointer = 0x00181063  # Frame Time
    ds.PatientOrientation, ds.PositionerMotion = "", "STATIC"
    ds.KVP, ds.RadiationSetting, ds.XRayTubeCurrent, ds.ExposureTime, ds.Exposure = 80, "GR", 400, 100, 40


def write_study(study: NativeStudy, out_dir: Path) -> list[Path]:
    """The instances as files under ``out_dir`` (``XA/AP.dcm``, ``XA/LAT.dcm``, ``CT/CT0001.dcm`` ...), the true
    pose in ``truth.json`` (not DICOM: what a registration should return); the DICOM files written."""
    out_dir = Path(out_dir)
    (out_dir / "XA").mkdir(parents=True, exist_ok=True)
    (out_dir / "CT").mkdir(exist_ok=True)
    written = []
    for name, data in study.runs.items():
        written.append(out_dir / "XA" / f"{name.upper()}.dcm")
        written[-1].write_bytes(data)
    for index, data in enumerate(study.volume, start=1):
        written.append(out_dir / "CT" / f"CT{index:04d}.dcm")
        written[-1].write_bytes(data)
    (out_dir / "truth.json").write_text(json.dumps({"mesh_to_world": study.mesh_to_world.tolist(),
                                                    "study_instance_uid": study.study_uid}, indent=2))
    return written
