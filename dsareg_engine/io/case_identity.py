"""Whose case it is: the patient, study and series of a case's inputs, for the person who reviews it.

:func:`case_identity` turns the :class:`~.dicom_identity.DicomSources` the readers kept (one parse,
never again) into plain JSON: patient name and ID, study date, description and accession number, the
modality and series of each input, the file names given for uploads and the source (``upload``,
``dicomweb`` or ``dimse``). ``mismatch`` names the attributes on which the DICOM inputs disagree
(an AP of one patient with a LAT of another is the first thing a reviewer must see).

Every value is untrusted text from a file header: it is kept as text, cut to :data:`MAX_TEXT`
characters with control characters removed, and never interpreted. :func:`case_search_text` is what a list
is searched by (patient ID and name, study date, description and accession), lower-cased.
"""

from __future__ import annotations

from typing import Any

from .dicom_identity import DicomIdentity, DicomSources

SOURCES = ("upload", "dicomweb", "dimse")
MAX_TEXT = 128
ROLES = ("ap", "lat", "volume", "mesh")
COMPARED = ("patient_id", "patient_name", "study_uid")
"""Attributes that must agree across the DICOM inputs of one case (``mismatch`` names those that do not)."""


def clean_text(value: Any) -> str | None:
    """A header value as bounded plain text: control characters dropped, at most :data:`MAX_TEXT` characters."""
    if value is None:
        return None
    text = "".join(ch if ch.isprintable() else " " for ch in str(value)).strip()
    return text[:MAX_TEXT] or None


def person_name(value: Any) -> str | None:
    """A DICOM PN (``Family^Given^Middle^Prefix^Suffix``) as ``Family, Given Middle``."""
    text = clean_text(value)
    if text is None or "^" not in text:
        return text
    family, *rest = [part.strip() for part in text.split("=")[0].split("^")]
    given = " ".join(part for part in rest[:2] if part)
    return f"{family}, {given}" if family and given else (family or given or None)


def dicom_date(value: Any) -> str | None:
    """``YYYYMMDD`` as ``YYYY-MM-DD``; anything else as given (clean text)."""
    text = clean_text(value)
    if text and len(text) == 8 and text.isdigit():
        return f"{text[:4]}-{text[4:6]}-{text[6:]}"
    return text


def _attrs(identity: DicomIdentity) -> dict[str, Any]:
    return {**dict(identity.patient), **dict(identity.study), **dict(identity.series)}


def _patient_and_study(identity: DicomIdentity | None) -> dict[str, str | None]:
    attrs = _attrs(identity) if identity else {}
    return {"patient_name": person_name(attrs.get("PatientName")), "patient_id": clean_text(attrs.get("PatientID")),
            "study_date": dicom_date(attrs.get("StudyDate")),
            "study_description": clean_text(attrs.get("StudyDescription")),
            "accession_number": clean_text(attrs.get("AccessionNumber")),
            "study_uid": clean_text(identity.study_instance_uid) if identity else None}


def _input(role: str, identities: list[DicomIdentity], names: list[str]) -> dict[str, Any]:
    attrs = _attrs(identities[0]) if identities else {}
    return {"role": role, "file_names": [name for name in (clean_text(n) for n in names) if name],
            "modality": clean_text(attrs.get("Modality")), "series_number": clean_text(attrs.get("SeriesNumber")),
            "series_description": clean_text(attrs.get("SeriesDescription")), "instances": len(identities)}


def _mismatch(identities: list[DicomIdentity]) -> list[str]:
    seen = [_patient_and_study(identity) for identity in identities]
    return [name for name in COMPARED if len({s[name] for s in seen if s[name]}) > 1]


def case_identity(sources: DicomSources, *, source: str, file_names: dict[str, list[str]] | None = None) -> dict:
    """The case's identity as JSON (patient and study from the first DICOM input: AP, LAT, then volume).

    Args:
        sources: the identities the readers kept (``case.sources``).
        source: how the inputs came: one of :data:`SOURCES`.
        file_names: per role (``ap``, ``lat``, ``volume``, ``mesh``), the file names given (uploads only).
    """
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, not {source!r}")
    names = file_names or {}
    per_role = {"ap": [sources.ap] if sources.ap else [], "lat": [sources.lat] if sources.lat else [],
                "volume": list(sources.volume), "mesh": []}
    inputs = [_input(role, per_role[role], names.get(role, [])) for role in ROLES
              if per_role[role] or names.get(role)]
    everything = [*sources.xa, *sources.volume[:1]]
    return {"source": source, **_patient_and_study(sources.first), "inputs": inputs,
            "mismatch": _mismatch(everything)}


def case_search_text(identity: dict | None) -> str | None:
    """What a job list is searched by (``?q=``): patient ID and name, study date, description, accession."""
    if not identity:
        return None
    fields = ("patient_id", "patient_name", "study_date", "study_description", "accession_number")
    text = " | ".join(str(identity[name]) for name in fields if identity.get(name))
    return text.lower() or None


def with_source(identity: dict | None, *, source: str, file_names: dict[str, list[str]] | None = None) -> dict:
    """``identity`` (from :func:`case_identity`, or None for a case without DICOM) with its ``source`` and the
    upload's file names set: a validator reads the case, the caller knows how it came."""
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, not {source!r}")
    base = dict(identity) if identity else case_identity(DicomSources(), source=source)
    names = file_names or {}
    rows = {row["role"]: dict(row) for row in base.get("inputs", [])}
    for role in ROLES:
        given = [name for name in (clean_text(n) for n in names.get(role, [])) if name]
        if given:
            rows[role] = {**(rows.get(role) or _input(role, [], [])), "file_names": given}
    return {**base, "source": source, "inputs": [rows[role] for role in ROLES if role in rows]}
