"""Whose case it is: the patient, study and series of a case's inputs, for the person who reviews it.

:func:`case_identity` turns the :class:`~.dicom_identity.DicomSources` the readers kept (one parse,
never again) into plain JSON: patient name and ID, study date, description and accession number, the
modality and series of each input, the file names given for uploads and the source (``upload``,
``dicomweb`` or ``dimse``). ``mismatch`` names the attributes on which the DICOM inputs disagree
(an AP of one patient with a LAT of another is the first thing a reviewer must see).

Every value is untrusted text from a file header: it is kept as text, cut to :data:`MAX_TEXT`
characters with control characters removed, and never interpreted. A header holding several values
(backslash-separated) gives a JSON list of at most :data:`MAX_VALUES` texts, never one run-together string.
:func:`case_search_text` is what a list is searched by (patient ID and name, study date, description and
accession), lower-cased.

Patient names are compared as DICOM defines a PN (PS3.5 6.2): up to three component groups, alphabetic,
ideographic and phonetic (``Yamada^Taro=山田^太郎=やまだ^たろう``), each ``Family^Given^Middle^Prefix^Suffix``.
Two inputs disagree on the name when a group both hold differs (after :func:`name_key`'s normalisation), or
when both hold a name but no group in common; a name given only in its ideographic group is a name.
"""

from __future__ import annotations

import unicodedata
from typing import Any

from .dicom_identity import DicomIdentity, DicomSources

SOURCES = ("upload", "dicomweb", "dimse")
MAX_TEXT = 128
MAX_VALUES = 8
"""At most this many values of a multi-valued header attribute are kept (each cut to :data:`MAX_TEXT`)."""
ROLES = ("ap", "lat", "volume", "mesh")
COMPARED = ("patient_id", "patient_name", "study_uid")
"""Attributes that must agree across the DICOM inputs of one case (``mismatch`` names those that do not)."""


def clean_text(value: Any) -> str | None:
    """A header value as bounded plain text: control characters dropped, at most :data:`MAX_TEXT` characters."""
    if value is None:
        return None
    text = "".join(ch if ch.isprintable() else " " for ch in str(value)).strip()
    return text[:MAX_TEXT] or None


def _values(value: Any) -> list[Any]:
    """The values of a header attribute: a pydicom MultiValue (or list) value by value, else the one value."""
    if value is None:
        return []
    if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
        return list(value)[:MAX_VALUES]
    return [value]


def _one_or_list(texts: list[str]) -> str | list[str] | None:
    return None if not texts else texts[0] if len(texts) == 1 else texts


def clean_value(value: Any) -> str | list[str] | None:
    """:func:`clean_text` of each value: one text, a list of texts for a multi-valued attribute, or None."""
    return _one_or_list([t for t in (clean_text(v) for v in _values(value)) if t])


def _groups(value: Any) -> list[str]:
    """A PN value's three component groups (alphabetic, ideographic, phonetic), missing ones as ``""``."""
    text = "".join(ch if ch.isprintable() else " " for ch in str(value))
    return (text.split("=") + ["", ""])[:3]


def _one_group(group: str) -> str | None:
    family, *rest = [part.strip() for part in group.split("^")]
    given = " ".join(part for part in rest[:2] if part)
    return f"{family}, {given}" if family and given else (family or given or None)


def person_name(value: Any) -> str | list[str] | None:
    """A DICOM PN as text: each component group ``Family^Given^Middle`` as ``Family, Given Middle``, the groups
    present joined by `` = `` (``=山田^太郎`` reads ``山田, 太郎``); a list for a multi-valued name."""
    names = []
    for one in _values(value):
        shown = " = ".join(g for g in (_one_group(group) for group in _groups(one)) if g)
        if shown:
            names.append(shown[:MAX_TEXT])
    return _one_or_list(names)


