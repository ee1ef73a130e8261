"""Inputs by reference over DIMSE: ``{"source": {"dimse": {"peer", "study_uid", "ap", "lat", "volume"}}}``.

The alternative to a DICOMweb reference for a PACS that only speaks DIMSE. The request names a
peer by AE title (one of ``dicom_peers``: nothing else is reachable); the worker retrieves the
AP and LAT instances and the volume series with **C-MOVE** (``"retrieve": "move"``, the default:
the peer sends them to dsareg's own DICOM node, :mod:`.query`) or **C-GET** (``"get"``: Study Root,
the instances come back on the same association, so the peer needs no route back to dsareg) and, with
``store_results``, the REG and overlays are stored back into the peer by C-STORE after the job, by the
exporter (:mod:`service.jobs.exports` with :mod:`.export`; a failed export is the job's ``export``
state, never fails the job nor holds the worker).
A retrieve that fails fails the job with ``pacs-error`` naming the peer, the step and the
DIMSE status.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from contextlib import ExitStack
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...engine_adapter import fetched_case_files
from ..dicomweb import ReferenceRequestFields, StudyReference
from .get_receive import GetReceiver
from .query import DimsePacsError, bounded, deadline_of, query_identifier, retrieve, scu_ae, silence_detail
from .scp import STORAGE_CLASSES, configured_peers, decodable_transfer_syntaxes

ROLE = "dimse-reference"
GET_MODEL = "1.2.840.10008.5.1.4.1.2.2.3"  # Study Root Query/Retrieve Information Model - GET
PENDING, SUCCESS = {0xFF00, 0xFF01}, 0x0000


class DimseSource(StudyReference):
    peer: str = Field(description="AE title of the PACS; must be one of the server's DSAREG_DICOM_PEERS.",
                      examples=["ORTHANC"])
    retrieve: Literal["move", "get"] = Field(
        "move", description="C-MOVE (default; the PACS sends the instances to dsareg's DICOM node, so it must know "
                            "dsareg's AE title as a modality) or C-GET (the instances come back on the same "
                            "association; no route back needed, fewer PACS allow it).")


class DimseSourceField(BaseModel):
    model_config = ConfigDict(extra="forbid")
    dimse: DimseSource


class DimseRegistrationRequest(ReferenceRequestFields):
    """``POST /v1/registrations`` (``application/json``) with inputs retrieved over DIMSE (C-MOVE or C-GET)."""

    source: DimseSourceField
    store_results: bool = Field(True, description="C-STORE the REG and the overlays back to the peer.")


def c_get(settings: Any, title: str, level: str, keys: dict[str, str], step: str,
          on_received: Callable[[int], None] | None = None) -> list[bytes]:
    """The instances a C-GET at ``level`` with ``keys`` returns from peer ``title`` (Part 10 bytes), each held on
    disk while the retrieval lasts (:mod:`.get_receive`); ``on_received(count)`` after each one kept.

    A peer that stops answering (frozen, or gone without closing) ends it after ``dicom_timeout_seconds`` of
    silence: the association is aborted and :class:`DimsePacsError` says so."""
    from pynetdicom import build_role, evt

    peer = configured_peers(settings).get(title)
    if peer is None:
        raise DimsePacsError(title, "configuration", "no longer one of this server's DSAREG_DICOM_PEERS")
    receiver = GetReceiver(settings, on_received)
    ae = scu_ae(settings)
    ae.add_requested_context(GET_MODEL)
    syntaxes = decodable_transfer_syntaxes()
    for sop_class in STORAGE_CLASSES:
        ae.add_requested_context(sop_class, syntaxes)
    roles = [build_role(sop_class, scp_role=True) for sop_class in STORAGE_CLASSES]
    assoc = ae.associate(peer.host, peer.port, ae_title=peer.ae_title, ext_neg=roles,
                         evt_handlers=[(evt.EVT_C_STORE, receiver.on_store)])
    if not assoc.is_established:
        raise DimsePacsError(title, step, "association rejected" if assoc.is_rejected else
                             f"no association with {peer.host}:{peer.port} (connection refused, timed out or aborted)")
    try:
        receiver.bind(assoc)
        final = _get_answers(settings, assoc, query_identifier(level, keys), title, step, receiver)
        if final not in (SUCCESS, 0xB000) or not receiver.kept:
            raise DimsePacsError(title, step, _get_failure(settings, final, receiver), final)
        return receiver.instances()
    finally:
        receiver.close()
        if assoc.is_established:
            assoc.release()


def _get_answers(settings: Any, assoc: Any, query: Any, title: str, step: str, receiver: GetReceiver) -> int | None:
    """The C-GET's final status (None: no final answer: the peer went silent, or the association ended)."""
    final = None
    for status, _identifier in bounded(assoc, assoc.send_c_get(query, GET_MODEL), deadline_of(settings), title, step):
        if not status:  # no answer in time, or the association ended
            continue
        receiver.heard()
        code = int(getattr(status, "Status", -1))
        if code not in PENDING:
            final = code
    return final


