"""Received studies → registration jobs, through the same checks and queue as an HTTP submission.

:class:`StudyDispatcher` looks (every ``tick_seconds``) for studies of the inbox that are
stable (no instance for ``dicom_stable_seconds``), plans their jobs (:mod:`.grouping`) and
submits each one like ``POST /v1/registrations`` would: back-pressure (queue limits), the
input validator, then one row in the job table and the executor's ``submit``.

A job's inputs are the received instances themselves (roles ``ap``, ``lat``, ``volume``: the
blobs the C-STORE wrote) and a small JSON input of role ``dimse`` (:func:`source_document`):
where the study came from and where the results go. Its Idempotency-Key is derived from the
study and the instances, so planning a study again (after a restart, or when more instances
arrive) never makes a second job for the same pair.
"""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import logging
import threading
import time
from typing import Any

from ..api.deps import ANONYMOUS, ServiceContext
from ..api.submission import check_queue, create_job, fingerprint, new_job, parse_options_json, validate_inputs
from ..engine_adapter import xa_view_angle_deg
from ..problems import Problem
from ..store import InputFile
from .grouping import PlannedJob, XaView, plan_study
from .inbox import Inbox, StoredInstance

log = logging.getLogger("dsareg.dimse")

ROLE = "dimse"
TRANSIENT_STATUS = {429, 503}


def angle_between(a: XaView, b: XaView) -> float:
    return xa_view_angle_deg((a.primary_deg, a.secondary_deg), (b.primary_deg, b.secondary_deg))


def job_owner(settings: Any) -> str:
    chosen = settings.dicom_job_owner_key_hash or (settings.api_key_hashes[0] if settings.api_key_hashes else None)
    return "key:" + chosen.strip().lower()[:16] if chosen and settings.auth_enabled else ANONYMOUS


def source_document(study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance], settings: Any) -> dict:
    """The job's ``dimse`` input: the study's origin and the export destinations (deterministic JSON)."""
    calling = by_uid[job.ap].calling_ae
    volume_series = sorted({by_uid[uid].series_uid for uid in job.volume})
    return {"source": {"dimse": {
        "calling_ae": calling, "study_uid": study_uid, "pairing": job.rule,
        "ap": {"series_uid": by_uid[job.ap].series_uid, "sop_instance_uid": job.ap},
        "lat": {"series_uid": by_uid[job.lat].series_uid, "sop_instance_uid": job.lat},
        "volume": {"series_uid": volume_series[0], "instances": len(job.volume)}}},
        "export": list(settings.dicom_export) or [calling]}


def idempotency_key(study_uid: str, job: PlannedJob) -> str:
    text = "|".join([study_uid, job.ap, job.lat, *sorted(job.volume)])
    return "dimse:" + hashlib.sha256(text.encode()).hexdigest()


async def _planned_inputs(ctx: ServiceContext, study_uid: str, job: PlannedJob,
                          by_uid: dict[str, StoredInstance]) -> tuple[list[InputFile], Any]:
    """The job's inputs (the received instances and its ``dimse`` document) and its parsed options."""
    document = json.dumps(source_document(study_uid, job, by_uid, ctx.settings), sort_keys=True).encode()
    digest, size = await asyncio.to_thread(ctx.blobs.put_bytes, document)

    def item(role: str, uid: str) -> InputFile:
        return InputFile(role=role, sha256=by_uid[uid].sha256, size=by_uid[uid].size, suffix=".dcm")

    inputs = [item("ap", job.ap), item("lat", job.lat), *(item("volume", uid) for uid in job.volume),
              InputFile(role=ROLE, sha256=digest, size=size, suffix=".json")]
    return inputs, parse_options_json(dict(ctx.settings.dicom_job_options) or None)


async def prevalidate(ctx: ServiceContext, study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance]) -> None:
    """Parse a planned job's inputs ahead of time (when its association is released, before the study is
    stable): the validator keeps successful outcomes by content, so the submission then costs no parse."""
    inputs, options = await _planned_inputs(ctx, study_uid, job, by_uid)
    try:
        await validate_inputs(ctx, inputs, None, options)
    except Problem:
        pass  # reported by the submission itself


async def submit_planned(ctx: ServiceContext, study_uid: str, job: PlannedJob,
                         by_uid: dict[str, StoredInstance]) -> tuple[str, bool]:
    """One planned job → ``(job id, created)``; raises :class:`Problem` like the HTTP submission."""
    owner, key = job_owner(ctx.settings), idempotency_key(study_uid, job)
    existing = await asyncio.to_thread(ctx.store.find_idempotent, owner, key)
    if existing is not None:
        return existing.id, False
    inputs, options = await _planned_inputs(ctx, study_uid, job, by_uid)
    options_json = options.model_dump(mode="json")
    await check_queue(ctx, owner)
    warnings = await validate_inputs(ctx, inputs, None, options)
    record = new_job(ctx, owner, key, options_json=options_json, geometry=None, inputs=inputs, warnings=warnings,
                     request_hash=fingerprint(inputs, None, options_json), input_bytes=sum(i.size for i in inputs))
    stored, _ = await create_job(ctx, record)
    if stored is None:  # an equal request won the race
        again = await asyncio.to_thread(ctx.store.find_idempotent, owner, key)
        return (again.id if again else ""), False
    await asyncio.to_thread(ctx.executor.submit, stored.id)
    return stored.id, True


