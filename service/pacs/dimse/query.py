"""Query/Retrieve SCU: C-FIND, C-MOVE to dsareg's own AE, and the patient's latest vessel volume.

* :func:`c_find` — one C-FIND (Study Root, else Patient Root) at a level, the matches' identifiers;
* :func:`retrieve` — a C-MOVE with Move Destination = our AE title (``dicom_ae_title``): the peer
  opens its own association to our C-STORE SCP (:mod:`.scp`), which commits those instances as
  ``retrieved`` (:mod:`.inbox`); we wait (bounded) until as many as the peer reported completed
  are there and return them. The peer must know our AE title as a modality (host, port);
* :func:`latest_volume` — the newest study of a patient holding a CT / MR / 3D-RA series (by
  Study Date, Study Time), and its largest such series.

Every failure raises :class:`DimsePacsError` naming the peer, the step and the DIMSE status. Each
DIMSE wait is bounded by ``dicom_timeout_seconds``; a peer that keeps answering "pending" is bounded
by ``pacs_deadline_seconds`` in all (:func:`bounded`: the association is aborted past it).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..dicomweb import PacsError
from .scp import configured_peers

STUDY_FIND, STUDY_MOVE = "1.2.840.10008.5.1.4.1.2.2.1", "1.2.840.10008.5.1.4.1.2.2.2"
PATIENT_FIND, PATIENT_MOVE = "1.2.840.10008.5.1.4.1.2.1.1", "1.2.840.10008.5.1.4.1.2.1.2"
PENDING, SUCCESS, WARNING = {0xFF00, 0xFF01}, 0x0000, 0xB000
VOLUME_MODALITIES = ("CT", "MR")
XA_3D_CLASSES = ("1.2.840.10008.5.1.4.1.1.13.1.1",)  # X-Ray 3D Angiographic Image Storage


class DimsePacsError(PacsError):
    """A DIMSE query or retrieve failed: which peer, which step, which DIMSE status."""

    def __init__(self, peer: str, step: str, detail: str, status: int | None = None):
        self.server, self.step, self.detail, self.status, self.attempts = peer, step, detail, status, 1
        where = f" (DIMSE status 0x{status:04X})" if status is not None else ""
        Exception.__init__(self, f"PACS {peer}: {step} failed{where}: {detail}")

    def problem_extra(self) -> dict[str, Any]:
        return {"peer": self.server, "step": self.step, "dimse_status": self.status}


def scu_ae(settings: Any):
    """A pynetdicom AE with our AE title and the DIMSE timeouts."""
    import logging

    from pynetdicom import AE

    if not logging.getLogger("dsareg").isEnabledFor(logging.DEBUG):  # one INFO line per sub-operation otherwise
        logging.getLogger("pynetdicom").setLevel(logging.WARNING)
    ae = AE(ae_title=settings.dimse.dicom_ae_title)
    for timeout in ("acse_timeout", "dimse_timeout", "network_timeout", "connection_timeout"):
        setattr(ae, timeout, settings.dimse.dicom_timeout_seconds)
    return ae


def associate(settings: Any, title: str, contexts: tuple[str, ...], step: str, **kwargs: Any):
    """An established association with peer ``title`` proposing ``contexts`` (else :class:`DimsePacsError`)."""
    peer = configured_peers(settings).get(title)
    if peer is None:
        raise DimsePacsError(title, "configuration", "not one of this server's DSAREG_DICOM_PEERS")
    ae = scu_ae(settings)
    for uid in contexts:
        ae.add_requested_context(uid)
    assoc = ae.associate(peer.host, peer.port, ae_title=peer.ae_title, **kwargs)
    if not assoc.is_established:
        raise DimsePacsError(title, step, f"association rejected by {title} (does it know the calling AE "
                                          f"{settings.dimse.dicom_ae_title}?)" if assoc.is_rejected else
                             f"no association with {peer.host}:{peer.port} (connection refused, timed out or "
                             "aborted: is the peer up?)")
    return assoc


def deadline_of(settings: Any) -> float:
    """The monotonic time by which a job's (or a study's) PACS queries and retrievals must be over."""
    return time.monotonic() + settings.dicomweb.pacs_deadline_seconds


def bounded(assoc: Any, answers: Any, deadline_at: float, title: str, step: str) -> Any:
    """``answers`` (a pynetdicom response generator) until ``deadline_at``; then abort and :class:`DimsePacsError`."""
    for answer in answers:
        yield answer
        if time.monotonic() > deadline_at:
            assoc.abort()
            raise DimsePacsError(title, step, "the peer was still answering 'pending' at the job's PACS deadline "
                                              "(DSAREG_PACS_DEADLINE_SECONDS); association aborted")


def _accepted(assoc: Any, *models: str) -> str | None:
    uids = {str(cx.abstract_syntax) for cx in assoc.accepted_contexts}
    return next((uid for uid in models if uid in uids), None)


def query_identifier(level: str, keys: dict[str, Any]):
    from pydicom.dataset import Dataset

    query = Dataset()
    query.QueryRetrieveLevel = level
    for keyword, value in keys.items():
        setattr(query, keyword, value)
    return query


def c_find(assoc: Any, title: str, level: str, keys: dict[str, Any], step: str,
           deadline_at: float = float("inf")) -> list[Any]:
    """The identifiers one C-FIND matches (``keys``: matching values, ``""`` for return keys)."""
    model = _accepted(assoc, STUDY_FIND, PATIENT_FIND)
    if model is None:
        raise DimsePacsError(title, step, "the peer accepted neither Study Root nor Patient Root C-FIND")
    found, final = [], None
    for status, identifier in bounded(assoc, assoc.send_c_find(query_identifier(level, keys), model), deadline_at,
                                      title, step):
        code = int(getattr(status, "Status", -1)) if status else None
        if code in PENDING and identifier is not None:
            found.append(identifier)
        elif code not in PENDING:
            final = code
    if final != SUCCESS:
        raise DimsePacsError(title, step, "no answer (timed out or aborted)" if final is None else
                             f"C-FIND ended with status 0x{final:04X}", final)
    return found


@dataclass(frozen=True)
class VolumeSeries:
    study_uid: str
    series_uid: str
    modality: str
    instances: int
    study_date: str


def _volume_series(assoc: Any, title: str, study_uid: str, until: float) -> VolumeSeries | None:
    series = c_find(assoc, title, "SERIES", {"StudyInstanceUID": study_uid, "SeriesInstanceUID": "", "Modality": "",
                                             "NumberOfSeriesRelatedInstances": ""}, "C-FIND series (volume)", until)
    candidates = []
    for item in series:
        modality = str(getattr(item, "Modality", "") or "")
        if modality == "XA":
            images = c_find(assoc, title, "IMAGE", {"StudyInstanceUID": study_uid,
                                                    "SeriesInstanceUID": item.SeriesInstanceUID, "SOPClassUID": "",
                                                    "SOPInstanceUID": ""}, "C-FIND images (3D-RA)", until)
            if not any(str(getattr(i, "SOPClassUID", "")) in XA_3D_CLASSES for i in images):
                continue
        elif modality not in VOLUME_MODALITIES:
            continue
        count = int(getattr(item, "NumberOfSeriesRelatedInstances", 0) or 0)
        candidates.append((count, str(item.SeriesInstanceUID), modality))
    if not candidates:
        return None
    count, uid, modality = max(candidates)
    return VolumeSeries(study_uid, uid, modality, count, "")


def latest_volume(settings: Any, title: str, patient_id: str, exclude_study: str) -> VolumeSeries | None:
    """The patient's newest study (Study Date + Time) with a CT / MR / 3D-RA series, and that series."""
    until = deadline_of(settings)
    assoc = associate(settings, title, (STUDY_FIND, PATIENT_FIND), "C-FIND studies (patient's volume)")
    try:
        studies = c_find(assoc, title, "STUDY", {"PatientID": patient_id, "StudyInstanceUID": "", "StudyDate": "",
                                                 "StudyTime": "", "ModalitiesInStudy": ""},
                         "C-FIND studies (patient's volume)", until)
        ranked = sorted(studies, key=lambda s: (str(getattr(s, "StudyDate", "") or ""),
                                                str(getattr(s, "StudyTime", "") or "")), reverse=True)
        for study in ranked:
            uid = str(study.StudyInstanceUID)
            value = getattr(study, "ModalitiesInStudy", None) or []
            modalities = {str(value)} if isinstance(value, str) else {str(item) for item in value}
            if uid == exclude_study or (modalities and not modalities & {*VOLUME_MODALITIES, "XA"}):
                continue
            found = _volume_series(assoc, title, uid, until)
            if found is not None:
                return VolumeSeries(found.study_uid, found.series_uid, found.modality, found.instances,
                                    str(getattr(study, "StudyDate", "") or ""))
        return None
    finally:
        if assoc.is_established:
            assoc.release()


