"""The DICOM objects a job wrote and where they went (PACS stores, exports), as the result names them."""

from __future__ import annotations

from pydantic import BaseModel, Field

from .closed import CLOSED
from .dimse_result import DimseExport, DimseSourceInfo


class DicomInstance(BaseModel):
    """One DICOM object the job wrote (`GET …/dicom/{name}`)."""

    model_config = CLOSED

    sop_class_uid: str
    sop_instance_uid: str
    series_instance_uid: str | None = None
    study_instance_uid: str | None = None


class DicomSource(BaseModel):
    """Where the inputs of a job by reference came from."""

    model_config = CLOSED

    server: str | None = Field(None, description="The DICOMweb base URL.")
    study_uid: str | None = None
    fetch_seconds: float | None = Field(None, description="Time to fetch the inputs, seconds.")
    requests: int | None = Field(None, description="HTTP requests made to fetch them.")
    dimse: DimseSourceInfo | None = Field(None, description="Inputs that came over DIMSE: a received study, or a pull.")


class DicomStored(BaseModel):
    """What was stored back into the PACS (STOW-RS) for a job by reference with `store_results`."""

    model_config = CLOSED

    server: str | None = None
    study_uid: str | None = None
    sop_instance_uids: list[str] = Field(default_factory=list)
    confirmed: bool | None = Field(None, description="True when the PACS confirmed every instance.")
    store_seconds: float | None = None


class DicomResult(BaseModel):
    """The DICOM results: REG (model → C-arm frame) and Secondary Captures."""

    model_config = CLOSED

    instances: dict[str, DicomInstance] = Field(
        default_factory=dict, description="By file name (`reg.dcm`, `overlay_ap.dcm`, `overlay_lat.dcm`, `loss.dcm`; "
                                          "with options.hemodynamics `parametric_ap.dcm`, `parametric_lat.dcm`).")
    source: DicomSource | None = None
    stored: DicomStored | None = Field(None, description="Jobs made before the exports left the worker only: their "
                                                         "STOW-RS (now the job's `export`).")
    exported: list[DimseExport] | None = Field(None, description="Jobs made before the exports left the worker only: "
                                                                 "their C-STORE to each destination (now the job's "
                                                                 "`export`).")
