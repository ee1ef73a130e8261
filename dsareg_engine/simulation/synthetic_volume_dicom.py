"""The DICOM series of the synthetic heads (:mod:`dsareg_engine.simulation.synthetic_volumes`), in two tag layouts.

Variant "a" and "b" differ as two vendors' series do: slice order and orientation, pixel representation,
rescale, and which identifying tags are present (Contrast/Bolus Agent, Angio Flag, sequence names).
"""

from __future__ import annotations

import numpy as np

CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"
MR_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.4"


def _slice_dataset(sop_class: str, series_uid: str, frame_uid: str, study_uid: str, modality: str, number: int):
    from ..io.dicom_out import new_instance, new_uid

    ds = new_instance(sop_class, new_uid(), charset="ISO_IR 100")
    from .phantom_study import PATIENT_ID, PATIENT_NAME

    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = PATIENT_NAME, PATIENT_ID, "", "O"
    ds.StudyInstanceUID, ds.StudyDate, ds.StudyTime, ds.StudyID = study_uid, "20260101", "120000", "DSAREG1"
    ds.AccessionNumber, ds.ReferringPhysicianName = "", ""
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.Modality, ds.InstanceNumber = series_uid, 3, modality, number
    ds.FrameOfReferenceUID, ds.PositionReferenceIndicator = frame_uid, ""
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    return ds


def _write_slices(data: np.ndarray, affine: np.ndarray, slice_axis: int, make, store, reverse: bool) -> list[bytes]:
    """One file per slice along ``slice_axis``; ``make(k)`` gives the dataset, ``store(plane)`` its pixels."""
    import io

    axes = [a for a in range(3) if a != slice_axis]  # the in-plane (column index, row index) axes
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    row_dir, col_dir = affine[:3, axes[0]] / spacing[axes[0]], affine[:3, axes[1]] / spacing[axes[1]]
    order = range(data.shape[slice_axis] - 1, -1, -1) if reverse else range(data.shape[slice_axis])
    parts = []
    for number, k in enumerate(order):
        plane = np.take(data, k, axis=slice_axis)  # [column index, row index]
        ds = make(number + 1)
        index = np.zeros(3)
        index[slice_axis] = k
        ds.ImagePositionPatient = [round(float(x), 5) for x in affine[:3, :3] @ index + affine[:3, 3]]
        ds.ImageOrientationPatient = [round(float(x), 6) for x in (*row_dir, *col_dir)]
        ds.PixelSpacing = [float(spacing[axes[1]]), float(spacing[axes[0]])]
        ds.SliceThickness = float(spacing[slice_axis])
        ds.Rows, ds.Columns = plane.shape[1], plane.shape[0]
        ds.PixelData = store(plane.T)
        buffer = io.BytesIO()
        ds.save_as(buffer, enforce_file_format=True)
        parts.append(buffer.getvalue())
    return parts


def cta_series(data: np.ndarray, affine: np.ndarray, variant: str) -> tuple[list[bytes], np.ndarray, np.ndarray, str]:
    """CT slices in HU; returns the files and the voxels as stored (HU after quantization)."""
    from ..io.dicom_out import new_uid

    study_uid, series_uid, frame_uid = new_uid(), new_uid(), new_uid()
    if variant == "a":  # unsigned + intercept −1024, ascending, Contrast/Bolus Agent present
        stored = np.clip(np.round(data + 1024.0), 0, 65535)
        quantized = stored - 1024.0
    else:  # signed, no intercept, descending, no contrast tag
        stored = np.clip(np.round(data), -32768, 32767)
        quantized = stored

    def make(number: int):
        ds = _slice_dataset(CT_SOP_CLASS, series_uid, frame_uid, study_uid, "CT", number)
        ds.RescaleSlope, ds.RescaleType = 1, "HU"
        if variant == "a":
            ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
            ds.SeriesDescription, ds.ContrastBolusAgent = "CTA head", "Iodinated contrast"
            ds.RescaleIntercept, ds.PixelRepresentation = -1024, 0
        else:
            ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "HELIX"]
            ds.SeriesDescription = "Head angio 0.8"
            ds.RescaleIntercept, ds.PixelRepresentation = 0, 1
        ds.KVP = 120
        return ds

    dtype = "<u2" if variant == "a" else "<i2"
    parts = _write_slices(stored, affine, 2, make, lambda plane: plane.astype(dtype).tobytes(), reverse=variant == "b")
    return parts, quantized.astype(np.float32), affine, study_uid


def mra_series(data: np.ndarray, affine: np.ndarray, variant: str) -> tuple[list[bytes], np.ndarray, np.ndarray, str]:
    """MR slices (axial for "a", sagittal for "b" with a rescale slope); the files and the voxels as stored."""
    from ..io.dicom_out import new_uid

    study_uid, series_uid, frame_uid = new_uid(), new_uid(), new_uid()
    slope = 1.0 if variant == "a" else 0.5
    stored = np.clip(np.round(data / slope), 0, 65535)

    def make(number: int):
        ds = _slice_dataset(MR_SOP_CLASS, series_uid, frame_uid, study_uid, "MR", number)
        ds.PixelRepresentation = 0
        ds.MRAcquisitionType, ds.ScanningSequence = "3D", "GR"
        if variant == "a":
            ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "ND"]
            ds.SeriesDescription, ds.SequenceName, ds.AngioFlag = "tof_fl3d_tra", "*fl3d1r_t70", "Y"
        else:
            ds.ImageType = ["ORIGINAL", "PRIMARY", "OTHER"]
            ds.SeriesDescription = "Head 3D T1 FFE"
            ds.RescaleSlope, ds.RescaleIntercept = slope, 0
        return ds

    parts = _write_slices(stored, affine, 2 if variant == "a" else 0, make,
                          lambda plane: plane.astype("<u2").tobytes(), reverse=False)
    return parts, (stored * slope).astype(np.float32), affine, study_uid
