"""The API's side of the job table (:class:`~service.storage.interfaces.Jobs`): create, read, list, cancel,
delete; and how a row becomes a :class:`~service.storage.records.JobRecord` (:func:`read_job`, shared by every
concern that answers with a job)."""

from __future__ import annotations

import time
from typing import Any

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError

from .audit import record_event
from .database import OnDatabase
from .deliveries import add_callback, callback_of, delete_deliveries, delivery_columns, export_of
from .records import STATUSES, ConflictError, InputFile, JobRecord, decode_cursor, dump_json, encode_cursor, load_json
from .schema import dimse_instances, job_blobs, job_callbacks, job_events, job_exports, job_previous, jobs


def row_to_job(row: Any) -> JobRecord:
    m = row._mapping
    return JobRecord(
        id=m["id"], owner=m["owner"], status=m["status"], created_at=m["created_at"], updated_at=m["updated_at"],
        started_at=m["started_at"], finished_at=m["finished_at"], attempts=m["attempts"],
        max_attempts=m["max_attempts"], worker_id=m["worker_id"], lease_expires_at=m["lease_expires_at"],
        cancel_requested=bool(m["cancel_requested"]), options=load_json(m["options"], {}), geometry=m["geometry"],
        inputs=[InputFile(**item) for item in load_json(m["inputs"], [])], progress=load_json(m["progress"]),
        result=load_json(m["result"]), error=load_json(m["error"]), artifacts=load_json(m["artifacts"], {}) or {},
        warnings=load_json(m["warnings"], []) or [], idempotency_key=m["idempotency_key"],
        request_hash=m["request_hash"], input_bytes=m["input_bytes"] or 0,
        review=load_json(m["review"]), callback_url=m.get("cb_url"), previous_id=m.get("previous_id"),
        callback=callback_of(m), export=export_of(m),
        case=load_json(m.get("case_identity")), case_search=m.get("case_search"),
    )


def read_job(engine: sa.Engine, job_id: str) -> JobRecord | None:
    """The job with its callback's delivery state, its PACS export and its previous job (outer joins)."""
    query = (sa.select(jobs, *delivery_columns(), job_previous.c.previous_id)
             .select_from(jobs.outerjoin(job_callbacks, job_callbacks.c.job_id == jobs.c.id)
                          .outerjoin(job_exports, job_exports.c.job_id == jobs.c.id)
                          .outerjoin(job_previous, job_previous.c.job_id == jobs.c.id))
             .where(jobs.c.id == job_id))
    with engine.connect() as conn:
        row = conn.execute(query).first()
    return None if row is None else row_to_job(row)


class SqlJobs(OnDatabase):
    """:class:`~service.storage.interfaces.Jobs` on SQLAlchemy Core."""

    def create(self, job: JobRecord) -> tuple[JobRecord, bool]:
        values = dict(  # noqa: C408 - column names as keywords
            id=job.id, owner=job.owner, status="queued", created_at=job.created_at, updated_at=job.created_at,
            attempts=0, max_attempts=job.max_attempts, cancel_requested=False, options=dump_json(job.options),
            geometry=job.geometry, inputs=dump_json([vars(f) for f in job.inputs]), warnings=dump_json(job.warnings),
            idempotency_key=job.idempotency_key, request_hash=job.request_hash, input_bytes=job.input_bytes,
            artifacts=dump_json({}), case_identity=dump_json(job.case), case_search=job.case_search,
        )
        try:
            with self.writer.begin() as conn:
                conn.execute(jobs.insert().values(**values))
                for item in job.inputs:
                    conn.execute(job_blobs.insert().values(job_id=job.id, sha256=item.sha256, role=item.role))
                if job.callback_url:
                    add_callback(conn, job.id, job.callback_url)
                if job.previous_id:
                    conn.execute(job_previous.insert().values(job_id=job.id, previous_id=job.previous_id))
                record_event(conn, job.id, "queued")
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
        return None if row is None else row_to_job(row)

    def get(self, job_id: str) -> JobRecord | None:
        """The job, with its callback's delivery state, its PACS export and its previous job (outer joins)."""
        return read_job(self.engine, job_id)

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
        records = [row_to_job(r) for r in rows[:limit]]
        next_cursor = encode_cursor(records[-1].created_at, records[-1].id) if len(rows) > limit and records else None
        return records, next_cursor

    def set_case(self, job_id: str, case: dict[str, Any], search: str | None) -> None:
        with self.writer.begin() as conn:
            conn.execute(jobs.update().where(jobs.c.id == job_id)
                         .values(case_identity=dump_json(case), case_search=search))

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
                record_event(conn, job_id, "canceled")
            else:
                flagged = conn.execute(
                    jobs.update().where(jobs.c.id == job_id, jobs.c.status == "running", jobs.c.cancel_requested.is_(False))
                    .values(cancel_requested=True, updated_at=now)
                ).rowcount
                if flagged:
                    record_event(conn, job_id, "cancel_requested")
        return self.get(job_id)

    def delete(self, job_id: str) -> list[str]:
        with self.writer.begin() as conn:
            hashes = {r[0] for r in conn.execute(sa.select(job_blobs.c.sha256).where(job_blobs.c.job_id == job_id))}
            conn.execute(job_blobs.delete().where(job_blobs.c.job_id == job_id))
            conn.execute(job_events.delete().where(job_events.c.job_id == job_id))
            delete_deliveries(conn, job_id)
            conn.execute(job_previous.delete().where(job_previous.c.job_id == job_id))
            conn.execute(jobs.delete().where(jobs.c.id == job_id))
            still = set()
            if hashes:
                still = {r[0] for r in conn.execute(sa.select(job_blobs.c.sha256).where(job_blobs.c.sha256.in_(hashes)))}
                still |= set(conn.execute(sa.select(dimse_instances.c.sha256)  # the inbox's: its own retention
                                          .where(dimse_instances.c.sha256.in_(hashes))).scalars())
        return sorted(hashes - still)

    def ping(self) -> bool:
        return self.database.ping()
