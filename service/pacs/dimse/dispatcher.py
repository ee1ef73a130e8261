"""Received studies → planned jobs, handed to the intake (:mod:`.submit`, over :mod:`service.intake`).

:class:`StudyDispatcher` looks (every ``tick_seconds``) for studies of the inbox that are
stable (no instance for ``dicom_stable_seconds``), plans their jobs (:mod:`.grouping`) and
hands each one to ``intake.submit`` — the same checks and queue as ``POST /v1/registrations``.
When an association is released it asks ``intake.prevalidate`` to parse the planned inputs
early (the validator caches successful parses by content), so the submission at stable time
costs no parse. No room now (the intake's :class:`~service.intake.refusals.Overloaded`): the study
waits a few seconds and is submitted again; any other refusal is recorded and logged.

A stable study with biplane pairs but no volume, when ``dicom_query_peer`` is set: the patient's
latest CT / MR / 3D-RA series is found by C-FIND and fetched by C-MOVE into the inbox
(:mod:`.query`, bounded by ``dicom_timeout_seconds``), and the pairs become jobs with it. The lookup
runs on a thread of its own (:class:`VolumeLookups`): a slow, large or frozen query peer holds that
study only, never the dispatch of the others. No volume found, or the peer down: a WARNING naming
the peer, the step and the status, the outcome in :attr:`StudyDispatcher.dispatched`, and the study
waits ``dicom_query_retry_seconds`` before it is asked for again (a volume sent meanwhile makes the job).
"""

from __future__ import annotations

import asyncio
import io
import logging
import threading
import time
from concurrent.futures import Future
from typing import Any

from ...engine_adapter import xa_view_angle_deg
from ...intake.refusals import Overloaded, Refusal
from ...storage.interfaces import DicomInbox
from ...storage.records import StoredInstance
from .grouping import PlannedJob, StudyPlan, XaView, plan_study
from .query import DimsePacsError, latest_volume, retrieve

log = logging.getLogger("dsareg.dimse")

OVERLOADED_RETRY_S = 5.0
"""At most this long before a study whose job found no room (:class:`Overloaded`) is submitted again."""
FAILED_RETRY_S = 30.0
"""A study whose dispatch failed unexpectedly (a missing blob, a database error) is tried again after this long;
the studies after it are dispatched meanwhile (an error used to end the pass: every study behind it waited)."""


def angle_between(a: XaView, b: XaView) -> float:
    return xa_view_angle_deg((a.primary_deg, a.secondary_deg), (b.primary_deg, b.secondary_deg))


def _header(blobs: Any, item: StoredInstance):
    import pydicom

    path = blobs.local_path(item.sha256)
    source = path if path is not None else io.BytesIO(blobs.read(item.sha256))
    return pydicom.dcmread(source, stop_before_pixels=True)


class VolumeLookups:
    """The patient's-volume lookups (C-FIND, then C-MOVE of the series) in progress, each on a daemon thread of its
    own, at most ``parallel`` talking to peers at once; ``done`` is called when one ends (wakes the dispatcher)."""

    def __init__(self, find: Any, done: Any, parallel: int = 2):
        self.find, self.done = find, done
        self.running: dict[str, Future] = {}
        self._slots = threading.BoundedSemaphore(parallel)

    def busy(self, study: str) -> bool:
        """A lookup of ``study`` is still running."""
        future = self.running.get(study)
        return future is not None and not future.done()

    def start(self, study: str, *args: Any) -> None:
        future: Future = Future()

        def run() -> None:
            with self._slots:
                try:
                    future.set_result(self.find(*args))
                except BaseException as exc:  # noqa: BLE001 - handed to the dispatcher
                    future.set_exception(exc)
            self.done()

        self.running[study] = future
        threading.Thread(target=run, name="dimse-volume-lookup", daemon=True).start()

    def take(self, study: str) -> Future | None:
        """The finished lookup of ``study`` (removed), or None when none was started."""
        return self.running.pop(study, None)


