"""The job store: the single record of every job.

:class:`JobStore` is the interface the API, the workers and the sweeper use;
:class:`SqlJobStore` implements it on SQLAlchemy Core with portable SQL only (SQLite in
WAL mode by default, any SQLAlchemy URL by configuration, e.g. PostgreSQL later).

Lease protocol (all transitions are single conditional UPDATEs, so they are atomic
on any SQL database and never need a lock held across a round trip):

* **claim** — pick the oldest queued job, then ``UPDATE … SET status='running',
  worker_id=:me, lease_expires_at=now+lease, attempts=attempts+1 WHERE id=:id AND
  status='queued'``; one row changed means the job is ours, zero means another worker
  won the race and we try the next candidate.
* **heartbeat / progress** — ``UPDATE … SET lease_expires_at=… WHERE id=:id AND
  worker_id=:me AND status='running'``; zero rows means we lost the job (lease
  expired and it was taken over, or it was deleted) and the worker must stop.
* **complete** — the same ``WHERE worker_id=:me AND status='running'`` guard, so a job
  is completed at most once even if a presumed-dead worker comes back.
* **recover** — running jobs whose lease expired go back to ``queued`` (attempts
  left) or to ``failed`` with a reason (no attempts left).
"""

from __future__ import annotations

import abc
import base64
import json
import re
import secrets
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError

from .dbtimeouts import StoreTimeouts, engine_kwargs, install_postgres_deadlines, sqlite_busy_pragma
from .migrate import upgrade_database
from .schema import metadata  # noqa: F401 - re-exported (tests make databases of earlier versions from it)
from .schema import job_blobs, job_callbacks, job_events, job_exports, job_previous, jobs, probe, workers

STATUSES = ("queued", "running", "succeeded", "failed", "canceled")
FINISHED = ("succeeded", "failed", "canceled")
DECISIONS = ("approved", "rejected")
REVIEW_FILTERS = ("none", *DECISIONS)
"""``list(review=…)``: jobs never reviewed, or whose latest review has this decision."""
EXPORT_STATES = ("awaiting_review", "pending", "exporting", "done", "failed", "skipped")
"""A held PACS export (service/jobs/exports.py): held until approved, then leased and stored like a callback."""


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
    export: dict[str, Any] | None = None  # the held PACS export (export_after_review; read by ``get``)
    case: dict[str, Any] | None = None  # whose case (patient, study, series; engine case_identity): owner's eyes only
    case_search: str | None = None  # what ``list(q=…)`` matches (lower-case; engine case_search_text)


class ConflictError(Exception):
    """Idempotency key reused with another request body."""

    def __init__(self, existing: JobRecord):
        super().__init__("idempotency conflict")
        self.existing = existing