def c_move(settings: Any, title: str, level: str, keys: dict[str, Any], step: str,
           deadline_at: float | None = None, on_progress: Callable[[int], None] | None = None) -> int:
    """C-MOVE the matches of ``keys`` to our own AE; the number of sub-operations the peer completed.
    ``on_progress(completed)`` at each of the peer's pending answers. A peer silent for ``dicom_timeout_seconds``
    (frozen, or gone without closing) ends it: the association is aborted and :class:`DimsePacsError` says so."""
    deadline_at = deadline_of(settings) if deadline_at is None else deadline_at
    assoc = associate(settings, title, (STUDY_MOVE, PATIENT_MOVE), step)
    final, completed, heard_at = None, 0, time.monotonic()
    try:
        model = _accepted(assoc, STUDY_MOVE, PATIENT_MOVE)
        if model is None:
            raise DimsePacsError(title, step, "the peer accepted neither Study Root nor Patient Root C-MOVE")
        answers = assoc.send_c_move(query_identifier(level, keys), settings.dimse.dicom_ae_title, model)
        for status, _answer in bounded(assoc, answers, deadline_at, title, step):
            if not status:  # no answer in time, or the association ended
                continue
            heard_at, code = time.monotonic(), int(getattr(status, "Status", -1))
            completed = int(getattr(status, "NumberOfCompletedSuboperations", completed) or completed)
            if code not in PENDING:
                final = code
            elif on_progress is not None:
                on_progress(completed)
    finally:
        if assoc.is_established:
            assoc.release()
    if final not in (SUCCESS, WARNING) or not completed:
        raise DimsePacsError(title, step, _move_failure(settings, final, completed, time.monotonic() - heard_at), final)
    return completed


