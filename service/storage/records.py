"""What the job store holds and answers, independent of how: job records, their states, ids, list cursors.

Plain data (no database): the API, the workers and every storage concern (:mod:`service.storage.interfaces`)
share these types.
"""

from __future__ import annotations

import base64
import json
import re
import secrets
import uuid
from dataclasses import dataclass, field
from typing import Any

STATUSES = ("queued", "running", "succeeded", "failed", "canceled")
FINISHED = ("succeeded", "failed", "canceled")
DECISIONS = ("approved", "rejected")
REVIEW_FILTERS = ("none", *DECISIONS)
"""``list(review=…)``: jobs never reviewed, or whose latest review has this decision."""
EXPORT_STATES = ("awaiting_review", "pending", "exporting", "done", "failed", "skipped")
"""A job's PACS export (service/jobs/exports.py): pending at once (or held until approved), then leased and stored like
a callback, outside the registration worker."""


def new_job_id() -> str:
    """Server-made, unguessable, URL-safe (never derived from user input)."""
    return uuid.uuid4().hex


JOB_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""What a job id may look like (new ones are 32 hex digits): checked before any id from a request reaches
the database, so a NUL, an over-long or a non-id string is a plain 404 on every store (PostgreSQL refuses
NUL in text with a DataError that used to become a 500)."""


def is_job_id(text: str) -> bool:
    return JOB_ID_PATTERN.fullmatch(text) is not None


@dataclass
class InputFile:
    role: str  # mesh | volume | ap | lat | geometry
    sha256: str
    size: int
    suffix: str  # sanitized extension, e.g. ".obj" (the only part of a client file name kept)


@dataclass
class JobRecord:
    id: str
    owner: str
    status: str
    created_at: float
    updated_at: float
    started_at: float | None = None
    finished_at: float | None = None
    attempts: int = 0
    max_attempts: int = 3
    worker_id: str | None = None
    lease_expires_at: float | None = None
    cancel_requested: bool = False
    options: dict[str, Any] = field(default_factory=dict)
    geometry: str | None = None  # canonical geometry JSON; older rows: a preset name or compact JSON (engine_adapter.job_geometry)
    inputs: list[InputFile] = field(default_factory=list)
    progress: dict[str, Any] | None = None
    result: dict[str, Any] | None = None
    error: dict[str, Any] | None = None
    artifacts: dict[str, str] = field(default_factory=dict)  # name -> sha256
    warnings: list[str] = field(default_factory=list)
    idempotency_key: str | None = None
    request_hash: str | None = None
    input_bytes: int = 0
    callback_url: str | None = None  # set at creation (its delivery state: ``callback``)
    previous_id: str | None = None  # the job a tracking job started from (``POST …/track``)
    callback: dict[str, Any] | None = None  # delivery state of the completion callback (read by ``get``)
    review: dict[str, Any] | None = None  # {"decision", "comment", "by", "at" (epoch s)}: the latest review
    export: dict[str, Any] | None = None  # the PACS export (at once or after review; read by ``get``)
    case: dict[str, Any] | None = None  # whose case (patient, study, series; engine case_identity): owner's eyes only
    case_search: str | None = None  # what ``list(q=…)`` matches (lower-case; engine case_search_text)


@dataclass(frozen=True)
class StoredInstance:
    """A DICOM instance the node received (its bytes in the blob store under ``sha256``)."""

    sop_instance_uid: str
    study_uid: str
    series_uid: str
    sop_class_uid: str
    sha256: str
    size: int
    calling_ae: str
    received_at: float


class ConflictError(Exception):
    """Idempotency key reused with another request body."""

    def __init__(self, existing: JobRecord):
        super().__init__("idempotency conflict")
        self.existing = existing


def dump_json(value: Any) -> str | None:
    return None if value is None else json.dumps(value, separators=(",", ":"))


def load_json(text: str | None, default: Any = None) -> Any:
    return default if text is None else json.loads(text)


def encode_cursor(created_at: float, job_id: str) -> str:
    return base64.urlsafe_b64encode(f"{created_at!r}|{job_id}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[float, str]:
    """Raises ``ValueError`` for a malformed cursor."""
    padded = cursor + "=" * (-len(cursor) % 4)
    created, job_id = base64.urlsafe_b64decode(padded.encode()).decode().split("|", 1)
    if len(job_id) > 32 or not job_id.isalnum():
        raise ValueError("bad cursor")
    return float(created), job_id


def random_token(n: int = 6) -> str:
    return secrets.token_hex(n)