class JobStore(abc.ABC):
    """What the service needs from a job database (see the module docstring for the lease protocol)."""

    @abc.abstractmethod
    def create(self, job: JobRecord) -> tuple[JobRecord, bool]:
        """Insert; with an idempotency key already used by ``job.owner``: the existing job and
        ``False`` if its request hash matches, else :class:`ConflictError`."""

    @abc.abstractmethod
    def find_idempotent(self, owner: str, key: str) -> JobRecord | None: ...

    @abc.abstractmethod
    def get(self, job_id: str) -> JobRecord | None: ...

    @abc.abstractmethod
    def list(self, *, owner: str | None, status: str | None, limit: int, cursor: str | None,
             review: str | None = None, q: str | None = None) -> tuple[list[JobRecord], str | None]:
        """Newest first; ``q``: only jobs whose ``case_search`` contains it (case-insensitive)."""

    def set_case(self, job_id: str, case: dict[str, Any], search: str | None) -> None:
        """Record whose case a job is, once its inputs were read (jobs by PACS reference: by the worker)."""
        raise NotImplementedError

    @abc.abstractmethod
    def review(self, job_id: str, decision: str, comment: str, by: str) -> JobRecord | None:
        """Record a review on a finished job (replacing an earlier one; each is a ``reviewed`` event);
        None when the job is not finished (or gone)."""

    @abc.abstractmethod
    def count_by_status(self) -> dict[str, int]: ...

    @abc.abstractmethod
    def queued_count(self, owner: str | None = None) -> int: ...

    @abc.abstractmethod
    def request_cancel(self, job_id: str) -> JobRecord | None: ...

    @abc.abstractmethod
    def delete(self, job_id: str) -> list[str]:
        """Remove the job; returns the blob hashes no other job references any more."""

    @abc.abstractmethod
    def claim(self, worker_id: str, lease_seconds: float) -> JobRecord | None: ...

    def claim_job(self, job_id: str, worker_id: str, lease_seconds: float) -> JobRecord | None:
        """Claim one given job (same guard as :meth:`claim`); None when it is not queued."""
        raise NotImplementedError

    def queued_since(self, before: float, limit: int = 1000) -> list[str]:
        """Ids of queued jobs not updated since ``before`` (oldest first)."""
        raise NotImplementedError

    @abc.abstractmethod
    def heartbeat(self, job_id: str, worker_id: str, lease_seconds: float, progress: dict | None = None) -> tuple[bool, bool]:
        """Extend the lease (and store progress); returns ``(still_owned, cancel_requested)``."""

    @abc.abstractmethod
    def complete(self, job_id: str, worker_id: str, status: str, *, result: dict | None = None,
                 error: dict | None = None, artifacts: dict[str, str] | None = None, attempt: int | None = None,
                 export: dict | None = None) -> bool: ...

    @abc.abstractmethod
    def release(self, job_id: str, worker_id: str, *, reason: str | None = None) -> bool:
        """Give a claimed job back to the queue (worker shutting down, disk full), without using up an
        attempt; ``reason`` (e.g. ``disk_full``) is kept in the job's ``released`` event name."""

    def expire_claims(self, worker_prefix: str) -> int:
        """End the leases of a dead worker's running jobs now (worker ids starting with ``worker_prefix``)."""
        return 0

    @abc.abstractmethod
    def recover_expired(self) -> tuple[list[str], list[str]]:
        """Requeue (or fail, when out of attempts) running jobs whose lease expired."""

    @abc.abstractmethod
    def expired_finished(self, before: float) -> list[str]: ...

    @abc.abstractmethod
    def referenced_blobs(self) -> set[str]: ...

    @abc.abstractmethod
    def worker_seen(self, worker_id: str, pid: int) -> None: ...

    @abc.abstractmethod
    def live_workers(self, since: float) -> int: ...

    def workers_seen_since(self, since: float) -> dict[int, float]:
        """``{pid: last_seen}`` of the workers seen at or after ``since`` (wall time)."""
        raise NotImplementedError

    @abc.abstractmethod
    def finished_durations(self) -> list[tuple[str, float]]: ...

    @abc.abstractmethod
    def events(self, job_id: str) -> list[dict[str, Any]]: ...

    @abc.abstractmethod
    def ping(self) -> bool:
        """True when the store accepts a write."""

    # completion callbacks (service/jobs/callbacks.py): at-least-once, claimed with a lease like jobs
    def due_callbacks(self, now: float, limit: int = 20) -> list[str]:
        """Jobs that ended whose callback is due (pending and its time has come, or its delivery lease expired)."""
        raise NotImplementedError

    def claim_callback(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        """Take one due delivery (``attempts`` + 1); None when another deliverer has it or it is not due."""
        raise NotImplementedError

    def finish_callback(self, job_id: str, attempt: int, *, state: str, status_code: int | None,
                        error: str | None, next_attempt_at: float | None) -> bool:
        """Record the outcome of delivery ``attempt`` (``delivered``, ``pending`` again, or ``failed``)."""
        raise NotImplementedError

    # PACS exports held for review (service/jobs/exports.py): the same lease pattern as callbacks
    def due_exports(self, now: float, limit: int = 20) -> list[str]:
        """Approved succeeded jobs whose export is due (pending and its time has come, or its lease expired)."""
        raise NotImplementedError

    def claim_export(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        """Take one due export (``attempts`` + 1); None when another process has it or it is not due."""
        raise NotImplementedError

    def renew_export(self, job_id: str, attempt: int, until: float) -> bool:
        """Extend the lease of export ``attempt`` while it runs; False when it is no longer that attempt's."""
        raise NotImplementedError

    def finish_export(self, job_id: str, attempt: int, *, state: str, outcome: dict | None, error: dict | None,
                      next_attempt_at: float | None) -> bool:
        """Record export ``attempt``: ``done``, ``pending`` again (a retry) or ``failed``; an audit event each."""
        raise NotImplementedError


# ---- SQLAlchemy implementation -----------------------------------------------------------

EXPORT_COLUMNS = ("target", "state", "attempts", "next_attempt_at", "last_attempt_at", "done_at", "outcome",
                  "last_error")

CALLBACK_COLUMNS = ("url", "delivery_id", "state", "attempts", "next_attempt_at", "last_attempt_at", "delivered_at",
                    "last_status", "last_error")

def _dump(value: Any) -> str | None:
    return None if value is None else json.dumps(value, separators=(",", ":"))


def _load(text: str | None, default: Any = None) -> Any:
    return default if text is None else json.loads(text)


def _encode_cursor(created_at: float, job_id: str) -> str:
    return base64.urlsafe_b64encode(f"{created_at!r}|{job_id}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[float, str]:
    """Raises ``ValueError`` for a malformed cursor."""
    padded = cursor + "=" * (-len(cursor) % 4)
    created, job_id = base64.urlsafe_b64decode(padded.encode()).decode().split("|", 1)
    if len(job_id) > 32 or not job_id.isalnum():
        raise ValueError("bad cursor")
    return float(created), job_id


class SqlJobStore(JobStore):
    def __init__(self, url: str, *, create_schema: bool = True, timeouts: StoreTimeouts | None = None):
        self.url = url
        self.is_sqlite = url.startswith("sqlite")
        self.timeouts = timeouts or StoreTimeouts()
        self.engine = sa.create_engine(url, future=True, **engine_kwargs(url, self.timeouts))
        self.writer = self.engine
        install_postgres_deadlines(self.engine, self.timeouts)
        if self.is_sqlite:
            busy = sqlite_busy_pragma(self.timeouts)
            sa.event.listen(self.engine, "connect", lambda dbapi_conn, record: _sqlite_pragmas(dbapi_conn, record, busy))
            # BEGIN IMMEDIATE for writes keeps the conditional updates serialized without deadlock retries
            sa.event.listen(self.engine, "begin", _sqlite_begin)
        # writes take the database lock up front (BEGIN IMMEDIATE on SQLite), reads do not
        self.writer = self.engine.execution_options(dsareg_write=True)
        if create_schema:  # the schema migrations, under a lock (service/storage/migrate.py)
            upgrade_database(self.engine)

    def dispose(self) -> None:
        self.engine.dispose()

    # ---- helpers ---------------------------------------------------------------------------
    def _row_to_job(self, row: Any) -> JobRecord:
        m = row._mapping
        return JobRecord(
            id=m["id"], owner=m["owner"], status=m["status"], created_at=m["created_at"], updated_at=m["updated_at"],
            started_at=m["started_at"], finished_at=m["finished_at"], attempts=m["attempts"],
            max_attempts=m["max_attempts"], worker_id=m["worker_id"], lease_expires_at=m["lease_expires_at"],
            cancel_requested=bool(m["cancel_requested"]), options=_load(m["options"], {}), geometry=m["geometry"],
            inputs=[InputFile(**item) for item in _load(m["inputs"], [])], progress=_load(m["progress"]),
            result=_load(m["result"]), error=_load(m["error"]), artifacts=_load(m["artifacts"], {}) or {},
            warnings=_load(m["warnings"], []) or [], idempotency_key=m["idempotency_key"],
            request_hash=m["request_hash"], input_bytes=m["input_bytes"] or 0,
            review=_load(m["review"]), callback_url=m.get("cb_url"), previous_id=m.get("previous_id"),
            callback={name: m.get(f"cb_{name}") for name in CALLBACK_COLUMNS} if m.get("cb_url") else None,
            export=_export_row(m) if m.get("ex_state") else None,
            case=_load(m.get("case_identity")), case_search=m.get("case_search"),
        )

    def _event(self, conn: Any, job_id: str, event: str, worker_id: str | None = None, attempt: int | None = None,
               detail: dict | None = None) -> None:
        conn.execute(job_events.insert().values(job_id=job_id, at=time.time(), event=event, worker_id=worker_id,
                                                attempt=attempt, detail=_dump(detail)))

    # ---- API side ----------------------------------------------------------------------------
    def create(self, job: JobRecord) -> tuple[JobRecord, bool]:
        values = dict(  # noqa: C408 - column names as keywords
            id=job.id, owner=job.owner, status="queued", created_at=job.created_at, updated_at=job.created_at,
            attempts=0, max_attempts=job.max_attempts, cancel_requested=False, options=_dump(job.options),
            geometry=job.geometry, inputs=_dump([vars(f) for f in job.inputs]), warnings=_dump(job.warnings),
            idempotency_key=job.idempotency_key, request_hash=job.request_hash, input_bytes=job.input_bytes,
            artifacts=_dump({}), case_identity=_dump(job.case), case_search=job.case_search,
        )
        try:
            with self.writer.begin() as conn:
                conn.execute(jobs.insert().values(**values))
                for item in job.inputs:
                    conn.execute(job_blobs.insert().values(job_id=job.id, sha256=item.sha256, role=item.role))
                if job.callback_url:
                    conn.execute(job_callbacks.insert().values(
                        job_id=job.id, url=job.callback_url, delivery_id=uuid.uuid4().hex, state="pending",
                        attempts=0, next_attempt_at=0.0))
                if job.previous_id:
                    conn.execute(job_previous.insert().values(job_id=job.id, previous_id=job.previous_id))
                self._event(conn, job.id, "queued")
        except IntegrityError:
            if job.idempotency_key is None:
                raise
            existing = self.find_idempotent(job.owner, job.idempotency_key)
            if existing is None:
                raise
            if existing.request_hash != job.request_hash:
                raise ConflictError(existing) from None
            return existing, False
        stored = self.get(job.id)
        assert stored is not None
        return stored, True

    def find_idempotent(self, owner: str, key: str) -> JobRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(jobs).where(jobs.c.owner == owner, jobs.c.idempotency_key == key)).first()
        return None if row is None else self._row_to_job(row)

    def get(self, job_id: str) -> JobRecord | None:
        """The job, with its callback's delivery state and its previous job (outer joins)."""
        query = (sa.select(jobs, *(job_callbacks.c[name].label(f"cb_{name}") for name in CALLBACK_COLUMNS),
                           *(job_exports.c[name].label(f"ex_{name}") for name in EXPORT_COLUMNS),
                           job_previous.c.previous_id)
                 .select_from(jobs.outerjoin(job_callbacks, job_callbacks.c.job_id == jobs.c.id)
                              .outerjoin(job_exports, job_exports.c.job_id == jobs.c.id)
                              .outerjoin(job_previous, job_previous.c.job_id == jobs.c.id))
                 .where(jobs.c.id == job_id))
        with self.engine.connect() as conn:
            row = conn.execute(query).first()
        return None if row is None else self._row_to_job(row)

    def list(self, *, owner: str | None, status: str | None, limit: int, cursor: str | None,
             review: str | None = None, q: str | None = None) -> tuple[list[JobRecord], str | None]:
        query = sa.select(jobs, job_previous.c.previous_id).select_from(  # summaries link to a previous job
            jobs.outerjoin(job_previous, job_previous.c.job_id == jobs.c.id))
        if owner is not None:
            query = query.where(jobs.c.owner == owner)
        if status is not None:
            query = query.where(jobs.c.status == status)
        if review == "none":
            query = query.where(jobs.c.review_decision.is_(None))
        elif review is not None:
            query = query.where(jobs.c.review_decision == review)
        if q:
            pattern = "%" + q.lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
            query = query.where(jobs.c.case_search.like(pattern, escape="\\"))
        if cursor:
            created, job_id = decode_cursor(cursor)
            query = query.where(sa.or_(jobs.c.created_at < created, sa.and_(jobs.c.created_at == created, jobs.c.id < job_id)))
        query = query.order_by(jobs.c.created_at.desc(), jobs.c.id.desc()).limit(limit + 1)
        with self.engine.connect() as conn:
            rows = conn.execute(query).fetchall()
        records = [self._row_to_job(r) for r in rows[:limit]]
        next_cursor = _encode_cursor(records[-1].created_at, records[-1].id) if len(rows) > limit and records else None
        return records, next_cursor

    def set_case(self, job_id: str, case: dict[str, Any], search: str | None) -> None:
        with self.writer.begin() as conn:
            conn.execute(jobs.update().where(jobs.c.id == job_id)
                         .values(case_identity=_dump(case), case_search=search))

    def count_by_status(self) -> dict[str, int]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(jobs.c.status, sa.func.count()).group_by(jobs.c.status)).fetchall()
        counts = {s: 0 for s in STATUSES}
        counts.update({status: int(n) for status, n in rows})
        return counts

    def queued_count(self, owner: str | None = None) -> int:
        query = sa.select(sa.func.count()).select_from(jobs).where(jobs.c.status == "queued")
        if owner is not None:
            query = query.where(jobs.c.owner == owner)
        with self.engine.connect() as conn:
            return int(conn.execute(query).scalar_one())

    def request_cancel(self, job_id: str) -> JobRecord | None:
        now = time.time()
        with self.writer.begin() as conn:
            done = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.status == "queued")
                .values(status="canceled", finished_at=now, updated_at=now, cancel_requested=True)
            ).rowcount
            if done:
                self._event(conn, job_id, "canceled")
            else:
                flagged = conn.execute(
                    jobs.update().where(jobs.c.id == job_id, jobs.c.status == "running", jobs.c.cancel_requested.is_(False))
                    .values(cancel_requested=True, updated_at=now)
                ).rowcount
                if flagged:
                    self._event(conn, job_id, "cancel_requested")
        return self.get(job_id)

    def review(self, job_id: str, decision: str, comment: str, by: str) -> JobRecord | None:
        if decision not in DECISIONS:
            raise ValueError(decision)
        now = time.time()
        record = {"decision": decision, "comment": comment, "by": by, "at": now}
        with self.writer.begin() as conn:
            done = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.status.in_(FINISHED))
                .values(review_decision=decision, review=_dump(record), updated_at=now)
            ).rowcount
            if done:
                self._event(conn, job_id, "reviewed", detail=record)
                self._review_export(conn, job_id, decision, now)
        return self.get(job_id) if done else None

    def _review_export(self, conn: Any, job_id: str, decision: str, now: float) -> None:
        """The latest review decides a held export: approved → due now (also again after ``skipped`` or
        ``failed``); rejected → ``skipped`` unless it is already under way or done."""
        if decision == "approved":
            before, values = ("awaiting_review", "skipped", "failed"), {"state": "pending", "attempts": 0,
                                                                          "next_attempt_at": 0.0, "last_error": None}
        else:
            before, values = ("awaiting_review", "pending"), {"state": "skipped"}
        moved = conn.execute(job_exports.update().where(job_exports.c.job_id == job_id,
                                                        job_exports.c.state.in_(before)).values(**values)).rowcount
        if moved:
            self._event(conn, job_id, "export_queued" if decision == "approved" else "export_skipped")

    def delete(self, job_id: str) -> list[str]:
        with self.writer.begin() as conn:
            hashes = {r[0] for r in conn.execute(sa.select(job_blobs.c.sha256).where(job_blobs.c.job_id == job_id))}
            conn.execute(job_blobs.delete().where(job_blobs.c.job_id == job_id))
            conn.execute(job_events.delete().where(job_events.c.job_id == job_id))
            conn.execute(job_callbacks.delete().where(job_callbacks.c.job_id == job_id))
            conn.execute(job_exports.delete().where(job_exports.c.job_id == job_id))
            conn.execute(job_previous.delete().where(job_previous.c.job_id == job_id))
            conn.execute(jobs.delete().where(jobs.c.id == job_id))
            still = set()
            if hashes:
                still = {r[0] for r in conn.execute(sa.select(job_blobs.c.sha256).where(job_blobs.c.sha256.in_(hashes)))}
        return sorted(hashes - still)

    # ---- worker side -------------------------------------------------------------------------
    def claim(self, worker_id: str, lease_seconds: float) -> JobRecord | None:
        for _ in range(5):
            with self.engine.connect() as conn:
                candidates = conn.execute(
                    sa.select(jobs.c.id).where(jobs.c.status == "queued").order_by(jobs.c.created_at, jobs.c.id).limit(5)
                ).scalars().all()
            if not candidates:
                return None
            for job_id in candidates:
                job = self.claim_job(job_id, worker_id, lease_seconds)
                if job is not None:
                    return job
        return None

    def claim_job(self, job_id: str, worker_id: str, lease_seconds: float) -> JobRecord | None:
        now = time.time()
        with self.writer.begin() as conn:
            won = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.status == "queued").values(
                    status="running", worker_id=worker_id, lease_expires_at=now + lease_seconds,
                    attempts=jobs.c.attempts + 1, started_at=sa.func.coalesce(jobs.c.started_at, now),
                    updated_at=now, progress=None,
                )
            ).rowcount
            if won:
                attempt = conn.execute(sa.select(jobs.c.attempts).where(jobs.c.id == job_id)).scalar_one()
                self._event(conn, job_id, "claimed", worker_id, attempt)
        return self.get(job_id) if won else None

    def queued_since(self, before: float, limit: int = 1000) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(
                sa.select(jobs.c.id).where(jobs.c.status == "queued", jobs.c.updated_at < before)
                .order_by(jobs.c.created_at, jobs.c.id).limit(limit)
            ).scalars())

    def heartbeat(self, job_id: str, worker_id: str, lease_seconds: float, progress: dict | None = None) -> tuple[bool, bool]:
        now = time.time()
        values: dict[str, Any] = {"lease_expires_at": now + lease_seconds, "updated_at": now}
        if progress is not None:
            values["progress"] = _dump(progress)
        with self.writer.begin() as conn:
            owned = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.worker_id == worker_id, jobs.c.status == "running").values(**values)
            ).rowcount
            if not owned:
                return False, False
            cancel = conn.execute(sa.select(jobs.c.cancel_requested).where(jobs.c.id == job_id)).scalar_one()
        return True, bool(cancel)

    def complete(self, job_id: str, worker_id: str, status: str, *, result: dict | None = None,
                 error: dict | None = None, artifacts: dict[str, str] | None = None, attempt: int | None = None,
                 export: dict | None = None) -> bool:
        """Finish the job if this worker still owns it (``export``: a PACS target held for review, recorded in
        the same transaction, so a job that succeeded never loses it).

        With ``attempt``: also when its lease expired meanwhile (e.g. the database was down while
        the job finished) and the sweeper put it back in the queue, as long as no worker claimed it
        since (``status='queued' AND attempts=attempt``): the result is kept instead of running the
        job again, and it still completes at most once.
        """
        if status not in FINISHED:
            raise ValueError(status)
        now = time.time()
        owned = sa.and_(jobs.c.worker_id == worker_id, jobs.c.status == "running")
        if attempt is not None:
            owned = sa.or_(owned, sa.and_(jobs.c.status == "queued", jobs.c.worker_id.is_(None),
                                          jobs.c.attempts == attempt, jobs.c.cancel_requested.is_(False)))
        with self.writer.begin() as conn:
            done = conn.execute(
                jobs.update().where(jobs.c.id == job_id, owned).values(
                    status=status, finished_at=now, updated_at=now, lease_expires_at=None, result=_dump(result),
                    worker_id=worker_id,
                    error=_dump(error), artifacts=_dump(artifacts or {}),
                )
            ).rowcount
            if done:
                for name, digest in (artifacts or {}).items():
                    conn.execute(job_blobs.insert().values(job_id=job_id, sha256=digest, role=f"artifact:{name}"))
                attempt = conn.execute(sa.select(jobs.c.attempts).where(jobs.c.id == job_id)).scalar_one()
                self._event(conn, job_id, status, worker_id, attempt)
                if export is not None and status == "succeeded":
                    conn.execute(job_exports.insert().values(job_id=job_id, target=_dump(export),
                                                             state="awaiting_review", attempts=0, next_attempt_at=0.0))
                    self._event(conn, job_id, "export_awaiting_review", detail=export)
        return bool(done)

    def release(self, job_id: str, worker_id: str, *, reason: str | None = None) -> bool:
        now = time.time()
        with self.writer.begin() as conn:
            done = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.worker_id == worker_id, jobs.c.status == "running").values(
                    status="queued", worker_id=None, lease_expires_at=None, attempts=jobs.c.attempts - 1,
                    updated_at=now, progress=None,
                )
            ).rowcount
            if done:
                self._event(conn, job_id, f"released:{reason}"[:32] if reason else "released", worker_id)
        return bool(done)

    def expire_claims(self, worker_prefix: str) -> int:
        """End now the leases of the running jobs of a worker known dead (ids starting with ``worker_prefix``):
        the next :meth:`recover_expired` requeues them without waiting for the lease."""
        owned = sa.func.substr(jobs.c.worker_id, 1, len(worker_prefix)) == worker_prefix
        with self.writer.begin() as conn:
            return conn.execute(jobs.update().where(jobs.c.status == "running", owned)
                                .values(lease_expires_at=0.0)).rowcount

    def recover_expired(self) -> tuple[list[str], list[str]]:
        now = time.time()
        requeued: list[str] = []
        failed: list[str] = []
        with self.engine.connect() as conn:
            rows = conn.execute(
                sa.select(jobs.c.id, jobs.c.worker_id, jobs.c.attempts, jobs.c.max_attempts, jobs.c.cancel_requested)
                .where(jobs.c.status == "running", jobs.c.lease_expires_at < now)
            ).fetchall()
        for job_id, worker_id, attempts, max_attempts, cancel in rows:
            guard = (jobs.c.id == job_id, jobs.c.status == "running", jobs.c.worker_id == worker_id, jobs.c.lease_expires_at < now)
            with self.writer.begin() as conn:
                if cancel:
                    n = conn.execute(jobs.update().where(*guard).values(
                        status="canceled", finished_at=now, updated_at=now, lease_expires_at=None)).rowcount
                    if n:
                        self._event(conn, job_id, "canceled", worker_id, attempts)
                        failed.append(job_id)
                elif attempts < max_attempts:
                    n = conn.execute(jobs.update().where(*guard).values(
                        status="queued", worker_id=None, lease_expires_at=None, updated_at=now, progress=None)).rowcount
                    if n:
                        self._event(conn, job_id, "lease_expired", worker_id, attempts)
                        requeued.append(job_id)
                else:
                    error = {
                        "type": "https://dsareg.dev/problems/worker-lost", "title": "Worker lost", "status": 500,
                        "detail": f"no heartbeat from the job's worker within the lease on each of {attempts} attempts "
                                  "(the worker crashed or was killed, e.g. out of memory, or could not reach the "
                                  "job database)",
                        "instance": f"/v1/registrations/{job_id}",
                    }
                    n = conn.execute(jobs.update().where(*guard).values(
                        status="failed", finished_at=now, updated_at=now, lease_expires_at=None, error=_dump(error))).rowcount
                    if n:
                        self._event(conn, job_id, "failed", worker_id, attempts)
                        failed.append(job_id)
        return requeued, failed

    # ---- maintenance ---------------------------------------------------------------------------
    def expired_finished(self, before: float) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(
                sa.select(jobs.c.id).where(jobs.c.status.in_(FINISHED), jobs.c.finished_at < before)
            ).scalars())

    def referenced_blobs(self) -> set[str]:
        with self.engine.connect() as conn:
            return set(conn.execute(sa.select(job_blobs.c.sha256).distinct()).scalars())

    def worker_seen(self, worker_id: str, pid: int) -> None:
        now = time.time()
        with self.writer.begin() as conn:
            n = conn.execute(workers.update().where(workers.c.id == worker_id).values(last_seen=now)).rowcount
            if not n:
                conn.execute(workers.insert().values(id=worker_id, pid=pid, last_seen=now))
            conn.execute(workers.delete().where(workers.c.last_seen < now - 86400))

    def live_workers(self, since: float) -> int:
        with self.engine.connect() as conn:
            return int(conn.execute(sa.select(sa.func.count()).select_from(workers).where(workers.c.last_seen >= since)).scalar_one())

    def workers_seen_since(self, since: float) -> dict[int, float]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(workers.c.pid, workers.c.last_seen).where(workers.c.last_seen >= since)).all()
        seen: dict[int, float] = {}
        for pid, last_seen in rows:
            if pid is not None:
                seen[int(pid)] = max(float(last_seen), seen.get(int(pid), 0.0))
        return seen

    def finished_durations(self) -> list[tuple[str, float]]:
        with self.engine.connect() as conn:
            rows = conn.execute(
                sa.select(jobs.c.status, jobs.c.started_at, jobs.c.finished_at)
                .where(jobs.c.status.in_(FINISHED), jobs.c.started_at.is_not(None), jobs.c.finished_at.is_not(None))
            ).fetchall()
        return [(status, max(0.0, finished - started)) for status, started, finished in rows]

    def events(self, job_id: str) -> list[dict[str, Any]]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(job_events).where(job_events.c.job_id == job_id).order_by(job_events.c.seq)).fetchall()
        return [dict(r._mapping) for r in rows]

    # ---- completion callbacks ---------------------------------------------------------------
    def _due(self, now: float):
        pending = sa.and_(job_callbacks.c.state == "pending", job_callbacks.c.next_attempt_at <= now)
        abandoned = sa.and_(job_callbacks.c.state == "delivering", job_callbacks.c.lease_until < now)
        ended = sa.select(jobs.c.id).where(jobs.c.id == job_callbacks.c.job_id, jobs.c.status.in_(FINISHED)).exists()
        return sa.and_(sa.or_(pending, abandoned), ended)

    def due_callbacks(self, now: float, limit: int = 20) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(sa.select(job_callbacks.c.job_id).where(self._due(now))
                                     .order_by(job_callbacks.c.next_attempt_at).limit(limit)).scalars())

    def claim_callback(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        with self.writer.begin() as conn:
            won = conn.execute(job_callbacks.update().where(job_callbacks.c.job_id == job_id, self._due(now)).values(
                state="delivering", lease_until=now + lease_seconds, attempts=job_callbacks.c.attempts + 1,
                last_attempt_at=now)).rowcount
            if not won:
                return None
            row = conn.execute(sa.select(job_callbacks).where(job_callbacks.c.job_id == job_id)).first()
        return dict(row._mapping)

    def finish_callback(self, job_id: str, attempt: int, *, state: str, status_code: int | None,
                        error: str | None, next_attempt_at: float | None) -> bool:
        if state not in ("delivered", "pending", "failed"):
            raise ValueError(state)
        now = time.time()
        values: dict[str, Any] = {"state": state, "lease_until": None, "last_status": status_code,
                                  "last_error": None if error is None else error[:500]}
        if state == "delivered":
            values["delivered_at"] = now
        if next_attempt_at is not None:
            values["next_attempt_at"] = next_attempt_at
        with self.writer.begin() as conn:
            done = conn.execute(job_callbacks.update().where(
                job_callbacks.c.job_id == job_id, job_callbacks.c.state == "delivering",
                job_callbacks.c.attempts == attempt).values(**values)).rowcount
        return bool(done)

    # ---- PACS exports held for review -----------------------------------------------------------
    def _export_due(self, now: float):
        pending = sa.and_(job_exports.c.state == "pending", job_exports.c.next_attempt_at <= now)
        abandoned = sa.and_(job_exports.c.state == "exporting", job_exports.c.lease_until < now)
        approved = sa.select(jobs.c.id).where(jobs.c.id == job_exports.c.job_id, jobs.c.status == "succeeded",
                                              jobs.c.review_decision == "approved").exists()
        return sa.and_(sa.or_(pending, abandoned), approved)

    def due_exports(self, now: float, limit: int = 20) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(sa.select(job_exports.c.job_id).where(self._export_due(now))
                                     .order_by(job_exports.c.next_attempt_at).limit(limit)).scalars())

    def claim_export(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        with self.writer.begin() as conn:
            won = conn.execute(job_exports.update().where(job_exports.c.job_id == job_id, self._export_due(now)).values(
                state="exporting", lease_until=now + lease_seconds, attempts=job_exports.c.attempts + 1,
                last_attempt_at=now)).rowcount
            if not won:
                return None
            row = conn.execute(sa.select(job_exports).where(job_exports.c.job_id == job_id)).first()
        return {**dict(row._mapping), "target": _load(row._mapping["target"])}

    def renew_export(self, job_id: str, attempt: int, until: float) -> bool:
        """Extend the lease of an export attempt still running (same attempt, still ``exporting``)."""
        with self.writer.begin() as conn:
            return bool(conn.execute(job_exports.update().where(
                job_exports.c.job_id == job_id, job_exports.c.state == "exporting",
                job_exports.c.attempts == attempt).values(lease_until=until)).rowcount)

    def finish_export(self, job_id: str, attempt: int, *, state: str, outcome: dict | None, error: dict | None,
                      next_attempt_at: float | None) -> bool:
        if state not in ("done", "pending", "failed"):
            raise ValueError(state)
        values: dict[str, Any] = {"state": state, "lease_until": None, "outcome": _dump(outcome),
                                  "last_error": _dump(error)}
        if state == "done":
            values["done_at"] = time.time()
        if next_attempt_at is not None:
            values["next_attempt_at"] = next_attempt_at
        event = {"done": "exported", "pending": "export_retry", "failed": "export_failed"}[state]
        with self.writer.begin() as conn:
            done = conn.execute(job_exports.update().where(
                job_exports.c.job_id == job_id, job_exports.c.state == "exporting",
                job_exports.c.attempts == attempt).values(**values)).rowcount
            if done:
                self._event(conn, job_id, event, attempt=attempt, detail=outcome if state == "done" else error)
        return bool(done)

    def ping(self) -> bool:
        try:
            with self.writer.begin() as conn:
                n = conn.execute(probe.update().where(probe.c.id == 1).values(at=time.time())).rowcount
                if not n:
                    conn.execute(probe.insert().values(id=1, at=time.time()))
            return True
        except Exception:  # noqa: BLE001 - readiness must answer, not raise
            return False


def _export_row(m: Any) -> dict[str, Any]:
    row = {name: m.get(f"ex_{name}") for name in EXPORT_COLUMNS}
    return {**row, "target": _load(row["target"], {}), "outcome": _load(row["outcome"]),
            "last_error": _load(row["last_error"])}


def _sqlite_begin(conn: Any) -> None:
    conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("dsareg_write") else "BEGIN")