def _get_failure(settings: Any, final: int | None, receiver: GetReceiver) -> str:
    received = f"{len(receiver.kept)} instance(s) received"
    if receiver.refused:
        received += f", {len(receiver.refused)} refused ({receiver.refused[0]})"
    return received if final is not None else silence_detail(settings, receiver.silent_s(), received)


def _first_by_number(parts: list[bytes]) -> bytes:
    import io

    import pydicom

    def number(data: bytes) -> float:
        try:
            return float(pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True).InstanceNumber)
        except Exception:  # noqa: BLE001
            return float("inf")

    return min(parts, key=number)


class DimsePullJob:
    """Fetch a job's inputs by C-MOVE or C-GET and C-STORE its DICOM results back (the worker's PACS-job interface)."""

    def __init__(self, reference: DimseRegistrationRequest, settings: Any, read: Any = None):
        self.reference, self.settings, self.read = reference, settings, read
        self.source_info: dict[str, Any] = {}

    def _retriever(self, stack: ExitStack):
        """``(level, keys, step) -> [Part 10 bytes]`` by the source's ``retrieve`` (C-MOVE or C-GET)."""
        source, settings = self.reference.source.dimse, self.settings
        if source.retrieve == "get":
            return lambda level, keys, step: c_get(settings, source.peer, level, keys, step)
        import sqlalchemy as sa

        from ...storage.inbox import Inbox

        database = sa.create_engine(settings.effective_database_url)  # the job database: the node's inbox
        stack.callback(database.dispose)
        inbox = Inbox(database)
        return lambda level, keys, step: [self.read(item.sha256) for item in
                                          retrieve(settings, inbox, source.peer, level, keys, step)]

    def fetch(self) -> Any:
        source = self.reference.source.dimse
        started, how = time.perf_counter(), "C-MOVE" if source.retrieve == "move" else "C-GET"
        warnings, images = [], {}
        with ExitStack() as stack:
            fetch = self._retriever(stack)
            for name in ("ap", "lat"):
                ref = getattr(source, name)
                keys = {"StudyInstanceUID": source.study_uid, "SeriesInstanceUID": ref.series_uid}
                if ref.sop_instance_uid:
                    keys["SOPInstanceUID"] = ref.sop_instance_uid
                parts = fetch("IMAGE" if ref.sop_instance_uid else "SERIES", keys, f"retrieve {name} ({how})")
                if len(parts) > 1:
                    warnings.append(f"{name}: series has {len(parts)} instances; the first by Instance Number was "
                                    "used (give sop_instance_uid to choose)")
                images[name] = _first_by_number(parts)
            volume = fetch("SERIES", {"StudyInstanceUID": source.volume.study_uid or source.study_uid,
                                      "SeriesInstanceUID": source.volume.series_uid}, f"retrieve volume ({how})")
        self.source_info = {"dimse": {"peer": source.peer, "study_uid": source.study_uid, "retrieve": source.retrieve,
                                      "fetch_seconds": round(time.perf_counter() - started, 3),
                                      "instances": 2 + len(volume)}}
        return fetched_case_files(images["ap"], images["lat"], volume, source.frames, warnings)


def pull_job(job: Any, read: Any, settings: Any) -> DimsePullJob | None:
    refs = [item for item in job.inputs if item.role == ROLE]
    if not refs:
        return None
    return DimsePullJob(DimseRegistrationRequest.model_validate(json.loads(read(refs[0].sha256))), settings, read)
