"""The review of a finished job by a person: what is sent and what the job shows."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...problems import ProblemDetails
from .closed import CLOSED
from .dimse_result import DimseExport

Decision = Literal["approved", "rejected"]
ReviewFilter = Literal["none", "approved", "rejected"]
MAX_COMMENT_CHARS = 2000


class ReviewRequest(BaseModel):
    """``POST /v1/registrations/{job_id}/review``: a person's decision on a finished job."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [
        {"decision": "approved", "comment": "Contours follow the vessels in both views."}]})

    decision: Decision = Field(description="approved: the pose may be used (and exported); rejected: it may not.")
    comment: str = Field("", max_length=MAX_COMMENT_CHARS,
                         description=f"Why, in the reviewer's words (at most {MAX_COMMENT_CHARS} characters).")


class Review(BaseModel):
    """The latest review of the job; earlier ones stay in the job's audit log."""

    model_config = CLOSED

    decision: Decision
    comment: str = Field(description="The reviewer's comment (may be empty).")
    by: str = Field(description="Who reviewed: 'key:' and the first 8 hex digits of the API key's SHA-256, "
                                "or 'anonymous' when the service runs without API keys.")
    at: str = Field(description="When, ISO 8601 UTC.")


def reviewer_label(principal: str) -> str:
    """A non-secret label of the caller: ``key:<8 hex of the key's SHA-256>`` or ``anonymous``."""
    if principal.startswith("key:"):
        return principal[:12]
    return principal


def review_model(record: dict[str, Any] | None) -> Review | None:
    if not record:
        return None
    at = datetime.fromtimestamp(float(record["at"]), tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    return Review(decision=record["decision"], comment=record.get("comment", ""), by=record["by"], at=at)


ExportStateName = Literal["awaiting_review", "pending", "exporting", "done", "failed", "skipped"]


class ExportState(BaseModel):
    """The PACS export of a job's results: sent after the job succeeded by the service's exporter, never by the
    registration worker (held for a review first with ``DSAREG_EXPORT_AFTER_REVIEW=true``; docs/review.md)."""

    model_config = CLOSED

    state: ExportStateName = Field(
        description="awaiting_review: the results wait for an approval; pending: due (at once, or approved), or "
                    "retried at next_attempt_at after a failed attempt (error says why); exporting: an attempt is "
                    "under way; done: stored; failed: out of attempts (error says why; an approval tries again); "
                    "skipped: rejected, never exported.")
    via: Literal["stow-rs", "c-store"] = Field(description="STOW-RS (job by DICOMweb reference) or C-STORE (DIMSE).")
    destination: str = Field(description="The DICOMweb server URL, or the AE titles of the DICOM peers.")
    after_review: bool = Field(True, description="Held until a person approved the job (DSAREG_EXPORT_AFTER_REVIEW "
                                                 "when the job ended); false: sent as soon as the job succeeded.")
    study_uid: str | None = Field(None, description="The study the results are stored into (STOW-RS).")
    attempts: int = Field(0, description="Export attempts (since the latest approval, for a held export).")
    last_attempt_at: str | None = None
    next_attempt_at: str | None = Field(None, description="When the next attempt is due (pending after a failure).")
    done_at: str | None = None
    sop_instance_uids: list[str] = Field(default_factory=list, description="What was stored (done).")
    peers: list[DimseExport] | None = Field(
        None, description="C-STORE: each destination's outcome in the latest attempt (a destination stored once is "
                          "not sent again).")
    error: ProblemDetails | None = Field(None, description="The pacs-error of the last failed attempt.")


def _iso(ts: float | None) -> str | None:
    return None if ts is None else datetime.fromtimestamp(float(ts), tz=UTC).isoformat(
        timespec="milliseconds").replace("+00:00", "Z")


def _stored_uids(outcome: dict[str, Any] | None) -> list[str]:
    if not outcome:
        return []
    if outcome.get("via") == "stow-rs":
        return list(outcome.get("sop_instance_uids") or [])
    uids = [uid for peer in outcome.get("peers") or [] for uid in peer.get("sop_instance_uids") or []]
    return list(dict.fromkeys(uids))


def export_model(row: dict[str, Any] | None) -> ExportState | None:
    if not row:
        return None
    target = row.get("target") or {}
    destination = target.get("server") if target.get("via") == "stow-rs" else ", ".join(target.get("peers") or [])
    retry_at = row.get("next_attempt_at") if row["state"] == "pending" and row.get("attempts") else None
    peers = (row.get("outcome") or {}).get("peers") if target.get("via") == "c-store" else None
    return ExportState(
        state=row["state"], via=target.get("via", "stow-rs"), destination=destination or "",
        after_review=bool(target.get("after_review", True)), study_uid=target.get("study_uid"),
        attempts=row.get("attempts") or 0, last_attempt_at=_iso(row.get("last_attempt_at")),
        next_attempt_at=_iso(retry_at), done_at=_iso(row.get("done_at")),
        sop_instance_uids=_stored_uids(row.get("outcome")) if row["state"] == "done" else [],
        peers=[DimseExport(**item) for item in peers] if peers else None,
        error=ProblemDetails(**row["last_error"]) if row.get("last_error") and row["state"] != "done" else None)


class AuditEvent(BaseModel):
    """One entry of a job's audit log (table ``job_events``), oldest first."""

    model_config = CLOSED

    at: str = Field(description="When, ISO 8601 UTC.")
    event: str = Field(description="What happened: queued, claimed, succeeded, failed, canceled, cancel_requested, "
                                   "lease_expired, released[:reason], reviewed, export_awaiting_review, "
                                   "export_queued, export_skipped, export_retry, exported, export_failed.")
    actor: str = Field(description="Who: 'key:' and 8 hex digits of the API key's SHA-256 (never the key) or "
                                   "'anonymous' for the submitter and reviewers; 'worker:<id>' for a worker; "
                                   "'service' for the service itself (recovery, exports).")
    attempt: int | None = Field(None, description="The job's (or the export's) attempt, where it counts.")
    details: dict[str, Any] | None = Field(
        None, description="reviewed: decision and comment; export events: the target (via, server or peers, "
                          "study_uid), what was stored, or the pacs-error of the attempt.")


class AuditLog(BaseModel):
    model_config = CLOSED

    job_id: str
    items: list[AuditEvent] = Field(description="Every event of the job, oldest first.")


SUBMITTER_EVENTS = ("queued", "canceled", "cancel_requested")


def audit_event(row: dict[str, Any], owner: str) -> AuditEvent:
    """A ``job_events`` row as shown to the job's owner (``owner``: the job's principal)."""
    details = json.loads(row["detail"]) if row.get("detail") else None
    if row["event"] == "reviewed" and isinstance(details, dict):
        actor = str(details.get("by") or "anonymous")
        details = {key: details[key] for key in ("decision", "comment") if key in details}
    elif row.get("worker_id"):
        actor = "worker:" + str(row["worker_id"])
    elif row["event"] in SUBMITTER_EVENTS:
        actor = reviewer_label(owner)
    else:
        actor = "service"
    return AuditEvent(at=_iso(row["at"]) or "", event=row["event"], actor=actor, attempt=row.get("attempt"),
                      details=details)
