"""The workers' and the sweeper's side of the job table (:class:`~service.storage.interfaces.Leases`).

Lease protocol (all transitions are single conditional UPDATEs, so they are atomic on any SQL database and
never need a lock held across a round trip):

* **claim** — pick the oldest queued job, then ``UPDATE … SET status='running', worker_id=:me,
  lease_expires_at=now+lease, attempts=attempts+1 WHERE id=:id AND status='queued'``; one row changed means the
  job is ours, zero means another worker won the race and we try the next candidate.
* **heartbeat / progress** — ``UPDATE … SET lease_expires_at=… WHERE id=:id AND worker_id=:me AND
  status='running'``; zero rows means we lost the job (lease expired and it was taken over, or it was deleted)
  and the worker must stop.
* **complete** — the same ``WHERE worker_id=:me AND status='running'`` guard, so a job is completed at most
  once even if a presumed-dead worker comes back.
* **recover** — running jobs whose lease expired go back to ``queued`` (attempts left) or to ``failed`` with a
  reason (no attempts left).

Also here: which workers are alive (``workers``), and what retention may remove.
"""

from __future__ import annotations

import time
from typing import Any

import sqlalchemy as sa

from .audit import record_event
from .database import OnDatabase
from .deliveries import queue_export
from .jobrows import read_job
from .records import FINISHED, JobRecord, dump_json
from .schema import dimse_instances, job_blobs, jobs, workers


class SqlLeases(OnDatabase):
    """:class:`~service.storage.interfaces.Leases` on SQLAlchemy Core."""

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
                record_event(conn, job_id, "claimed", worker_id, attempt)
        return read_job(self.engine, job_id) if won else None

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
            values["progress"] = dump_json(progress)
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
        """Finish the job if this worker still owns it (``export``: the PACS target of its results, due at once or
        held for review, recorded in the same transaction, so a job that succeeded never loses it).

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
                    status=status, finished_at=now, updated_at=now, lease_expires_at=None, result=dump_json(result),
                    worker_id=worker_id,
                    error=dump_json(error), artifacts=dump_json(artifacts or {}),
                )
            ).rowcount
            if done:
                for name, digest in (artifacts or {}).items():
                    conn.execute(job_blobs.insert().values(job_id=job_id, sha256=digest, role=f"artifact:{name}"))
                attempt = conn.execute(sa.select(jobs.c.attempts).where(jobs.c.id == job_id)).scalar_one()
                record_event(conn, job_id, status, worker_id, attempt)
                if export is not None and status == "succeeded":
                    queue_export(conn, job_id, export)
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
                record_event(conn, job_id, f"released:{reason}"[:32] if reason else "released", worker_id)
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
                        record_event(conn, job_id, "canceled", worker_id, attempts)
                        failed.append(job_id)
                elif attempts < max_attempts:
                    n = conn.execute(jobs.update().where(*guard).values(
                        status="queued", worker_id=None, lease_expires_at=None, updated_at=now, progress=None)).rowcount
                    if n:
                        record_event(conn, job_id, "lease_expired", worker_id, attempts)
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
                        status="failed", finished_at=now, updated_at=now, lease_expires_at=None, error=dump_json(error))).rowcount
                    if n:
                        record_event(conn, job_id, "failed", worker_id, attempts)
                        failed.append(job_id)
        return requeued, failed

    # ---- maintenance ---------------------------------------------------------------------------
    def expired_finished(self, before: float) -> list[str]:
        with self.engine.connect() as conn:
            return list(conn.execute(
                sa.select(jobs.c.id).where(jobs.c.status.in_(FINISHED), jobs.c.finished_at < before)
            ).scalars())

    def referenced_blobs(self) -> set[str]:
        """Digests a job or a received DICOM instance uses (the inbox's files go by its own retention,
        :mod:`.inbox_retention`: garbage collection used to remove a study's files while it waited for a volume)."""
        with self.engine.connect() as conn:
            used = set(conn.execute(sa.select(job_blobs.c.sha256).distinct()).scalars())
            return used | set(conn.execute(sa.select(dimse_instances.c.sha256).distinct()).scalars())

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
