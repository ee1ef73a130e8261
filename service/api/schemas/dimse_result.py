"""``result.dicom`` of a job whose inputs came over DIMSE: where from (``source.dimse``) and where its results
went by C-STORE (``exported``). Written by service/pacs/dimse/export.py (a study the node received),
service/pacs/dimse/pull.py (a pull by reference) and service/pacs/dimse/submit.py (the job's source document).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from .closed import CLOSED


class DimseImageRef(BaseModel):
    model_config = CLOSED

    series_uid: str | None = Field(None, description="Series Instance UID.")
    sop_instance_uid: str | None = Field(None, description="SOP Instance UID of the image used.")


class DimseVolumeOrigin(BaseModel):
    """A volume not in the study: the patient's latest, found by C-FIND and retrieved by C-MOVE."""

    model_config = CLOSED

    peer: str = Field(description="AE title of the query peer (DSAREG_DICOM_QUERY_PEER).")
    study_uid: str = Field(description="The study the volume came from.")
    modality: str = Field(description="CT, MR or XA (3D-RA).")
    study_date: str = Field("", description="Its Study Date (DA), as the peer answered it.")


class DimseVolumeSource(BaseModel):
    model_config = CLOSED

    series_uid: str | None = Field(None, description="Series Instance UID of the volume series.")
    instances: int | None = Field(None, description="Instances (slices, or one multi-frame) used.")
    retrieved: DimseVolumeOrigin | None = Field(None, description="Only for a volume retrieved from the query peer.")


class DimseSourceInfo(BaseModel):
    """A study received by the node (``calling_ae`` … ``volume``) or inputs pulled from a peer (``peer`` …)."""

    model_config = CLOSED

    calling_ae: str | None = Field(None, description="AE title of the peer that sent the study.")
    study_uid: str | None = Field(None, description="Study Instance UID.")
    pairing: str | None = Field(None, description="The rule that paired AP and LAT (docs/pacs/dimse.md).")
    ap: DimseImageRef | None = None
    lat: DimseImageRef | None = None
    volume: DimseVolumeSource | None = None
    peer: str | None = Field(None, description="Pull by reference: the peer's AE title.")
    retrieve: Literal["move", "get"] | None = Field(None, description="Pull by reference: C-MOVE or C-GET.")
    fetch_seconds: float | None = Field(None, description="Pull by reference: time to fetch the inputs, seconds.")
    instances: int | None = Field(None, description="Pull by reference: instances fetched.")


class DimseExportError(BaseModel):
    model_config = CLOSED

    type: str = Field(description="The pacs-error problem type.")
    peer: str = Field(description="AE title of the destination.")
    step: str = Field(description="configuration, associate or C-STORE.")
    status: int | None = Field(None, description="The DIMSE status, when the peer answered one.")
    detail: str = Field(description="What failed, in words.")


class DimseExport(BaseModel):
    """One destination's C-STORE of the results (service/pacs/dimse/export.py)."""

    model_config = CLOSED

    peer: str = Field(description="AE title of the destination.")
    host: str | None = None
    port: int | None = None
    status: Literal["stored", "failed"]
    attempts: int = Field(description="Associations tried (1 + retries used).")
    sop_instance_uids: list[str] = Field(default_factory=list, description="Stored, as the peer confirmed.")
    seconds: float | None = Field(None, description="Time of the export, seconds.")
    error: DimseExportError | None = None
