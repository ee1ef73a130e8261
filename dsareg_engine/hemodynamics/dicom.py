"""The parametric maps as DICOM Secondary Capture instances, in the inputs' study (when DICOM outputs are on)."""

from __future__ import annotations

from pathlib import Path

import cv2

from ..artifacts import parametric_dcm, parametric_png
from ..io.dicom_identity import DicomSources
from ..io.dicom_out import build_secondary_capture, new_uid, study_uid_for, to_bytes

VIEWS = ("ap", "lat")
SERIES_NUMBER = 9104


def derivation(view: str) -> str:
    return (f"dsareg parametric map of the {view.upper()} run: each pixel coloured by its contrast arrival time "
            "(half-peak rise), colour bar in seconds")


def write_parametric_dicom(out_dir: Path, sources: DicomSources, dicom_dir: Path | None = None
                           ) -> dict[str, dict[str, str]]:
    """``parametric_{ap,lat}.dcm`` from the PNGs in ``out_dir`` (one new series, written to ``dicom_dir``, default
    ``out_dir``); their identities by file name."""
    out_dir = Path(out_dir)
    dicom_dir = Path(dicom_dir) if dicom_dir is not None else out_dir
    study_uid = study_uid_for(sources)
    series_uid = new_uid()
    written: dict[str, dict[str, str]] = {}
    for number, view in enumerate(VIEWS, start=1):
        png = out_dir / parametric_png(view)
        if not png.is_file():
            continue
        rgb = cv2.cvtColor(cv2.imread(str(png), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        ds = build_secondary_capture(rgb, sources, study_uid=study_uid, series_uid=series_uid, instance_number=number,
                                     derivation=derivation(view))
        ds.SeriesNumber, ds.SeriesDescription = SERIES_NUMBER, "dsareg hemodynamics parametric maps"
        (dicom_dir / parametric_dcm(view)).write_bytes(to_bytes(ds))
        written[parametric_dcm(view)] = {"sop_class_uid": str(ds.SOPClassUID), "sop_instance_uid": str(ds.SOPInstanceUID),
                                         "series_instance_uid": str(ds.SeriesInstanceUID), "study_instance_uid": study_uid}
    return written