def _sqlite_pragmas(dbapi_conn: Any, _record: Any, busy_pragma: str) -> None:
    # let SQLAlchemy's "begin" event issue BEGIN IMMEDIATE itself
    dbapi_conn.isolation_level = None
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute(busy_pragma)  # short: a writer frozen with the lock must not hang requests (dbtimeouts)
    cur.execute("PRAGMA foreign_keys=ON")
    cur.close()


def store_outage_errors() -> tuple[type[BaseException], ...]:
    """Exceptions meaning "the job database is unreachable or busy" (connection refused or lost, pool
    timeout, SQLite locked): answered 503 by the API, retried by workers; not bugs."""
    return (sa.exc.OperationalError, sa.exc.InterfaceError, sa.exc.TimeoutError)


def open_store(url: str) -> JobStore:
    return SqlJobStore(url)


def store_for(settings: Any, *, create_schema: bool = True) -> SqlJobStore:
    """The job store of ``settings`` with its database timeouts."""
    return SqlJobStore(settings.effective_database_url, create_schema=create_schema,
                       timeouts=StoreTimeouts.from_settings(settings))


def random_token(n: int = 6) -> str:
    return secrets.token_hex(n)


def iter_chunks(items: Iterable[str], size: int) -> Iterable[list[str]]:
    chunk: list[str] = []
    for item in items:
        chunk.append(item)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk
