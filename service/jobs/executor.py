"""Executors: what runs queued jobs. The job store is the queue; an executor only
provides workers that claim from it.

:class:`Executor` is deliberately small so that a later executor (Celery, Kubernetes
jobs…) can plug in: ``start``/``stop`` its workers, ``notify`` them that a job was
queued (a hint, workers also poll), and report how many are alive for ``/readyz``.
"""

from __future__ import annotations

import abc
import logging
import multiprocessing as mp
import os
import threading
import time
from typing import TYPE_CHECKING, Any

from .procwatch import WakeLink
from ..settings import ServiceSettings
from .worker import worker_id_prefix, worker_main

if TYPE_CHECKING:
    from ..storage.interfaces import Leases, Upkeep

log = logging.getLogger("dsareg.service.executor")


class Executor(abc.ABC):
    @abc.abstractmethod
    def start(self) -> None: ...

    @abc.abstractmethod
    def stop(self, timeout: float = 10.0) -> None: ...

    @abc.abstractmethod
    def notify(self) -> None:
        """A job was queued."""

    @abc.abstractmethod
    def alive_workers(self) -> int: ...

    def ready_workers(self) -> int:
        """Workers that can take a job now (warmed up); ``/readyz`` is 200 only when this is > 0."""
        return self.alive_workers()

    def submit(self, job_id: str) -> None:
        """A job was queued (the API calls this after inserting it)."""
        self.notify()

    def cancel(self, job_id: str) -> None:
        """Cancellation was requested in the job table (workers also read the flag)."""

    def requeued(self, job_ids: list[str]) -> None:
        """Jobs went back to ``queued`` (lease recovery)."""
        if job_ids:
            self.notify()

    def maintain(self, store: Upkeep) -> None:
        """Periodic work of the API's sweeper (e.g. re-dispatching jobs a broker lost)."""

    def describe(self) -> dict[str, Any]:
        return {"kind": type(self).__name__, "alive_workers": self.alive_workers()}


class NoExecutor(Executor):
    """API only: jobs stay queued until an external worker claims them."""

    def start(self) -> None:
        pass

    def stop(self, timeout: float = 10.0) -> None:
        pass

    def notify(self) -> None:
        pass

    def alive_workers(self) -> int:
        return 0


class EmbeddedProcessExecutor(Executor):
    """N worker processes (``spawn`` context) supervised by a thread of the server.

    Each worker has its own :class:`~service.jobs.procwatch.WakeLink` pipe (wake-up bytes; closing
    it stops the worker) instead of process-shared events, whose internal lock a SIGKILLed
    worker could leave held and so block every later notify."""

    def __init__(self, settings: ServiceSettings, workers: int | None = None, store: Leases | None = None):
        self.settings = settings
        self.store = store  # to tell warmed-up workers (they register in the store after warm-up) from warming ones
        self.count = settings.jobs.workers if workers is None else workers
        self.ctx = mp.get_context("spawn")
        self.links: list[WakeLink | None] = [None] * self.count
        self.processes: list[Any] = [None] * self.count
        self.spawned_at: list[float] = [0.0] * self.count  # wall time of each process's start
        self.restarts = 0
        self._supervisor: threading.Thread | None = None
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self._links_lock = threading.Lock()

    def _spawn(self, index: int) -> None:
        with self._links_lock:  # no notify writes to the old pipe once it is closed (its fd number may be reused)
            old, self.links[index] = self.links[index], None
        if old is not None:
            old.close()
        link = WakeLink(self.ctx)
        process = self.ctx.Process(
            target=worker_main, args=(self.settings, index, link.child_end(), os.getpid()),
            name=f"dsareg-worker-{index}", daemon=False,
        )
        self.spawned_at[index] = time.time()
        process.start()
        link.started()
        with self._links_lock:
            self.links[index] = link
        self.processes[index] = process
        log.info("worker process %d started (pid %s)", index, process.pid)

    def start(self) -> None:
        with self._lock:
            for index in range(self.count):
                self._spawn(index)
        self._supervisor = threading.Thread(target=self._supervise, name="worker-supervisor", daemon=True)
        self._supervisor.start()

    def _supervise(self) -> None:
        backoff = [0.0] * self.count
        while not self._halt.wait(1.0):
            with self._lock:
                for index, process in enumerate(self.processes):
                    if process is None or process.is_alive() or self._halt.is_set():
                        continue
                    if time.monotonic() < backoff[index]:
                        continue
                    log.warning("worker process %d (pid %s) exited with %s; restarting", index, process.pid, process.exitcode)
                    process.join(0)
                    self._requeue_jobs_of(index, process.pid)
                    self.restarts += 1
                    backoff[index] = time.monotonic() + 2.0
                    self._spawn(index)

    def _requeue_jobs_of(self, index: int, pid: int) -> None:
        """The dead worker's job goes back to the queue now, not when its lease ends (its attempt counts)."""
        if self.store is None:
            return
        try:
            if not self.store.expire_claims(worker_id_prefix(pid, index)):
                return
            requeued, failed = self.store.recover_expired()
        except Exception:  # the store out: the sweeper recovers the lease later
            log.exception("worker %d (pid %s) died; its job is requeued when its lease ends", index, pid)
            return
        for job_id in requeued:
            log.warning("job %s: its worker (pid %s) died, requeued at once", job_id, pid)
        for job_id in failed:
            log.warning("job %s: its worker (pid %s) died, no attempts left (or canceled)", job_id, pid)
        self.requeued(requeued)

    def notify(self) -> None:
        with self._links_lock:  # held only for non-blocking one-byte writes
            for link in self.links:
                if link is not None:
                    link.notify()

    def alive_workers(self) -> int:
        return sum(1 for p in self.processes if p is not None and p.is_alive())

    def ready_workers(self) -> int:
        """Live processes that registered in the store since they started: a worker registers only
        after its warm-up (compiling the kernels: minutes on a fresh install), so a warming worker
        is alive but not ready. Without a store (tests of the executor alone): the live ones."""
        if self.store is None:
            return self.alive_workers()
        try:
            seen = self.store.workers_seen_since(min(self.spawned_at, default=0.0))
        except Exception:  # noqa: BLE001 - the store being out is reported by /readyz's store check
            return 0
        return sum(1 for index, p in enumerate(self.processes)
                   if p is not None and p.is_alive() and seen.get(p.pid, 0.0) >= self.spawned_at[index])

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "ready_workers": self.ready_workers()}

    def pids(self) -> list[int]:
        return [p.pid for p in self.processes if p is not None and p.is_alive()]

    def stop(self, timeout: float = 10.0) -> None:
        self._halt.set()
        with self._lock, self._links_lock:  # no restart after this point: the supervisor checks _halt under _lock
            for index, link in enumerate(self.links):
                if link is not None:
                    link.close()
                self.links[index] = None
        deadline = time.monotonic() + timeout
        for process in self.processes:
            if process is not None:
                process.join(max(0.0, deadline - time.monotonic()))
        for process in self.processes:
            if process is not None and process.is_alive():
                log.warning("worker pid %s did not stop in time; terminating", process.pid)
                process.terminate()
                process.join(3)
                if process.is_alive():
                    process.kill()
                    process.join(3)
