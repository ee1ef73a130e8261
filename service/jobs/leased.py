"""The delivery loop shared by completion callbacks and held PACS exports (API process only).

Every ``POLL_SECONDS`` the loop asks the store what is due (:meth:`LeasedDeliverer.due`), takes
each item with a lease (:meth:`claim`: a conditional UPDATE, so two API replicas never run the
same attempt) and runs it on a small thread pool (:meth:`deliver`), never claiming more than the pool has
threads free: what is not under way waits in the table (unclaimed, taken by whichever replica is free), not in a
queue in memory whose leases would lapse before it starts. An API that dies mid-attempt
leaves the row with a lease; once it has passed, a deliverer (after a restart, or another
replica) takes it again: at least once, never lost. A deliverer with ``renewed_lease_seconds``
claims a short lease and renews it every third of it while the attempt runs (:meth:`renew`), so a
dead API's item is taken again after that short lease, whatever an attempt may take. A process
never claims an item its own pool is still delivering: an API frozen (SIGSTOP) past the lease
finishes its attempt when it resumes instead of starting a second one beside it.
"""

from __future__ import annotations

import abc
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from ..storage.store import store_outage_errors

log = logging.getLogger("dsareg.service.deliveries")

POLL_SECONDS = 0.25
DELIVERY_THREADS = 4


class LeasedDeliverer(abc.ABC):
    """A thread that claims due items from the store and delivers each on a thread pool."""

    name = "deliveries"
    renewed_lease_seconds: float | None = None  # None: the claim's lease covers a whole attempt

    def __init__(self, threads: int = DELIVERY_THREADS):
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._threads = threads
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix=self.name)
        self._inflight: set[str] = set()
        self._inflight_lock = threading.Lock()

    @abc.abstractmethod
    def due(self, now: float) -> list[str]:
        """Job ids whose item is due now."""

    @abc.abstractmethod
    def claim(self, job_id: str, now: float) -> dict[str, Any] | None:
        """Take the item with a lease; None when another deliverer has it or it is no longer due."""

    @abc.abstractmethod
    def deliver(self, row: dict[str, Any]) -> str:
        """One attempt of a claimed item; the state it left."""

    def renew(self, row: dict[str, Any], until: float) -> bool:
        """Extend the lease of a claimed item to ``until``; False when it is no longer ours."""
        return True

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._halt.set()
        self._thread.join(5)
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _run(self) -> None:
        while not self._halt.wait(POLL_SECONDS):
            try:
                self.deliver_due()
            except store_outage_errors() as exc:
                log.warning("%s skipped: job store unavailable (%s)", self.name, type(exc).__name__)
            except Exception:
                log.exception("%s round failed", self.name)

    def deliver_due(self) -> int:
        """Claim due items while the pool has a free thread and hand each to it; how many were claimed."""
        claimed = 0
        for job_id in self.due(time.time()):
            with self._inflight_lock:
                if len(self._inflight) >= self._threads:  # bounded: the rest stay due in the table
                    break
                if job_id in self._inflight:  # ours, still running (its lease lapsed while we were frozen)
                    continue
            row = self.claim(job_id, time.time())
            if row is not None:
                claimed += 1
                with self._inflight_lock:
                    self._inflight.add(job_id)
                self._pool.submit(self._deliver_logged, row)
        return claimed

    def _deliver_logged(self, row: dict[str, Any]) -> None:
        done = threading.Event()
        if self.renewed_lease_seconds:
            threading.Thread(target=self._keep_lease, args=(row, done), name=f"{self.name}-lease", daemon=True).start()
        try:
            self.deliver(row)
        except Exception:  # the lease expires and the item is tried again
            log.exception("job %s: %s attempt raised", row["job_id"], self.name)
        finally:
            done.set()
            with self._inflight_lock:
                self._inflight.discard(row["job_id"])

    def _keep_lease(self, row: dict[str, Any], done: threading.Event) -> None:
        lease = float(self.renewed_lease_seconds or 0.0)
        while not done.wait(lease / 3.0):
            try:
                if not self.renew(row, time.time() + lease):
                    log.warning("job %s: %s lease lost (taken over, or finished)", row["job_id"], self.name)
                    return
            except Exception:  # noqa: BLE001 - the store out: the lease may lapse, the item is tried again
                log.warning("job %s: %s lease not renewed (job store unavailable)", row["job_id"], self.name)