class StudyDispatcher:
    """A thread: stable studies → planned jobs → ``intake.submit`` on ``loop`` (the API's event loop, or its own)."""

    HOUSEKEEPING_SECONDS = 5.0
    HEADER_CACHE_STUDIES = 32

    def __init__(self, settings: Any, blobs: Any, inbox: DicomInbox, intake: Any, loop: asyncio.AbstractEventLoop,
                 tick_seconds: float = 0.25, housekeeping=None):
        self.settings, self.blobs, self.inbox, self.intake = settings, blobs, inbox, intake
        self.loop, self.tick = loop, tick_seconds
        self.housekeeping = housekeeping or (lambda: None)
        self._last_housekeeping = 0.0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._retry_at: dict[str, float] = {}
        self._early: set[str] = set()
        self._header_cache: dict[str, dict[tuple[str, str], Any]] = {}
        self._lock = threading.Lock()
        self._lookups = VolumeLookups(self._find_volume, self._wake.set)
        self._thread = threading.Thread(target=self._run, name="dimse-dispatcher", daemon=True)
        self.dispatched: list[dict[str, Any]] = []  # recent outcomes, for logs and tests

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(10)

    def wake(self, studies: Any = None) -> None:
        """An association was released with instances of ``studies``: parse their planned jobs early; a study
        waiting to ask its query peer again (no volume found) is looked at again as soon as it is stable."""
        with self._lock:
            self._early.update(studies or ())
            for study in studies or ():
                self._retry_at.pop(study, None)
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:  # parse first: a study that became stable during the parse is then submitted at once
                self._prevalidate_released()
                self.dispatch_once()
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
            plan = plan_study(list(self._headers(study, items).values()), angle_between)
            by_uid = {item.sop_instance_uid: item for item in items}
            for job in plan.jobs:
                future = asyncio.run_coroutine_threadsafe(self.intake.prevalidate(study, job, by_uid), self.loop)
                future.result(timeout=self.settings.limits.validation_timeout_seconds + 30)

    def _headers(self, study: str, items: list[StoredInstance]) -> dict[str, Any]:
        """``{SOP Instance UID: header}`` of the study's instances, kept from the early parse to the dispatch
        (read once per stored file)."""
        cached = self._header_cache.setdefault(study, {})
        while len(self._header_cache) > self.HEADER_CACHE_STUDIES:
            self._header_cache.pop(next(iter(self._header_cache)))
        out = {}
        for item in items:
            key = (item.sop_instance_uid, item.sha256)
            if key not in cached:
                cached[key] = _header(self.blobs, item)
            out[item.sop_instance_uid] = cached[key]
        return out

    def dispatch_once(self) -> int:
        now = time.time()
        studies = [s for s in self.inbox.stable_studies(self.settings.dimse.dicom_stable_seconds, now)
                   if self._retry_at.get(s, 0.0) <= now]
        for study in studies:
            try:
                self._dispatch(study)
            except Exception:  # noqa: BLE001 - this study waits; the others go on
                self._retry_at[study] = time.time() + FAILED_RETRY_S
                log.exception("study: dispatching it failed; the other studies go on, this one is tried again in "
                              "%g s", FAILED_RETRY_S)
        return len(studies)

    def _dispatch(self, study: str) -> None:
        if self._lookups.busy(study):
            return  # its patient's volume is being looked up (the lookup wakes us)
        started = time.perf_counter()
        items = self.inbox.study(study)
        headers = self._headers(study, items)
        self._header_cache.pop(study, None)
        plan = plan_study(list(headers.values()), angle_between)
        planned = time.perf_counter()
        by_uid = {item.sop_instance_uid: item for item in items}
        outcome: dict[str, Any] = {"study_uid": study, "jobs": [], "notes": plan.notes}
        if (plan.unmodelled and self.settings.dimse.dicom_query_peer
                and not self._patient_volume(study, plan, headers, by_uid, outcome)):
            return  # no volume for the pairs yet (logged; asked again later)
        for job in plan.jobs:
            future = asyncio.run_coroutine_threadsafe(self.intake.submit(study, job, by_uid), self.loop)
            try:
                job_id, created = future.result(timeout=self.settings.limits.validation_timeout_seconds + 30)
            except Overloaded as exc:  # no room now (queue, quota, validators): the study is submitted again
                wait_s = min(float(exc.retry_after_s), OVERLOADED_RETRY_S)
                self._retry_at[study] = time.time() + wait_s
                log.warning("study: job not queued yet (%s); retrying in %g s", exc.detail, wait_s)
                return
            except Refusal as exc:
                log.error("study: a planned job was refused (%s: %s, field %s)", exc.kind, exc.detail, exc.field)
                outcome["jobs"].append({"refused": exc.kind, "detail": exc.detail, "instances": job.instances})
                continue
            outcome["jobs"].append({"job_id": job_id, "created": created, "pairing": job.rule})
            lag = time.time() - max(item.received_at for item in items)
            log.info("job %s: %s from a DICOM study (%s), %.2f s after its last instance (planning %.2f s, "
                     "submission %.2f s)", job_id, "queued" if created else "already queued", job.rule, lag,
                     planned - started, time.perf_counter() - planned)
        for note in plan.notes:
            log.info("study: %s", note)
        self._retry_at.pop(study, None)
        self.inbox.mark_dispatched(study, [item.sop_instance_uid for item in items])
        self._remember(outcome)

    def _patient_volume(self, study: str, plan: StudyPlan, headers: dict[str, Any], by_uid: dict[str, StoredInstance],
                        outcome: dict[str, Any]) -> bool:
        """Fill ``plan.jobs`` with the patient's latest volume from the query peer, looked up on a thread of its own
        (:class:`VolumeLookups`); False: not yet (the lookup was started), or none (retried later)."""
        lookup, peer = self._lookups.take(study), self.settings.dimse.dicom_query_peer
        if lookup is None:
            patient = str(getattr(headers[plan.unmodelled[0][0]], "PatientID", "") or "")
            self._lookups.start(study, study, patient)
            log.info("study: asking %s for the patient's latest volume", peer)
            return False
        try:
            found, ordered = _lookup_result(lookup, peer)
        except DimsePacsError as exc:
            self._retry_at[study] = time.time() + self.settings.dimse.dicom_query_retry_seconds
            log.warning("study: %s; asking again in %g s", exc, self.settings.dimse.dicom_query_retry_seconds)
            outcome["error"] = {"type": "pacs-error", "peer": exc.server, "step": exc.step,
                                "dimse_status": exc.status, "detail": str(exc)}
            self._remember(outcome)
            return False
        by_uid.update({item.sop_instance_uid: item for item in ordered})
        origin = {"peer": peer, "study_uid": found.study_uid, "modality": found.modality, "study_date": found.study_date}
        plan.jobs = [PlannedJob(ap, lat, [item.sop_instance_uid for item in ordered], f"{rule}; patient's latest volume",
                                volume_origin=origin) for ap, lat, rule in plan.unmodelled]
        log.info("study: the patient's latest %s volume (%d instances) retrieved from %s", found.modality,
                 len(ordered), peer)
        return True

    def _find_volume(self, study: str, patient: str) -> tuple[Any, list[StoredInstance]]:
        """The patient's latest volume series (C-FIND) and its instances retrieved into the inbox (C-MOVE), ordered
        by Instance Number; :class:`DimsePacsError` when there is none or the peer fails (on a lookup thread)."""
        peer = self.settings.dimse.dicom_query_peer
        if not patient:
            raise DimsePacsError(peer, "C-FIND studies (patient's volume)", "the XA images have no Patient ID")
        found = latest_volume(self.settings, peer, patient, exclude_study=study)
        if found is None:
            raise DimsePacsError(peer, "C-FIND studies (patient's volume)", "no CT / MR / 3D-RA series of the "
                                 "patient (the study waits for a volume)")
        volume = retrieve(self.settings, self.inbox, peer, "SERIES", {
            "StudyInstanceUID": found.study_uid, "SeriesInstanceUID": found.series_uid}, "C-MOVE volume")
        return found, sorted(volume, key=lambda item: _instance_number(self.blobs, item))

    def _remember(self, outcome: dict[str, Any]) -> None:
        self.dispatched.append(outcome)
        del self.dispatched[:-100]


def _lookup_result(lookup: Future, peer: str) -> Any:
    """A finished lookup's result; an unexpected error in it is a :class:`DimsePacsError` too (logged with its
    traceback), so that the study waits and is asked for again like any failed lookup."""
    try:
        return lookup.result()
    except DimsePacsError:
        raise
    except Exception as exc:  # noqa: BLE001 - on the lookup thread; reported here
        log.error("study: the patient's volume lookup failed", exc_info=exc)
        raise DimsePacsError(peer, "patient's volume lookup", f"{type(exc).__name__}: {exc}") from None


def _instance_number(blobs: Any, item: StoredInstance) -> float:
    try:
        return float(_header(blobs, item).InstanceNumber)
    except Exception:  # noqa: BLE001 - no or odd Instance Number: last
        return float("inf")
