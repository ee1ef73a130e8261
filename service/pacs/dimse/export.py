"""Results back by C-STORE (SCU): the REG and the overlays of a job to its DICOM destinations.

Run by the API process's exporter (:mod:`service.jobs.exports`) after the job succeeded, never by
the worker, for jobs made from a DICOM study (input role ``dimse``) and DIMSE references with
``store_results``. The destinations are ``dicom_export`` (AE titles of ``dicom_peers``), else the
peer that sent the study. Each destination gets one association with every file; a failure
(connection refused, association rejected or timed out, a C-STORE status that is not success or
warning) is retried ``dicom_export_retries`` times with doubling back-off within one export attempt.
Export never fails the job: the registration result stands, and the job's ``export`` says for
each destination what was stored, or a ``pacs-error`` naming the peer, the step and the DIMSE status.
"""

from __future__ import annotations

import io
import json
import logging
import time
from pathlib import Path
from typing import Any

from ...problems import TYPE_BASE
from .scp import configured_peers

log = logging.getLogger("dsareg.dimse")

PACS_ERROR = TYPE_BASE + "pacs-error"
SUCCESS_STATUSES = {0x0000, 0xB000, 0xB006, 0xB007}  # success, and the storage warnings (stored anyway)


class ExportError(Exception):
    def __init__(self, step: str, detail: str, status: int | None = None):
        super().__init__(detail)
        self.step, self.detail, self.status = step, detail, status


def _store_once(settings: Any, peer: Any, datasets: list) -> list[str]:
    """One association to ``peer`` storing ``datasets``; the SOP Instance UIDs stored."""
    from pynetdicom import AE

    ae = AE(ae_title=settings.dimse.dicom_ae_title)
    for timeout in ("acse_timeout", "dimse_timeout", "network_timeout", "connection_timeout"):
        setattr(ae, timeout, settings.dimse.dicom_timeout_seconds)
    for sop_class in sorted({str(ds.SOPClassUID) for ds in datasets}):
        ae.add_requested_context(sop_class, "1.2.840.10008.1.2.1")
    assoc = ae.associate(peer.host, peer.port, ae_title=peer.ae_title)
    if not assoc.is_established:
        if assoc.is_rejected:
            raise ExportError("associate", f"association rejected by {peer.ae_title} (does it know the calling AE "
                                           f"{settings.dimse.dicom_ae_title}?)")
        raise ExportError("associate", f"no association with {peer.host}:{peer.port} (connection refused, timed out "
                                       "or aborted: is the peer up?)")
    stored = []
    try:
        for ds in datasets:
            status = assoc.send_c_store(ds)
            code = int(getattr(status, "Status", -1)) if status else None
            if code not in SUCCESS_STATUSES:
                detail = "no answer" if code is None else f"status 0x{code:04X}"
                raise ExportError("C-STORE", f"{ds.SOPClassUID.name}: {detail}", code)
            stored.append(str(ds.SOPInstanceUID))
    finally:
        if assoc.is_established:
            assoc.release()
    return stored


def export_to(settings: Any, title: str, files: list[Path]) -> dict[str, Any]:
    """Store ``files`` at the peer ``title`` with bounded retries; the outcome (never raises)."""
    import pydicom

    peer = configured_peers(settings).get(title)
    started = time.perf_counter()
    if peer is None:
        return {"peer": title, "status": "failed", "attempts": 0, "error": {
            "type": PACS_ERROR, "peer": title, "step": "configuration", "status": None,
            "detail": "not one of DSAREG_DICOM_PEERS"}}
    datasets = [pydicom.dcmread(io.BytesIO(path.read_bytes())) for path in files]
    attempts, error = 0, None
    while attempts <= settings.dimse.dicom_export_retries:
        attempts += 1
        try:
            uids = _store_once(settings, peer, datasets)
            return {"peer": title, "host": peer.host, "port": peer.port, "status": "stored", "attempts": attempts,
                    "sop_instance_uids": uids, "seconds": round(time.perf_counter() - started, 3)}
        except ExportError as exc:
            error = exc
        except Exception as exc:  # noqa: BLE001 - a network failure of any kind is a failed attempt
            error = ExportError("associate", f"{type(exc).__name__}: {str(exc)[:160]}")
        if attempts <= settings.dimse.dicom_export_retries:
            time.sleep(settings.dimse.dicom_export_backoff_seconds * 2 ** (attempts - 1))
    log.debug("export to %s failed after %d attempts: %s %s", title, attempts, error.step, error.detail)  # the
    # exporter's one warning per export attempt carries it (service/jobs/exports.py; it was logged twice)
    return {"peer": title, "host": peer.host, "port": peer.port, "status": "failed", "attempts": attempts,
            "seconds": round(time.perf_counter() - started, 3),
            "error": {"type": PACS_ERROR, "peer": title, "step": error.step, "status": error.status,
                      "detail": f"PACS {title}: {error.step} failed after {attempts} attempts: {error.detail}"}}


class DimseJob:
    """The DICOM side of a job made from a received study: its source and its export destinations."""

    def __init__(self, document: dict[str, Any], settings: Any):
        self.document, self.settings = document, settings


def dimse_source(job: Any, read: Any) -> dict[str, Any] | None:
    """``{"dimse": {...}}`` of a job made from a DICOM study (None otherwise, or when its input is gone)."""
    refs = [item for item in job.inputs if item.role == "dimse"]
    if not refs:
        return None
    try:
        return json.loads(read(refs[0].sha256))["source"]
    except Exception:  # noqa: BLE001 - informative only; a status answer must not fail on it
        return None


def dimse_job(job: Any, read: Any, settings: Any) -> DimseJob | None:
    """The job's DICOM source (``None`` for a job that did not come from a DICOM study)."""
    refs = [item for item in job.inputs if item.role == "dimse"]
    return DimseJob(json.loads(read(refs[0].sha256)), settings) if refs else None
