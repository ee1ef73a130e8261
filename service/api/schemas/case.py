"""Whose case a job is (``case`` on a job and its list summary): patient, study and series of the inputs.

Taken from the inputs' DICOM headers when they are read (``dsareg_engine.io.case_identity``), stored with
the job, shown only to a caller who may see the job, never logged. Every value is untrusted text from a
file header or a client (file names): a client must show it as text, never as markup.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .closed import CLOSED

TEXT = ("Untrusted text from the inputs' DICOM headers (plain text, at most 128 characters); a list of such texts "
        "(at most 8) when the header holds several values; null when absent.")
Text = str | list[str] | None
"""A header value: one text, a list of texts for a multi-valued attribute (never one run-together string)."""


class CaseInput(BaseModel):
    """One input of the case (a role), as its DICOM header or its upload names it."""

    model_config = CLOSED

    role: Literal["ap", "lat", "volume", "mesh"] = Field(description="Which input: the AP or LAT image, the "
                                                                     "volume or the mesh.")
    file_names: list[str] = Field(default_factory=list, description="The file names given with an upload "
                                                                    "(untrusted text); empty for PACS inputs.")
    modality: Text = Field(None, description="Modality (0008,0060), e.g. XA, CT, MR. " + TEXT)
    series_number: Text = Field(None, description="Series Number (0020,0011). " + TEXT)
    series_description: Text = Field(None, description="Series Description (0008,103E). " + TEXT)
    instances: int = Field(0, ge=0, description="DICOM instances of this input (0: not DICOM).")
    carried_from: str | None = Field(
        None, description="An image not acquired for this job: a tracking job (POST …/track) sent the other plane only, "
                          "and this plane's image is an earlier run's, carried along (shown in its view, not fitted). "
                          "The id of the job it was sent with. Null: the image came with this job.")


class CaseIdentity(BaseModel):
    """Patient and study of the case (from its first DICOM input: AP, LAT, then volume) and each input."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "source": "dicomweb", "patient_name": "Doe, Jane", "patient_id": "P-0042", "study_date": "2026-11-30",
        "study_description": "Cerebral angiography", "accession_number": "A-17", "study_uid": "1.2.826.0.1.3680043.2",
        "inputs": [{"role": "ap", "file_names": [], "modality": "XA", "series_number": "3",
                    "series_description": "AP run", "instances": 1}], "mismatch": []}]})

    source: Literal["upload", "dicomweb", "dimse"] = Field(
        description="How the inputs came: uploaded, fetched from a DICOMweb server, or received over DIMSE.")
    patient_name: Text = Field(None, description="Patient's Name (0010,0010) as 'Family, Given'; its "
                                         "alphabetic, ideographic and phonetic groups joined by ' = '. " + TEXT)
    patient_id: Text = Field(None, description="Patient ID (0010,0020). " + TEXT)
    study_date: Text = Field(None, description="Study Date (0008,0020) as YYYY-MM-DD. " + TEXT)
    study_description: Text = Field(None, description="Study Description (0008,1030). " + TEXT)
    accession_number: Text = Field(None, description="Accession Number (0008,0050). " + TEXT)
    study_uid: str | None = Field(None, description="Study Instance UID (0020,000D).")
    inputs: list[CaseInput] = Field(default_factory=list, description="Per input: file names, modality, series.")
    mismatch: list[Literal["patient_id", "patient_name", "study_uid"]] = Field(
        default_factory=list, description="Attributes on which the DICOM inputs disagree (inputs of different "
                                          "patients or studies: look before trusting the case).")


def case_model(case: dict[str, Any] | None) -> CaseIdentity | None:
    """The stored case identity as its model (None for jobs without one, e.g. rows from earlier versions)."""
    return CaseIdentity(**case) if case else None