def _fold(text: str) -> str:
    """Compatibility forms unified (full-width Latin, half-width kana, Hangul jamo), accents on Latin letters
    dropped (``Müller`` = ``Muller``), case folded, spaces collapsed. Marks on other scripts are kept: a
    dakuten or a Cyrillic breve makes a different letter (``が`` is not ``か``, ``й`` is not ``и``)."""
    kept, base_latin = [], False
    for ch in unicodedata.normalize("NFD", unicodedata.normalize("NFKC", text)):
        if unicodedata.combining(ch):
            if not base_latin:
                kept.append(ch)
            continue
        base_latin = unicodedata.name(ch, "").startswith("LATIN")
        kept.append(ch)
    return " ".join(unicodedata.normalize("NFKC", "".join(kept)).casefold().split())


def name_key(value: Any) -> tuple[frozenset[str], frozenset[str], frozenset[str]]:
    """What two PN values are compared by: per component group, the set of its normalised values
    (components :func:`_fold`-ed, trailing empty components dropped); an empty set where no value has it."""
    keys: tuple[set[str], set[str], set[str]] = (set(), set(), set())
    for one in _values(value):
        for index, group in enumerate(_groups(one)):
            parts = [_fold(part) for part in group.split("^")]
            while parts and not parts[-1]:
                parts.pop()
            if parts:
                keys[index].add("^".join(parts))
    return frozenset(keys[0]), frozenset(keys[1]), frozenset(keys[2])


def names_differ(first: Any, second: Any) -> bool:
    """Whether two PN values name different people: a component group both hold differs, or both hold a
    name but share no group (nothing to compare them by). A missing name on either side differs from nothing."""
    a, b = name_key(first), name_key(second)
    shared = [(x, y) for x, y in zip(a, b) if x and y]
    if not shared:
        return any(a) and any(b)
    return any(x != y for x, y in shared)


def dicom_date(value: Any) -> str | list[str] | None:
    """``YYYYMMDD`` as ``YYYY-MM-DD``; anything else as given (clean text); a list for several values."""
    dates = []
    for one in _values(value):
        text = clean_text(one)
        if text and len(text) == 8 and text.isdigit():
            text = f"{text[:4]}-{text[4:6]}-{text[6:]}"
        if text:
            dates.append(text)
    return _one_or_list(dates)


def _attrs(identity: DicomIdentity) -> dict[str, Any]:
    return {**dict(identity.patient), **dict(identity.study), **dict(identity.series)}


def _patient_and_study(identity: DicomIdentity | None) -> dict[str, str | None]:
    attrs = _attrs(identity) if identity else {}
    return {"patient_name": person_name(attrs.get("PatientName")), "patient_id": clean_value(attrs.get("PatientID")),
            "study_date": dicom_date(attrs.get("StudyDate")),
            "study_description": clean_value(attrs.get("StudyDescription")),
            "accession_number": clean_value(attrs.get("AccessionNumber")),
            "study_uid": clean_text(identity.study_instance_uid) if identity else None}


def _input(role: str, identities: list[DicomIdentity], names: list[str]) -> dict[str, Any]:
    attrs = _attrs(identities[0]) if identities else {}
    return {"role": role, "file_names": [name for name in (clean_text(n) for n in names) if name],
            "modality": clean_value(attrs.get("Modality")), "series_number": clean_value(attrs.get("SeriesNumber")),
            "series_description": clean_value(attrs.get("SeriesDescription")), "instances": len(identities)}


def _texts(value: Any) -> frozenset[str]:
    return frozenset(t for t in (clean_text(v) for v in _values(value)) if t)


def _mismatch(identities: list[DicomIdentity]) -> list[str]:
    """The :data:`COMPARED` attributes on which some two inputs disagree (every value of each compared)."""
    names = [_attrs(i).get("PatientName") for i in identities]
    ids = {_texts(_attrs(i).get("PatientID")) for i in identities} - {frozenset()}
    studies = {clean_text(i.study_instance_uid) for i in identities} - {None}
    differ = {"patient_id": len(ids) > 1, "study_uid": len(studies) > 1,
              "patient_name": any(names_differ(a, b) for k, a in enumerate(names) for b in names[k + 1:])}
    return [name for name in COMPARED if differ[name]]


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
    values = [identity.get(name) for name in fields]
    text = " | ".join(" ".join(v) if isinstance(v, list) else str(v) for v in values if v)
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
