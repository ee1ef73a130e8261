"""Received studies → planned jobs, handed to the API's intake (:mod:`service.api.intake.dimse`).

:class:`StudyDispatcher` looks (every ``tick_seconds``) for studies of the inbox that are
stable (no instance for ``dicom_stable_seconds``), plans their jobs (:mod:`.grouping`) and
hands each one to ``intake.submit`` — the same checks and queue as ``POST /v1/registrations``.
When an association is released it asks ``intake.prevalidate`` to parse the planned inputs
early (the validator caches successful parses by content), so the submission at stable time
costs no parse. The intake is injected: this package knows nothing of the API.
"""

from __future__ import annotations

import asyncio
import io
import logging
import threading
import time
from typing import Any

from ...engine_adapter import xa_view_angle_deg
from ...problems import Problem
from .grouping import XaView, plan_study
from .inbox import Inbox, StoredInstance

log = logging.getLogger("dsareg.dimse")

TRANSIENT_STATUS = {429, 503}


def angle_between(a: XaView, b: XaView) -> float:
    return xa_view_angle_deg((a.primary_deg, a.secondary_deg), (b.primary_deg, b.secondary_deg))


def _header(blobs: Any, item: StoredInstance):
    import pydicom

    path = blobs.local_path(item.sha256)
    source = path if path is not None else io.BytesIO(blobs.read(item.sha256))
    return pydicom.dcmread(source, stop_before_pixels=True)


class StudyDispatcher:
    """A thread: stable studies → planned jobs → ``intake.submit`` on ``loop`` (the API's event loop, or its own)."""

    HOUSEKEEPING_SECONDS = 5.0

    def __init__(self, settings: Any, blobs: Any, inbox: Inbox, intake: Any, loop: asyncio.AbstractEventLoop,
                 tick_seconds: float = 0.25, housekeeping=None):
        self.settings, self.blobs, self.inbox, self.intake = settings, blobs, inbox, intake
        self.loop, self.tick = loop, tick_seconds
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
            except Exception:
                log.exception("dispatching received studies failed; retrying")
                self._stop.wait(2.0)
            self._wake.wait(self.tick)
            self._wake.clear()

    def _prevalidate_released(self) -> None:
        with self._lock:
            studies, self._early = self._early, set()
        for study in studies:
            items = self.inbox.study(study)
            plan = plan_study([_header(self.blobs, item) for item in items], angle_between)
            by_uid = {item.sop_instance_uid: item for item in items}
            for job in plan.jobs:
                future = asyncio.run_coroutine_threadsafe(self.intake.prevalidate(study, job, by_uid), self.loop)
                future.result(timeout=self.settings.limits.validation_timeout_seconds + 30)

    def dispatch_once(self) -> int:
        now = time.time()
        studies = [s for s in self.inbox.stable_studies(self.settings.dimse.dicom_stable_seconds, now)
                   if self._retry_at.get(s, 0.0) <= now]
        for study in studies:
            self._dispatch(study)
        return len(studies)

    def _dispatch(self, study: str) -> None:
        items = self.inbox.study(study)
        headers = {item.sop_instance_uid: _header(self.blobs, item) for item in items}
        plan = plan_study(list(headers.values()), angle_between)
        by_uid = {item.sop_instance_uid: item for item in items}
        outcome: dict[str, Any] = {"study_uid": study, "jobs": [], "notes": plan.notes}
        for job in plan.jobs:
            future = asyncio.run_coroutine_threadsafe(self.intake.submit(study, job, by_uid), self.loop)
            try:
                job_id, created = future.result(timeout=self.settings.limits.validation_timeout_seconds + 30)
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
