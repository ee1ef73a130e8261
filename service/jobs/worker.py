"""A worker: claims jobs from the store and runs them (one at a time).

One job is one straight path (:func:`_register`): its inputs (the stored blobs, or a DICOMweb
fetch) → :func:`service.engine_adapter.run_job`, the one call into the engine (read, register,
write every output, warnings joined there) → the artifacts and the result into the store. A job
is done when its registration is stored: the STOW-RS / C-STORE of its results into a PACS is
written with its completion as an export (:mod:`service.jobs.exports`) that the API process's
exporter carries out; a worker never waits on a PACS peer after the engine.

Runs in its own process (started by an executor with the ``spawn`` context). See
:mod:`service.storage.leases` for the lease protocol. A background thread renews the lease
every ``heartbeat`` seconds even when the engine reports no progress (loading,
writing), and reads the job's ``cancel_requested`` flag; the engine's
``should_stop`` callback then answers from memory.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from ..storage.blobs import BlobStore
from ..pacs.dicom_jobs import PacsJob, pacs_job, pacs_problem
from ..pacs.dicomweb import PacsError
from ..pacs.dimse.export import dimse_job
from .exports import export_target, source_of
from ..storage.diskspace import has_room, is_disk_full
from ..storage.shared_models import shared_models_for
from ..engine_adapter import (collect_artifacts, engine, fetched_case, model_cache, model_store, run_job,
                              stored_case_files, volume_model_key)
from ..problems import TYPE_BASE
from ..settings import ServiceSettings
from ..storage.interfaces import Leases
from ..storage.store import JobRecord, random_token, store_for, store_outage_errors

log = logging.getLogger("dsareg.service.worker")

SAVING_FRACTION = 0.99  # artifacts into the blob store, then the result into the job store


def worker_id_prefix(pid: int, index: int) -> str:
    """What every worker id of process ``pid`` (slot ``index``) on this host starts with."""
    return f"{socket.gethostname()[:40]}-{pid}-w{index}-"


def make_worker_id(index: int) -> str:
    return worker_id_prefix(os.getpid(), index) + random_token(3)


class _JobControl:
    """State shared by the engine callbacks and the heartbeat thread of one running job."""

    def __init__(self, store: Leases, job: JobRecord, worker_id: str, settings: ServiceSettings, stop: Any,
                 cancel_hint: Any = None):
        self.store = store
        self.cancel_hint = cancel_hint  # e.g. "the Celery task was revoked": cancel without waiting for a beat
        self.job = job
        self.worker_id = worker_id
        self.settings = settings
        self.stop_event = stop
        self.cancel = job.cancel_requested
        self.lost = False
        self.timed_out = False
        self.started = time.monotonic()
        self.last_progress_write = 0.0
        self.last_stage: str | None = None
        self.latest_progress: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def finish(self) -> None:
        self._done.set()
        self._thread.join(5)

    def _write(self, progress: dict | None) -> None:
        try:
            owned, cancel = self.store.heartbeat(self.job.id, self.worker_id, self.settings.jobs.lease_seconds, progress)
        except Exception:  # noqa: BLE001 - a database hiccup: try again next beat
            log.warning("job %s: heartbeat failed", self.job.id)
            return
        if not owned:
            self.lost = True
        self.cancel = self.cancel or cancel

    def _beat(self) -> None:
        interval = self.settings.jobs.effective_heartbeat_seconds
        while not self._done.wait(interval):
            with self._lock:
                pending = self.latest_progress
                self.latest_progress = None
            self._write(pending)
            if time.monotonic() - self.started > self.settings.jobs.job_timeout_seconds:
                self.timed_out = True

    def progress(self, update: dict) -> None:
        progress = {
            "stage": str(update.get("stage", "")),
            "iteration": int(update.get("iteration", 0) or 0),
            "loss": None if update.get("loss") is None else float(update["loss"]),
            "fraction": max(0.0, min(1.0, float(update.get("fraction", 0.0) or 0.0))),
        }
        now = time.monotonic()
        new_stage = progress["stage"] != self.last_stage  # a stage change is written at once (e.g. 'outputs')
        if new_stage or now - self.last_progress_write >= self.settings.jobs.progress_interval_seconds:
            self.last_progress_write, self.last_stage = now, progress["stage"]
            self._write(progress)
        else:
            with self._lock:
                self.latest_progress = progress

    def should_stop(self) -> bool:
        if not self.cancel and self.cancel_hint is not None and self.cancel_hint():
            self.cancel = True
        return self.cancel or self.lost or self.timed_out or self.stop_event.is_set()


def _problem(job_id: str, status: int, kind: str, title: str, detail: str, **extra: Any) -> dict[str, Any]:
    body = {"type": TYPE_BASE + kind, "title": title, "status": status, "detail": detail,
            "instance": f"/v1/registrations/{job_id}"}
    body.update({k: v for k, v in extra.items() if v is not None})
    return body


def is_store_outage(exc: BaseException) -> bool:
    """The job database is unreachable or busy (see :func:`service.storage.store.store_outage_errors`)."""
    return isinstance(exc, store_outage_errors())


def with_store_retries(call: Any, settings: ServiceSettings, what: str, job_id: str) -> Any:
    """``call()`` retried with exponential backoff while the store is out, for at most
    ``result_save_seconds``: a short database outage must not throw away a finished registration."""
    deadline = time.monotonic() + settings.jobs.result_save_seconds
    delay = 0.25
    while True:
        try:
            return call()
        except Exception as exc:
            if not is_store_outage(exc) or time.monotonic() + delay > deadline:
                raise
            log.warning("job %s: %s failed (%s); retrying in %.1f s", job_id, what, type(exc).__name__, delay)
            time.sleep(delay)
            delay = min(delay * 2.0, 5.0)


class _Finisher:
    """Guarded end-state writes of one claimed job, each with bounded retries on store outages."""

    def __init__(self, store: Leases, job: JobRecord, worker_id: str, settings: ServiceSettings):
        self.store, self.job, self.worker_id, self.settings = store, job, worker_id, settings

    def complete(self, status: str, **values: Any) -> str:
        """``status`` if written, ``'lost'`` if another worker owns the job or the store stayed out."""
        def write() -> bool:
            return self.store.complete(self.job.id, self.worker_id, status, attempt=self.job.attempts, **values)
        try:
            return status if with_store_retries(write, self.settings, f"saving '{status}'", self.job.id) else "lost"
        except Exception as exc:  # noqa: BLE001 - the lease expires and the sweeper requeues the job
            log.error("job %s: could not save '%s' (%s); the attempt is given up", self.job.id, status, type(exc).__name__)
            return "lost"

    def release(self, reason: str | None = None) -> str:
        try:
            with_store_retries(lambda: self.store.release(self.job.id, self.worker_id, reason=reason), self.settings,
                               "release", self.job.id)
        except Exception as exc:  # noqa: BLE001 - the lease expires and the sweeper requeues the job
            log.error("job %s: could not release (%s)", self.job.id, type(exc).__name__)
        return "released"


def run_one(store: Leases, blobs: BlobStore, job: JobRecord, worker_id: str, settings: ServiceSettings, stop: Any,
            cancel_hint: Any = None) -> str:
    """Run a claimed job to an end state; returns what happened (for logs and tests).

    ``cancel_hint``: optional callable, true when the job was canceled by other means than
    the job table's flag (the Celery executor passes "this task was revoked")."""
    control = _JobControl(store, job, worker_id, settings, stop, cancel_hint)
    finish = _Finisher(store, job, worker_id, settings)
    out_dir = blobs.job_work_dir(job.id) / f"{job.attempts}-{random_token(4)}"
    started = time.monotonic()
    log.info("job %s: runs on %s", job.id, _thread_budget())
    control.start()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)  # may itself find the disk full
        outcome = _register(blobs, job, settings, control, finish, out_dir)
    except Exception as exc:  # noqa: BLE001 - every failure ends the job in a state
        outcome = _ended_early(exc, job, settings, control, finish)
    finally:
        control.finish()
        shutil.rmtree(out_dir, ignore_errors=True)
        try:
            out_dir.parent.rmdir()
        except OSError:
            pass
    log.info("job %s: %s after %.2f s (attempt %d, %d input bytes)", job.id, outcome, time.monotonic() - started,
             job.attempts, job.input_bytes)
    return outcome


