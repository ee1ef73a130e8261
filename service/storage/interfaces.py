"""The job store by concern: a small interface each, implemented on the one schema (:mod:`service.storage.schema`).

* :class:`Jobs` — the API's side of the job table: create (idempotently), read (:class:`JobReader`), list, cancel,
  delete;
* :class:`Leases` — the workers' and the sweeper's side: claim, heartbeat, complete, release, recover (the lease
  protocol: :mod:`service.storage.leases`), the case a worker read, worker liveness, retention;
* :class:`Reviews` — a person's review of a finished job and the audit log of every transition;
* :class:`Deliveries` — completion callbacks and PACS exports (at once or after a review), each leased like a job;
* :class:`DicomInbox` — the DICOM node's durable index of received instances.

:class:`JobStore` is the first four together, what :class:`~service.storage.store.SqlJobStore` is; code that
needs one concern takes that one: the API's routes (``service.api.deps``: ``JobsStore``, ``ReviewStore``) and the
intake (``IntakeContext.jobs``) :class:`Jobs`, a worker :class:`Leases`, the callback and export deliverers
:class:`DeliveryStore`, the sweeper and the executors' upkeep :class:`Upkeep`, the DICOM node :class:`DicomInbox`.
Only the code that opens the store (``store_for``: the service context, a worker's claim loop) holds all of it.
"""

from __future__ import annotations

from typing import Any, Protocol

from .records import JobRecord, StoredInstance


class JobReader(Protocol):
    def get(self, job_id: str) -> JobRecord | None:
        """The job with its callback's delivery state, its PACS export and its previous job."""


class Jobs(JobReader, Protocol):
    def create(self, job: JobRecord) -> tuple[JobRecord, bool]:
        """Insert; with an idempotency key already used by ``job.owner``: the existing job and ``False`` if its
        request hash matches, else :class:`~service.storage.records.ConflictError`."""

    def find_idempotent(self, owner: str, key: str) -> JobRecord | None: ...

    def list(self, *, owner: str | None, status: str | None, limit: int, cursor: str | None,
             review: str | None = None, q: str | None = None) -> tuple[list[JobRecord], str | None]:
        """Newest first; ``q``: only jobs whose ``case_search`` contains it (case-insensitive)."""

    def count_by_status(self) -> dict[str, int]: ...

    def queued_count(self, owner: str | None = None) -> int: ...

    def request_cancel(self, job_id: str) -> JobRecord | None: ...

    def delete(self, job_id: str) -> list[str]:
        """Remove the job; returns the blob hashes no other job references any more."""

    def ping(self) -> bool:
        """True when the store accepts a write."""


class Leases(Protocol):
    def claim(self, worker_id: str, lease_seconds: float) -> JobRecord | None: ...

    def claim_job(self, job_id: str, worker_id: str, lease_seconds: float) -> JobRecord | None:
        """Claim one given job (same guard as :meth:`claim`); None when it is not queued."""

    def queued_since(self, before: float, limit: int = 1000) -> list[str]:
        """Ids of queued jobs not updated since ``before`` (oldest first)."""

    def set_case(self, job_id: str, case: dict[str, Any], search: str | None) -> None:
        """Record whose case a job is, once its inputs were read (jobs by PACS reference: by the worker holding it;
        implemented with the job rows, :mod:`service.storage.jobrows`)."""

    def heartbeat(self, job_id: str, worker_id: str, lease_seconds: float,
                  progress: dict | None = None) -> tuple[bool, bool]:
        """Extend the lease (and store progress); returns ``(still_owned, cancel_requested)``."""

    def complete(self, job_id: str, worker_id: str, status: str, *, result: dict | None = None,
                 error: dict | None = None, artifacts: dict[str, str] | None = None, attempt: int | None = None,
                 export: dict | None = None) -> bool: ...

    def release(self, job_id: str, worker_id: str, *, reason: str | None = None) -> bool:
        """Give a claimed job back to the queue without using up an attempt."""

    def expire_claims(self, worker_prefix: str) -> int:
        """End the leases of a dead worker's running jobs now (worker ids starting with ``worker_prefix``)."""

    def recover_expired(self) -> tuple[list[str], list[str]]:
        """Requeue (or fail, when out of attempts) running jobs whose lease expired."""

    def expired_finished(self, before: float) -> list[str]: ...

    def referenced_blobs(self) -> set[str]: ...

    def worker_seen(self, worker_id: str, pid: int) -> None: ...

    def live_workers(self, since: float) -> int: ...

    def workers_seen_since(self, since: float) -> dict[int, float]:
        """``{pid: last_seen}`` of the workers seen at or after ``since`` (wall time)."""

    def finished_durations(self) -> list[tuple[str, float]]: ...


