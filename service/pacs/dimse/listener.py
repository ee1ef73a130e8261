"""The DICOM node as a whole: the C-STORE SCP, the durable inbox and the study dispatcher.

Two ways to run it (same settings, ``DSAREG_DICOM_*``):

* inside ``dsareg serve`` when ``DSAREG_DICOM_PORT`` is set (started by the API's lifespan):
  jobs are submitted on the API's event loop with its intake (validator, queue and executor);
* alone, ``dsareg dicom-listener`` (:mod:`.standalone`), e.g. next to Celery workers: the same
  pieces, opened by that process.

Received studies become jobs through the intake (:class:`service.intake.context.IntakeContext`,
:mod:`.submit`), as every submission does. Only one listener per job database: at start it marks
``interrupted`` what associations of an earlier, dead listener left open — instances answered
Success are kept and join their study when the sender comes back (:mod:`.inbox`).
"""

from __future__ import annotations

import asyncio
import logging
import time

from ...intake.context import IntakeContext
from ...storage.inbox import Inbox
from ...storage.inbox_retention import purge_settled
from .dispatcher import StudyDispatcher
from .job_options import dicom_job_options
from .scp import StoreScp, start_server
from .submit import DimseIntake

log = logging.getLogger("dsareg.dimse")


class DicomListener:
    def __init__(self, intake: IntakeContext, loop: asyncio.AbstractEventLoop, *, collects_garbage: bool = False):
        """``loop``: the event loop the jobs are submitted on (running in another thread); ``collects_garbage``:
        the housekeeping also removes stored files no row names (the standalone listener; in ``dsareg serve`` the
        API's sweeper does)."""
        settings, store = intake.settings, intake.store
        dicom_job_options(settings)  # a SettingError now, not a failure of every study later
        self.settings, self.blobs, self.store = settings, intake.blobs, store
        self.collects_garbage = collects_garbage
        self.inbox = Inbox(store.engine, getattr(store, "writer", None))
        tick = min(0.25, settings.dimse.dicom_stable_seconds / 4)
        self.dispatcher = StudyDispatcher(settings, self.blobs, self.inbox, DimseIntake(intake), loop,
                                          tick_seconds=tick, housekeeping=self.housekeeping)
        self.scp = StoreScp(settings, self.inbox, self.blobs, on_commit=self.dispatcher.wake)
        self.server = None
        self._last_purge = float("-inf")  # the first housekeeping purges

    def housekeeping(self) -> None:
        """On the dispatcher's thread: dead associations (often), the inbox retention and, when ``collects_garbage``,
        the files no row names (at start, then every sweep interval)."""
        self.scp.sweep()
        if time.monotonic() - self._last_purge < self.settings.retention.sweep_interval_seconds:
            return
        self._last_purge = time.monotonic()
        retention_s = self.settings.dimse.dicom_inbox_retention_hours * 3600.0
        done = purge_settled(self.inbox.engine, self.inbox.writer, self.blobs, retention_s)
        if done.rows:
            log.info("inbox retention: removed %d instance(s) of %d settled stud(ies), %d file(s)", done.rows,
                     done.studies, done.files)
        if self.collects_garbage:  # e.g. a C-STORE whose index write failed after its file was stored (answered A700)
            removed = self.blobs.collect_garbage(self.store.referenced_blobs())  # UNNAMED_FILE_AGE_S old
            if removed:
                log.warning("removed %d stored file(s) that no instance or job names", removed)

    def start(self) -> None:
        # pydicom and pynetdicom are imported here, in the starting thread, before the dispatcher thread runs:
        # the dispatcher reading a stable study's headers (pydicom) while this thread imports pynetdicom (which
        # imports pydicom) is a cross-thread import deadlock that Python breaks by handing one of them a half-
        # initialised pydicom ("cannot import name 'UID' from partially initialized module"): a restarted
        # listener with studies waiting died at start.
        import pydicom  # noqa: F401
        import pynetdicom  # noqa: F401

        kept = self.inbox.interrupt_stale(live=set())
        if kept:
            log.warning("kept %d instance(s) answered Success in associations an earlier listener left open "
                        "(interrupted: they join their study when the sender comes back, or after %g s)", kept,
                        self.settings.dimse.dicom_interrupted_wait_seconds)
        self.dispatcher.start()
        self.server = start_server(self.settings, self.scp)
        dimse = self.settings.dimse
        log.info("DICOM node %s listening on %s:%d (%d peers)", dimse.dicom_ae_title, dimse.dicom_host,
                 self.port, len(dimse.dicom_peers))

    @property
    def port(self) -> int:
        return self.server.server_address[1] if self.server is not None else 0

    def stop(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server = None
        self.dispatcher.stop()