def _ended_early(exc: Exception, job: JobRecord, settings: ServiceSettings, control: _JobControl,
                 finish: _Finisher) -> str:
    """The end state of a job whose run raised ``exc``."""
    if isinstance(exc, engine.RegistrationCanceled):
        return _stopped(job, settings, control, finish)
    if is_disk_full(exc):  # not the job's fault either: hand it back, claimed again once there is room
        log.warning("job %s: no space left on the data disk for its outputs; released without using an attempt",
                    job.id)
        return finish.release(reason="disk_full")
    if isinstance(exc, PacsError):
        return finish.complete("failed", error=_problem(job.id, 502, "pacs-error", "PACS error", str(exc),
                                                        **pacs_problem(exc)))
    if isinstance(exc, engine.DsaregInputError):
        return finish.complete("failed", error=_problem(job.id, 422, "invalid-input", "Unprocessable input", str(exc),
                                                        field=exc.field, accepted=exc.accepted))
    if is_store_outage(exc):  # not the job's fault: hand it back without using up an attempt
        log.warning("job %s: the job store is out (%s); releasing the job", job.id, type(exc).__name__)
        return finish.release()
    log.error("job %s: internal error", job.id, exc_info=exc)
    return finish.complete("failed", error=_problem(
        job.id, 500, "internal-error", "Internal error",
        f"the registration failed because of an internal error (logged under job {job.id})"))