class Reviews(Protocol):
    def review(self, job_id: str, decision: str, comment: str, by: str) -> JobRecord | None:
        """Record a review on a finished job (replacing an earlier one; each is a ``reviewed`` event); None when
        the job is not finished (or gone)."""

    def events(self, job_id: str) -> list[dict[str, Any]]:
        """The job's audit log, oldest first."""


class Deliveries(Protocol):
    def due_callbacks(self, now: float, limit: int = 20) -> list[str]:
        """Jobs that ended whose callback is due (pending and its time has come, or its delivery lease expired)."""

    def claim_callback(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        """Take one due delivery (``attempts`` + 1); None when another deliverer has it or it is not due."""

    def finish_callback(self, job_id: str, attempt: int, *, state: str, status_code: int | None,
                        error: str | None, next_attempt_at: float | None) -> bool:
        """Record the outcome of delivery ``attempt`` (``delivered``, ``pending`` again, or ``failed``)."""

    def due_exports(self, now: float, limit: int = 20) -> list[str]:
        """Succeeded jobs not rejected whose export is due (pending and its time has come, or its lease expired)."""

    def claim_export(self, job_id: str, now: float, lease_seconds: float) -> dict[str, Any] | None:
        """Take one due export (``attempts`` + 1); None when another process has it or it is not due."""

    def renew_export(self, job_id: str, attempt: int, until: float) -> bool:
        """Extend the lease of export ``attempt`` while it runs; False when it is no longer that attempt's."""

    def finish_export(self, job_id: str, attempt: int, *, state: str, outcome: dict | None, error: dict | None,
                      next_attempt_at: float | None) -> bool:
        """Record export ``attempt``: ``done``, ``pending`` again (a retry) or ``failed``; an audit event each."""


class DeliveryStore(JobReader, Deliveries, Protocol):
    """What the callback and export deliverers use: their leased rows and the job each one delivers."""


class Upkeep(Jobs, Leases, Protocol):
    """What the sweeper and an executor's upkeep use: leases recovered, retention (a job deleted), the queue read."""


class JobStore(Jobs, Leases, Reviews, Deliveries, Protocol):
    """Every concern of the job database but the DICOM inbox (the API's, the workers' and the sweeper's store)."""


class DicomInbox(Protocol):
    """Received instances by study (their states: :mod:`service.storage.inbox`)."""

    def add(self, item: StoredInstance, association: str, state: str = "received") -> None: ...

    def commit_association(self, association: str) -> int: ...

    def interrupt_association(self, association: str) -> int: ...

    def interrupt_stale(self, live: set[str], older_than_seconds: float = 0.0) -> int: ...

    def promote_interrupted(self, wait_seconds: float, now: float | None = None) -> list[str]: ...

    def series(self, series_uid: str, sop_instance_uid: str | None = None) -> list[StoredInstance]: ...

    def stable_studies(self, quiet_seconds: float, now: float | None = None) -> list[str]: ...

    def study(self, study_uid: str) -> list[StoredInstance]: ...

    def mark_dispatched(self, study_uid: str, sop_instance_uids: list[str]) -> None: ...

    def counts(self) -> dict[str, int]: ...
