"""Completion callbacks and PACS exports (:class:`~service.storage.interfaces.Deliveries`).

Both are at-least-once and leased like jobs: a due row is claimed by a conditional UPDATE (``attempts`` + 1, a
lease), its outcome recorded only by the attempt that holds it. A callback is due once its job ended. An export
row is written with its job's success (:func:`queue_export`): ``pending`` (due at once) when the server exports
at once, ``awaiting_review`` when it holds exports for a review (``export_after_review``), which an approval
makes ``pending`` (:func:`decide_export`). A pending export is due unless the job's latest review rejected it
(a held export is only ever pending after an approval, so for it this reads "approved"). The functions below
write these rows inside the job transactions that create them (:mod:`service.storage.jobrows`,
:mod:`service.storage.leases`, :mod:`service.storage.reviews`).
"""

from __future__ import annotations

import time
import uuid
from typing import Any

import sqlalchemy as sa

from .audit import record_event
from .database import OnDatabase
from .records import FINISHED, dump_json, load_json
from .schema import job_callbacks, job_exports, jobs

CALLBACK_COLUMNS = ("url", "delivery_id", "state", "attempts", "next_attempt_at", "last_attempt_at", "delivered_at",
                    "last_status", "last_error")
EXPORT_COLUMNS = ("target", "state", "attempts", "next_attempt_at", "last_attempt_at", "done_at", "outcome",
                  "last_error")


def delivery_columns() -> list[Any]:
    """The callback's and the export's columns a job read joins in (``cb_…``, ``ex_…``)."""
    return [*(job_callbacks.c[name].label(f"cb_{name}") for name in CALLBACK_COLUMNS),
            *(job_exports.c[name].label(f"ex_{name}") for name in EXPORT_COLUMNS)]


def callback_of(m: Any) -> dict[str, Any] | None:
    return {name: m.get(f"cb_{name}") for name in CALLBACK_COLUMNS} if m.get("cb_url") else None


def export_of(m: Any) -> dict[str, Any] | None:
    if not m.get("ex_state"):
        return None
    row = {name: m.get(f"ex_{name}") for name in EXPORT_COLUMNS}
    return {**row, "target": load_json(row["target"], {}), "outcome": load_json(row["outcome"]),
            "last_error": load_json(row["last_error"])}


def add_callback(conn: Any, job_id: str, url: str) -> None:
    conn.execute(job_callbacks.insert().values(job_id=job_id, url=url, delivery_id=uuid.uuid4().hex,
                                               state="pending", attempts=0, next_attempt_at=0.0))


def queue_export(conn: Any, job_id: str, target: dict) -> None:
    """A succeeded job's PACS export: due at once, or held until a review approves it (``target["after_review"]``,
    true when absent)."""
    held = bool(target.get("after_review", True))
    conn.execute(job_exports.insert().values(job_id=job_id, target=dump_json(target),
                                             state="awaiting_review" if held else "pending",
                                             attempts=0, next_attempt_at=0.0))
    record_event(conn, job_id, "export_awaiting_review" if held else "export_queued", detail=target)


def decide_export(conn: Any, job_id: str, decision: str) -> None:
    """The latest review decides the export (held or not): approved → due now (also again after ``skipped`` or
    ``failed``: an approval is how a failed export is tried again); rejected → ``skipped`` unless it is already
    under way or done (a rejected result is not sent on)."""
    if decision == "approved":
        before, values = ("awaiting_review", "skipped", "failed"), {"state": "pending", "attempts": 0,
                                                                      "next_attempt_at": 0.0, "last_error": None}
    else:
        before, values = ("awaiting_review", "pending"), {"state": "skipped"}
    moved = conn.execute(job_exports.update().where(job_exports.c.job_id == job_id,
                                                    job_exports.c.state.in_(before)).values(**values)).rowcount
    if moved:
        record_event(conn, job_id, "export_queued" if decision == "approved" else "export_skipped")


def delete_deliveries(conn: Any, job_id: str) -> None:
    conn.execute(job_callbacks.delete().where(job_callbacks.c.job_id == job_id))
    conn.execute(job_exports.delete().where(job_exports.c.job_id == job_id))


class SqlDeliveries(OnDatabase):
    """:class:`~service.storage.interfaces.Deliveries` on SQLAlchemy Core."""

    # ---- completion callbacks ---------------------------------------------------------------
    def _callback_due(self, now: float):
        pending = sa.and_(job_callbacks.c.state == "pending", job_callbacks.c.next_attempt_at <= now)
        abandoned = sa.and_(job_callbacks.c.state == "delivering", job_callbacks.c.lease_until < now)
        ended = sa.select(jobs.c.id).where(jobs.c.id == job_callbacks.c.job_id, jobs.c.status.in_(FINISHED)).exists()
        return sa.and_(sa.or_(pending, abandoned), ended)

    def due_callbacks(self, now: float, limit: int = 20) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(sa.select(job_callbacks.c.job_id).where(self._callback_due(now))
                                     .order_by(job_callbacks.c.next_attempt_at).limit(limit)).scalars())

    def claim_callback(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        with self.writer.begin() as conn:
            won = conn.execute(job_callbacks.update().where(job_callbacks.c.job_id == job_id, self._callback_due(now)).values(
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

    # ---- PACS exports ---------------------------------------------------------------------------
    def _export_due(self, now: float):
        pending = sa.and_(job_exports.c.state == "pending", job_exports.c.next_attempt_at <= now)
        abandoned = sa.and_(job_exports.c.state == "exporting", job_exports.c.lease_until < now)
        not_rejected = sa.or_(jobs.c.review_decision.is_(None), jobs.c.review_decision != "rejected")
        allowed = sa.select(jobs.c.id).where(jobs.c.id == job_exports.c.job_id, jobs.c.status == "succeeded",
                                             not_rejected).exists()
        return sa.and_(sa.or_(pending, abandoned), allowed)

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
        return {**dict(row._mapping), "target": load_json(row._mapping["target"]),
                "outcome": load_json(row._mapping["outcome"])}

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
        values: dict[str, Any] = {"state": state, "lease_until": None, "outcome": dump_json(outcome),
                                  "last_error": dump_json(error)}
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
                record_event(conn, job_id, event, attempt=attempt, detail=outcome if state == "done" else error)
        return bool(done)