class DiskFloor:
    """Whether the data disk has room for a job's outputs (``min_free_bytes``); says so at WARNING once
    a minute while it has not (the job stays queued: nothing is claimed that could not be written)."""

    def __init__(self, settings: ServiceSettings):
        self.path = Path(settings.storage.data_dir)
        self.floor = settings.storage.min_free_bytes
        self.last_warning = 0.0

    def check(self) -> bool:
        if has_room(self.path, self.floor):
            return True
        if time.monotonic() - self.last_warning > 60.0:
            self.last_warning = time.monotonic()
            log.warning("the data disk has less than %d MiB free: no job is claimed until there is room",
                        self.floor // (1 << 20))
        return False


def _thread_budget() -> str:
    """The CPU threads torch and numba use *on this thread* (both settings are per thread)."""
    try:
        import numba
        import torch

        return f"{torch.get_num_threads()} torch / {numba.get_num_threads()} numba threads"
    except Exception:  # noqa: BLE001 - informative only
        return "unknown threads"


def _no_share() -> None:
    return None


def _shared_model(blobs: BlobStore, job: JobRecord, settings: ServiceSettings) -> Callable[[], None]:
    """Scale-out (the database blob backend): the model another node kept for this job's volume, pulled into this
    node's model folder before the job; returns what puts the model the job kept into the shared store."""
    shared = shared_models_for(settings, blobs, model_store(model_cache(settings.storage)))
    if shared is None:
        return _no_share
    try:
        key = volume_model_key(job.inputs, engine.parse_options(job.options), settings.limits.input_limits)
    except Exception:  # noqa: BLE001 - options the engine refuses: the job reports them
        return _no_share
    if key is None:
        return _no_share
    if shared.pull(key):
        log.info("job %s: the volume's model from the shared store", job.id)
    return partial(shared.push, key)


def _register(blobs: BlobStore, job: JobRecord, settings: ServiceSettings, control: _JobControl, finish: _Finisher,
              out_dir: Path) -> str:
    """Inputs → one engine call → artifacts and result into the store (both retried across store outages)."""
    pacs = pacs_job(job, blobs.read, settings)  # inputs by DICOMweb reference, or None
    dimse = dimse_job(job, blobs.read, settings)  # made from a study received over DIMSE, or None
    share = _no_share
    if pacs is None:
        files = stored_case_files(job.inputs, job.geometry, blobs.read, settings.limits.input_limits, blobs.read_head)
        share = _shared_model(blobs, job, settings)
    else:
        files = pacs.fetch()
        _record_case(finish.store, job, files, "dicomweb" if isinstance(pacs, PacsJob) else "dimse", settings)
    result = run_job(files, job.options, out_dir, limits=settings.limits.input_limits, control=control,
                     label=f"job {job.id}", dicom="best_effort" if pacs is None and dimse is None else "required",
                     models=model_cache(settings.storage))
    if control.lost:
        return "lost"
    share()
    carried_images(result, job.case)
    export = export_target(pacs, dimse, after_review=settings.jobs.export_after_review)  # sent by the exporter
    if pacs is not None or dimse is not None:
        result.setdefault("dicom", {})["source"] = source_of(pacs, dimse)
    control.progress({"stage": "saving", "iteration": 0, "loss": None, "fraction": SAVING_FRACTION})
    artifacts = with_store_retries(lambda: collect_artifacts(out_dir, blobs), settings, "storing artifacts", job.id)
    outcome = finish.complete("succeeded", result=result, artifacts=artifacts, export=export)
    if outcome == "succeeded":  # shared (identical) artifacts may have been removed by a concurrent delete
        for name, digest in artifacts.items():
            if not blobs.exists(digest):
                blobs.put_file(out_dir / name)
    return outcome


def carried_images(result: dict[str, Any], case: dict[str, Any] | None) -> None:
    """A tracking job's plane not sent again (``case.inputs[].carried_from``): its view in ``result`` names the
    earlier job whose run its image is (``image_from_job``)."""
    views = result.get("views") or {}
    for row in (case or {}).get("inputs") or []:
        if row.get("carried_from") and row.get("role") in views:
            views[row["role"]]["image_from_job"] = row["carried_from"]


def _record_case(store: Leases, job: JobRecord, files: Any, source: str, settings: ServiceSettings) -> None:
    """Whose case a job by PACS reference is, once its inputs were fetched (informative: never fails the job)."""
    case, search = fetched_case(files, source)
    try:
        with_store_retries(lambda: store.set_case(job.id, case, search), settings, "recording the case", job.id)
    except Exception:  # noqa: BLE001 - the registration goes on without it
        log.warning("job %s: the case identity was not recorded", job.id)


def _stopped(job: JobRecord, settings: ServiceSettings, control: _JobControl, finish: _Finisher) -> str:
    """The engine stopped early: canceled, lost lease, timed out, or worker shutting down."""
    if control.lost:
        return "lost"
    if control.cancel:
        return finish.complete("canceled")
    if control.timed_out:
        err = _problem(job.id, 500, "job-timeout", "Job timed out",
                       f"the registration did not finish within {settings.jobs.job_timeout_seconds:g} s; "
                       "try fewer starts, fewer iterations or a smaller working_size_px")
        return finish.complete("failed", error=err)
    return finish.release()  # worker shutting down: hand the job back


def warm_up(job: bool = True) -> None:
    """Load the engine, its compiled kernels and everything a job imports on first use, by running
    one tiny registration with all its outputs, before the first job (best effort): a fresh worker's
    first job otherwise costs ~1.5 CPU-s more than the next ones. ``job`` False (``DSAREG_WARM_UP_JOB=0``,
    for test servers): the kernels only."""
    import tempfile

    started = time.monotonic()
    log.info("worker warming up: compiling the numba kernels a job needs (two processes) and running one tiny job "
             "(about a minute on 2 cores on a fresh install with an empty kernel cache, a few seconds once cached; "
             "`dsareg warmup` fills the cache ahead)")
    try:
        engine.warm_up_kernels()
        if job:
            with tempfile.TemporaryDirectory(prefix="dsareg-warm-up-") as work_dir:
                engine.warm_up_job(Path(work_dir))
    except Exception:
        log.warning("warm-up incomplete; the first job will be slower", exc_info=True)
    log.info("worker warmed up in %.1f s%s; ready for jobs", time.monotonic() - started,
             "" if job else " (kernels only: DSAREG_WARM_UP_JOB=0)")
    try:  # tracking's and the pose search's kernels: a low-priority helper fills the cache while jobs run
        if engine.compile_later_groups() is not None:
            log.info("compiling tracking's and the pose search's kernels in the background (lowest priority)")
    except Exception:  # noqa: BLE001
        log.warning("could not start the background kernel compile; a first tracking job compiles them itself")


def worker_main(settings: ServiceSettings, index: int, link: Any = None, parent_pid: int | None = None) -> None:
    """Entry point of a worker process.

    ``link``: the read end of the server's :class:`~service.jobs.procwatch.WakeLink` (None for a
    standalone ``dsareg worker --engine embedded``); its end-of-file, SIGTERM, or the death of
    ``parent_pid`` stop the worker (a running job is handed back to the queue).
    """
    import signal

    from .procwatch import WorkerControl, die_with_parent, set_process_name

    set_process_name(f"dsareg-worker{index}")
    engine.skip_exit_collections()  # its stop is a server's stop: no seconds of garbage collection at exit
    control = WorkerControl()
    signal.signal(signal.SIGINT, signal.SIG_IGN if link is not None else control.request_stop)
    signal.signal(signal.SIGTERM, control.request_stop)
    if parent_pid is not None:
        die_with_parent(parent_pid)
    if link is not None:
        control.watch(link)
    logging.basicConfig(level=settings.server.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        jobs = settings.jobs
        engine.set_cpu_threads(jobs.threads_per_worker or engine.default_cpu_threads(max(1, jobs.workers)))
    except Exception:  # noqa: BLE001
        log.warning("could not set the worker's CPU threads")
    warm_up(settings.jobs.warm_up_job)
    _claim_loop(settings, index, control)


def _claim_loop(settings: ServiceSettings, index: int, control: Any) -> None:
    """Claim and run jobs until stopped; idle, wait for a wake-up or ``poll_seconds``."""
    store = store_for(settings, create_schema=False)
    from ..storage.dbblobs import make_blob_store

    blobs = make_blob_store(settings, store.engine, cache=False)
    worker_id = make_worker_id(index)
    room = DiskFloor(settings)
    log.info("worker %s started", worker_id)
    last_seen = 0.0
    try:
        while not control.stop.is_set():
            now = time.monotonic()
            if now - last_seen > max(1.0, settings.jobs.effective_heartbeat_seconds):
                try:
                    store.worker_seen(worker_id, os.getpid())
                except Exception:  # noqa: BLE001
                    log.warning("worker %s: store not reachable", worker_id)
                last_seen = now
            job = None
            if room.check():
                try:
                    job = store.claim(worker_id, settings.jobs.lease_seconds)
                except Exception:  # noqa: BLE001
                    log.warning("worker %s: claim failed", worker_id)
            if job is None:
                control.wait_for_work(settings.jobs.poll_seconds)
                continue
            log.info("job %s: claimed by %s (attempt %d)", job.id, worker_id, job.attempts)
            run_one(store, blobs, job, worker_id, settings, control.stop)
            last_seen = 0.0
    finally:
        store.dispose()
        log.info("worker %s stopped", worker_id)
