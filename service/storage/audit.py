"""The audit log's one writer: every transition of a job is a ``job_events`` row, written in the transaction
that makes the transition (read back by :meth:`service.storage.reviews.SqlReviews.events`)."""

from __future__ import annotations

import time
from typing import Any

from .records import dump_json
from .schema import job_events


def record_event(conn: Any, job_id: str, event: str, worker_id: str | None = None, attempt: int | None = None,
                 detail: dict | None = None) -> None:
    conn.execute(job_events.insert().values(job_id=job_id, at=time.time(), event=event, worker_id=worker_id,
                                            attempt=attempt, detail=dump_json(detail)))
