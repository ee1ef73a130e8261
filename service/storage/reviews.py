"""A person's review of a finished job and the audit log (:class:`~service.storage.interfaces.Reviews`).

The latest review is kept on the job (``review_decision`` for filtering, ``review`` for the page); every review
is also a ``reviewed`` event of the audit log, which holds every transition of the job
(:func:`~service.storage.audit.record_event`). A review decides the job's PACS export in the same
transaction (:func:`~service.storage.deliveries.decide_export`).
"""

from __future__ import annotations

import time
from typing import Any

import sqlalchemy as sa

from .audit import record_event
from .database import OnDatabase
from .deliveries import decide_export
from .jobrows import read_job
from .records import DECISIONS, FINISHED, JobRecord, dump_json
from .schema import job_events, jobs


class SqlReviews(OnDatabase):
    """:class:`~service.storage.interfaces.Reviews` on SQLAlchemy Core."""

    def review(self, job_id: str, decision: str, comment: str, by: str) -> JobRecord | None:
        if decision not in DECISIONS:
            raise ValueError(decision)
        now = time.time()
        record = {"decision": decision, "comment": comment, "by": by, "at": now}
        with self.writer.begin() as conn:
            done = conn.execute(
                jobs.update().where(jobs.c.id == job_id, jobs.c.status.in_(FINISHED))
                .values(review_decision=decision, review=dump_json(record), updated_at=now)
            ).rowcount
            if done:
                record_event(conn, job_id, "reviewed", detail=record)
                decide_export(conn, job_id, decision)
        return read_job(self.engine, job_id) if done else None

    def events(self, job_id: str) -> list[dict[str, Any]]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(job_events).where(job_events.c.job_id == job_id)
                                .order_by(job_events.c.seq)).fetchall()
        return [dict(r._mapping) for r in rows]