def _header(ctx: ServiceContext, item: StoredInstance):
    import pydicom

    path = ctx.blobs.local_path(item.sha256)
    source = path if path is not None else io.BytesIO(ctx.blobs.read(item.sha256))
    return pydicom.dcmread(source, stop_before_pixels=True)


class StudyDispatcher:
    """A thread: stable studies → planned jobs → submitted on ``loop`` (the API's event loop, or its own)."""

    HOUSEKEEPING_SECONDS = 5.0

    def __init__(self, ctx: ServiceContext, inbox: Inbox, loop: asyncio.AbstractEventLoop, tick_seconds: float = 0.25,
                 housekeeping=None):
        self.ctx, self.inbox, self.loop, self.tick = ctx, inbox, loop, tick_seconds
        self.housekeeping = housekeeping or (lambda: None)
        self._last_housekeeping = 0.0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._retry_at: dict[str, float] = {}
        self._early: set[str] = set()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="dimse-dispatcher", daemon=True)
        self.dispatched: list[dict[str, Any]] = []  # recent outcomes, for logs and tests

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(10)

    def wake(self, studies: Any = None) -> None:
        """An association was released with instances of ``studies``: parse their planned jobs early."""
        with self._lock:
            self._early.update(studies or ())
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.dispatch_once()
                self._prevalidate_released()
                if time.monotonic() - self._last_housekeeping > self.HOUSEKEEPING_SECONDS:
                    self._last_housekeeping = time.monotonic()
                    self.housekeeping()
            except Exception:  # noqa: BLE001 - keep dispatching; the inbox is unchanged, retried next tick
                log.exception("dispatching received studies failed; retrying")
                self._stop.wait(2.0)
            self._wake.wait(self.tick)
            self._wake.clear()

    def _prevalidate_released(self) -> None:
        with self._lock:
            studies, self._early = self._early, set()
        for study in studies:
            items = self.inbox.study(study)
            plan = plan_study([_header(self.ctx, item) for item in items], angle_between)
            by_uid = {item.sop_instance_uid: item for item in items}
            for job in plan.jobs:
                future = asyncio.run_coroutine_threadsafe(prevalidate(self.ctx, study, job, by_uid), self.loop)
                future.result(timeout=self.ctx.settings.validation_timeout_seconds + 30)

    def dispatch_once(self) -> int:
        now = time.time()
        studies = [s for s in self.inbox.stable_studies(self.ctx.settings.dicom_stable_seconds, now)
                   if self._retry_at.get(s, 0.0) <= now]
        for study in studies:
            self._dispatch(study)
        return len(studies)

    def _dispatch(self, study: str) -> None:
        items = self.inbox.study(study)
        headers = {item.sop_instance_uid: _header(self.ctx, item) for item in items}
        plan = plan_study(list(headers.values()), angle_between)
        by_uid = {item.sop_instance_uid: item for item in items}
        outcome: dict[str, Any] = {"study_uid": study, "jobs": [], "notes": plan.notes}
        for job in plan.jobs:
            future = asyncio.run_coroutine_threadsafe(submit_planned(self.ctx, study, job, by_uid), self.loop)
            try:
                job_id, created = future.result(timeout=self.ctx.settings.validation_timeout_seconds + 30)
            except Problem as exc:
                if exc.status in TRANSIENT_STATUS:
                    self._retry_at[study] = time.time() + 5.0
                    log.warning("study: job not queued yet (%s); retrying in 5 s", exc.detail)
                    return
                log.error("study: a planned job was refused (%d %s, field %s)", exc.status, exc.detail,
                          getattr(exc, "field", None))
                outcome["jobs"].append({"refused": exc.status, "detail": exc.detail, "instances": job.instances})
                continue
            outcome["jobs"].append({"job_id": job_id, "created": created, "pairing": job.rule})
            log.info("job %s: %s from a DICOM study (%s)", job_id, "queued" if created else "already queued", job.rule)
        for note in plan.notes:
            log.info("study: %s", note)
        self._retry_at.pop(study, None)
        self.inbox.mark_dispatched(study, [item.sop_instance_uid for item in items])
        self.dispatched.append(outcome)
        del self.dispatched[:-100]
