"""Retention of the DICOM inbox (``dimse_instances`` and the files of its instances): a settled study is removed.

A study's received instances stay while anything may still need them: while any of its rows is not yet
``dispatched`` (``received``, ``interrupted``, ``committed``, ``retrieving``), while a job that uses one of its
files is queued or running, and for ``DSAREG_DICOM_INBOX_RETENTION_HOURS`` after it settled — the latest of its
last instance's arrival (a refused study settles when it is dispatched, seconds later) and its jobs' ``finished_at``.
``retrieved`` instances (a volume fetched by C-MOVE for a job) follow the same rule, row by row with their study.

One pass (:func:`purge_settled`, run by the DICOM node's housekeeping every ``DSAREG_SWEEP_INTERVAL_SECONDS``):

1. the rows of (at most :data:`STUDIES_PER_PASS`) settled studies become ``purging`` (one transaction: they no longer count as the study's instances);
2. their files are deleted, but for those a job (``job_blobs``) or another inbox row still uses, or that were
   written again in the last minute (a re-sent instance: :meth:`BlobStore._adopt` refreshes the mtime);
3. the ``purging`` rows are deleted.

A crash after 1 or 2 leaves ``purging`` rows, which the next pass takes up again (deleting a file that is already
gone is a no-op): no file is left without a row, no row that is still needed is lost. A file that a finished job
still uses goes with that job (job retention, ``DSAREG_RETENTION_HOURS``): the job store counts inbox rows as
references too (:meth:`service.storage.leases.LeaseRows.referenced_blobs`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa

from .records import FINISHED
from .schema import dimse_instances as instances
from .schema import job_blobs, jobs

OPEN_STATES = ("received", "interrupted", "committed", "retrieving")
"""A study with a row in one of these states is not settled (not dispatched yet, or still arriving)."""
SETTLED_STATES = ("dispatched", "retrieved")
PURGING = "purging"
STUDIES_PER_PASS = 200
"""At most this many studies are marked per pass: a months-long backlog is removed over several passes, never
holding the dispatcher's thread (which runs the pass) for long."""
REWRITTEN_GRACE_S = 60.0
"""A file written again this recently is kept (an instance re-sent while its old row was being purged)."""


@dataclass(frozen=True)
class PurgeOutcome:
    studies: int
    rows: int
    files: int


def _unsettled_blobs(cutoff: float) -> sa.Select:
    """Digests used by a job that is not finished, or finished after ``cutoff``."""
    settled = sa.and_(jobs.c.status.in_(FINISHED), jobs.c.finished_at.is_not(None), jobs.c.finished_at <= cutoff)
    return (sa.select(job_blobs.c.sha256).join(jobs, jobs.c.id == job_blobs.c.job_id)
            .where(sa.not_(settled)))


def _held_studies(cutoff: float) -> sa.Select:
    """Studies not to purge: a row still open, arrived after ``cutoff``, or used by an unsettled job."""
    return sa.select(instances.c.study_uid).where(sa.or_(
        instances.c.state.in_(OPEN_STATES), instances.c.received_at > cutoff,
        instances.c.sha256.in_(_unsettled_blobs(cutoff))))


def mark_settled(writer: sa.Engine, cutoff: float, limit: int = STUDIES_PER_PASS) -> int:
    """Step 1: the rows of (at most ``limit``) studies settled before ``cutoff`` become ``purging``; how many."""
    settled = instances.c.state.in_(SETTLED_STATES)
    studies = (sa.select(instances.c.study_uid).where(settled, instances.c.study_uid.not_in(_held_studies(cutoff)))
               .distinct().limit(limit))
    with writer.begin() as conn:
        chosen = list(conn.execute(studies).scalars())
        if not chosen:
            return 0
        return conn.execute(instances.update().where(settled, instances.c.study_uid.in_(chosen))
                            .values(state=PURGING)).rowcount


def purging_files(engine: sa.Engine) -> tuple[list[str], int]:
    """The digests of the ``purging`` rows that nothing else uses (no job, no other inbox row); number of studies."""
    purging = instances.c.state == PURGING
    others = sa.select(instances.c.sha256).where(instances.c.state != PURGING)
    free = (sa.select(instances.c.sha256).where(purging, instances.c.sha256.not_in(sa.select(job_blobs.c.sha256)),
                                                instances.c.sha256.not_in(others)).distinct())
    with engine.connect() as conn:
        studies = conn.execute(sa.select(sa.func.count(sa.distinct(instances.c.study_uid))).where(purging)).scalar_one()
        digests = sorted(conn.execute(free).scalars()) if studies else []
    return digests, int(studies)


def delete_purging(writer: sa.Engine) -> int:
    """Step 3: the ``purging`` rows go; how many."""
    with writer.begin() as conn:
        return conn.execute(instances.delete().where(instances.c.state == PURGING)).rowcount


def purge_settled(engine: sa.Engine, writer: sa.Engine, blobs: Any, retention_s: float,
                  now: float | None = None) -> PurgeOutcome:
    """One retention pass over the inbox (steps 1–3 above); ``blobs``: the node's blob store."""
    cutoff = (time.time() if now is None else now) - retention_s
    mark_settled(writer, cutoff)
    digests, studies = purging_files(engine)
    files = blobs.delete(digests, min_age_seconds=REWRITTEN_GRACE_S) if digests else 0
    rows = delete_purging(writer)
    return PurgeOutcome(studies=studies, rows=rows, files=files)