def silence_detail(settings: Any, silent_s: float, received: str) -> str:
    """Why a retrieval without its final answer ended: the peer silent past the timeout, or the association lost."""
    if silent_s >= 0.9 * settings.dimse.dicom_timeout_seconds:  # pynetdicom's timers start a little after ours
        return (f"the peer stopped answering (nothing for {settings.dimse.dicom_timeout_seconds:g} s, "
                f"DSAREG_DICOM_TIMEOUT_SECONDS): association aborted, {received}")
    return f"the association ended before the peer's final answer (aborted or connection lost), {received}"


def _move_failure(settings: Any, final: int | None, completed: int, silent_s: float) -> str:
    ours = settings.dimse.dicom_ae_title
    if final is None:
        return silence_detail(settings, silent_s, f"{completed} instance(s) sent to {ours} before")
    return (f"{completed} instance(s) sent to {ours} (does the peer know {ours} as a DICOM modality, and is dsareg's "
            "DICOM node listening?)")


def retrieve(settings: Any, inbox: Any, title: str, level: str, keys: dict[str, Any], step: str,
             on_progress: Callable[[int], None] | None = None) -> list[Any]:
    """C-MOVE one series (or one instance of it) to us; its ``retrieved`` inbox rows once all have arrived."""
    completed = c_move(settings, title, level, keys, step, on_progress=on_progress)
    series, sop = keys["SeriesInstanceUID"], keys.get("SOPInstanceUID")
    deadline = time.monotonic() + settings.dimse.dicom_timeout_seconds
    while True:
        found = inbox.series(series, sop)
        if len(found) >= completed:
            return found
        if time.monotonic() > deadline:
            raise DimsePacsError(title, step, f"the peer reported {completed} instance(s) sent but {len(found)} "
                                              f"reached {settings.dimse.dicom_ae_title} within "
                                              f"{settings.dimse.dicom_timeout_seconds:g} s")
        time.sleep(0.05)
