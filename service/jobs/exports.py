"""PACS exports of a job's results, outside the registration worker (issue 43).

* **Recorded with the job**: a job whose DICOM results go to a PACS (STOW-RS for a DICOMweb reference with
  ``store_results``; C-STORE for a DIMSE reference with ``store_results`` or for a study received over DIMSE
  with export destinations) is completed by its worker *without* the store: the target (:func:`export_target`)
  is written with the job's completion, in the same transaction (``job_exports``): nothing can be lost between
  the two, and the job is ``succeeded`` as soon as its registration is stored, whatever the PACS does.
  State ``pending`` (due at once), or ``awaiting_review`` with ``DSAREG_EXPORT_AFTER_REVIEW=true``.
* **Reviews**: an approval makes a held (or failed) export ``pending`` in the review's transaction
  (``SqlJobStore.review``); a rejection makes a held or pending one ``skipped``; nothing is sent for a job whose
  latest review is a rejection (the store's due query checks it).
* **Delivered by the API process** (:class:`ExportDeliverer`, the loop of completion callbacks,
  :mod:`.leased`), in both topologies, never by a registration worker: claimed with a lease, at most
  ``EXPORT_THREADS`` attempts at a time and one per destination (a frozen peer holds one thread, the other
  destinations' exports go on; the rest wait in the table, not in memory), stored, recorded (``done``,
  or a ``pacs-error`` and a retry after ``export_retry_backoff_seconds`` doubling, ``export_max_attempts`` in
  all, then ``failed``). An attempt is bounded by the DIMSE timeouts and ``dicom_export_retries`` (C-STORE) or
  ``pacs_deadline_seconds`` (STOW-RS); a C-STORE retry goes only to the destinations not yet stored. The lease is
  short (``export_lease_seconds``, 15 s) and renewed every third of it while the attempt runs: an API killed (or
  frozen) between the job's end and the store, or during it, leaves the row pending or leased for at most that
  long; after the restart it is stored then (at least once; a PACS keeps one copy of a SOP Instance UID stored
  twice). Every step is an audit event of the job.
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ..pacs.dicom_jobs import STORED_FILES, PacsJob
from ..pacs.dicomweb import DicomwebClient, PacsBudget, PacsError, resolve_server
from ..pacs.dimse.export import export_to
from ..pacs.dimse.pull import DimsePullJob
from ..problems import TYPE_BASE
from ..settings import ServiceSettings
from ..storage.blobs import BlobStore
from ..storage.interfaces import DeliveryStore
from ..storage.store import JobRecord
from .leased import LeasedDeliverer

log = logging.getLogger("dsareg.service.exports")

STOW, CSTORE = "stow-rs", "c-store"
MAX_BACKOFF_SECONDS = 300.0
EXPORT_THREADS = 4  # export attempts at a time per API process, each to another destination


def export_target(pacs: Any, dimse: Any, after_review: bool = False) -> dict[str, Any] | None:
    """Where this job's results are to be stored (``pacs``/``dimse``: the worker's PACS job objects); None: nowhere."""
    target: dict[str, Any] | None = None
    if isinstance(pacs, PacsJob) and pacs.reference.store_results:
        source = pacs.reference.source.dicomweb
        target = {"via": STOW, "server": source.url, "study_uid": source.study_uid}
    elif isinstance(pacs, DimsePullJob) and pacs.reference.store_results:
        target = {"via": CSTORE, "peers": [pacs.reference.source.dimse.peer]}
    elif dimse is not None and dimse.document.get("export"):
        target = {"via": CSTORE, "peers": list(dimse.document["export"])}
    return None if target is None else {**target, "after_review": after_review}


def destination_of(target: dict[str, Any]) -> str:
    """One export attempt at a time per destination (per API process): a frozen peer holds one thread, not all."""
    return str(target.get("server")) if target.get("via") == STOW else ",".join(target.get("peers") or [])


def source_of(pacs: Any, dimse: Any) -> dict[str, Any] | None:
    """``result.dicom.source`` as the inline export would have written it."""
    if pacs is not None:
        return pacs.source_info
    return None if dimse is None else dimse.document.get("source")


def pacs_error(detail: str, **extra: Any) -> dict[str, Any]:
    return {"type": TYPE_BASE + "pacs-error", "title": "PACS error", "status": 502, "detail": detail, **extra}


def _stow(target: dict[str, Any], files: list[tuple[str, bytes]], uids: list[str],
          settings: ServiceSettings) -> tuple[dict | None, dict | None]:
    server = resolve_server(settings, target["server"])
    if server is None:
        return None, pacs_error(f"PACS {target['server']}: no longer one of this server's DSAREG_DICOMWEB_SERVERS",
                                server=target["server"], step="configuration")
    started = time.perf_counter()
    try:
        with DicomwebClient(server, timeout=settings.dicomweb.dicomweb_timeout_seconds, retries=settings.dicomweb.dicomweb_retries,
                            backoff=settings.dicomweb.dicomweb_retry_backoff_seconds,
                            max_bytes=settings.limits.max_upload_bytes,
                            budget=PacsBudget(settings.dicomweb.pacs_deadline_seconds)) as client:
            stored = client.store(target["study_uid"], [data for _, data in files])
    except PacsError as exc:
        return None, pacs_error(str(exc), **exc.problem_extra())
    return {"via": STOW, "server": server.url, "study_uid": target["study_uid"], "sop_instance_uids": uids,
            "confirmed": bool(uids) and set(uids) <= set(stored),
            "seconds": round(time.perf_counter() - started, 3)}, None


def _cstore(target: dict[str, Any], files: list[tuple[str, bytes]], settings: ServiceSettings,
            before: dict | None = None) -> tuple[dict | None, dict | None]:
    """C-STORE to each destination not yet stored by an earlier attempt (``before``: its outcome)."""
    stored = {item["peer"]: item for item in (before or {}).get("peers") or [] if item.get("status") == "stored"}
    with tempfile.TemporaryDirectory(prefix="dsareg-export-") as tmp:
        paths = []
        for name, data in files:
            (Path(tmp) / name).write_bytes(data)
            paths.append(Path(tmp) / name)
        results = [stored.get(peer) or export_to(settings, peer, paths) for peer in target["peers"]]
    outcome = {"via": CSTORE, "peers": results}
    failed = [item["error"] for item in results if item["status"] != "stored"]
    if failed:  # every failed destination in the detail (the exporter's one log line per attempt shows it)
        first = failed[0]
        return outcome, pacs_error("; ".join(item["detail"] for item in failed), peer=first["peer"], step=first["step"],
                                   dimse_status=first["status"])
    return outcome, None


def store_results(job: JobRecord, target: dict[str, Any], read: Any, settings: ServiceSettings,
                  before: dict | None = None) -> tuple[dict | None, dict | None]:
    """One export attempt of ``job``'s REG and overlays: ``(outcome, None)`` or ``(outcome or None, pacs-error)``
    (``before``: the outcome of the previous attempt, whose stored C-STORE destinations are not sent again)."""
    missing = [name for name in STORED_FILES if name not in (job.artifacts or {})]
    if missing:
        return None, pacs_error(f"the job has no {', '.join(missing)} to export", step="results")
    files = [(name, read(job.artifacts[name])) for name in STORED_FILES]
    instances = ((job.result or {}).get("dicom") or {}).get("instances") or {}
    uids = [str(instances[name]["sop_instance_uid"]) for name in STORED_FILES if name in instances]
    if target.get("via") == STOW:
        return _stow(target, files, uids, settings)
    return _cstore(target, files, settings, before)


class ExportDeliverer(LeasedDeliverer):
    """The API process's loop that stores succeeded jobs' results into their PACS (see the module docstring)."""

    name = "exports"

    def __init__(self, store: DeliveryStore, blobs: BlobStore, settings: ServiceSettings):
        super().__init__(threads=EXPORT_THREADS)
        self.store, self.blobs, self.settings = store, blobs, settings
        self.renewed_lease_seconds = settings.jobs.export_lease_seconds  # recovery after an API crash: this + a poll
        self._busy: set[str] = set()  # destinations with an attempt under way here
        self._busy_lock = threading.Lock()

    def due(self, now: float) -> list[str]:
        return self.store.due_exports(now, limit=100)

    def claim(self, job_id: str, now: float) -> dict[str, Any] | None:
        job = self.store.get(job_id)
        if job is None or not job.export:
            return None
        destination = destination_of(job.export["target"])
        with self._busy_lock:
            if destination in self._busy:  # its peer is busy with another job's attempt (or frozen): later
                return None
            self._busy.add(destination)
        row = self.store.claim_export(job_id, now, self.renewed_lease_seconds)
        if row is None:
            self._free(destination)
        return row

    def _free(self, destination: str) -> None:
        with self._busy_lock:
            self._busy.discard(destination)

    def renew(self, row: dict[str, Any], until: float) -> bool:
        return self.store.renew_export(row["job_id"], row["attempts"], until)

    def deliver(self, row: dict[str, Any]) -> str:
        try:
            return self._attempt(row)
        finally:
            self._free(destination_of(row["target"]))

    def _attempt(self, row: dict[str, Any]) -> str:
        job = self.store.get(row["job_id"])
        if job is None:
            return "gone"
        outcome, error = store_results(job, row["target"], self.blobs.read, self.settings, row.get("outcome"))
        attempt = row["attempts"]
        if error is None:
            state, next_at = "done", None
        elif attempt >= self.settings.jobs.export_max_attempts:
            state, next_at = "failed", None
        else:
            delay = min(MAX_BACKOFF_SECONDS, self.settings.jobs.export_retry_backoff_seconds * 2.0 ** (attempt - 1))
            state, next_at = "pending", time.time() + delay
        if error is not None:
            error = {**error, "attempts": attempt, "instance": f"/v1/registrations/{job.id}"}
        self.store.finish_export(job.id, attempt, state=state, outcome=outcome, error=error, next_attempt_at=next_at)
        log.log(logging.INFO if state == "done" else logging.WARNING, "job %s: export attempt %d %s%s", job.id,
                attempt, state, f" ({error['detail']})" if error else "")
        return state
