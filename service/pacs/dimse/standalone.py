"""``dsareg dicom-listener``: the DICOM node in its own process, composing the intake without the API.

It opens the intake (:class:`service.intake.context.IntakeContext`: store, blobs, validator processes and an
executor), runs an event loop in a thread for the submissions, and serves until SIGTERM / SIGINT.
Embedded workers belong to ``dsareg serve`` (they poll the job table); with Celery each job is a message.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
import time

from ...intake.context import IntakeContext, close_intake
from ...jobs.executor import Executor, NoExecutor
from ...jobs.factory import make_executor
from ...settings import ServiceSettings
from ...storage.interfaces import Leases
from .job_options import dicom_job_options
from .listener import DicomListener

log = logging.getLogger("dsareg.dimse")


def listener_executor(settings: ServiceSettings, store: Leases) -> Executor:
    """Celery's executor (a message per job) when the settings use Celery; else none (``dsareg serve``'s embedded
    workers take the jobs from the table)."""
    return make_executor(settings, store) if settings.jobs.executor == "celery" else NoExecutor()


def _wait_for_validators(intake: IntakeContext) -> None:
    deadline = time.monotonic() + intake.settings.limits.validation_timeout_seconds
    while intake.validator is not None and not intake.validator.ready() and time.monotonic() < deadline:
        time.sleep(0.1)


def run_dicom_listener(settings: ServiceSettings) -> int:
    """The DICOM node alone, until SIGTERM / SIGINT; 2 when no port is set."""
    if not settings.dimse.dicom_port:
        log.error("set DSAREG_DICOM_PORT (the listener's TCP port)")
        return 2
    dicom_job_options(settings)  # before anything starts: a SettingError naming DSAREG_DICOM_JOB_OPTIONS
    intake = IntakeContext.open(settings, listener_executor)
    loop = asyncio.new_event_loop()
    loop_thread = threading.Thread(target=loop.run_forever, name="dimse-submit-loop", daemon=True)
    loop_thread.start()
    listener = DicomListener(intake, loop, collects_garbage=True)  # no API sweeper runs in this process
    stopping = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.set())
    try:
        _wait_for_validators(intake)
        intake.executor.start()
        listener.start()
        print(f"dsareg dicom-listener: {settings.dimse.dicom_ae_title} on {settings.dimse.dicom_host}:{listener.port}",
              flush=True)
        stopping.wait()
    finally:
        listener.stop()
        loop.call_soon_threadsafe(loop.stop)
        loop_thread.join(5)
        close_intake(intake)
    return 0
