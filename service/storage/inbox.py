"""The DICOM node's durable index of received instances (table ``dimse_instances`` in the job database;
:class:`~service.storage.interfaces.DicomInbox`).

An instance is first written to the blob store and flushed to disk (``fsync`` of the file and
its folder: :func:`service.pacs.dimse.inbox.fsync_file`), then indexed here, and only then is the C-STORE
answered "success": a peer that saw success never loses the instance, whatever is killed afterwards.

Rows go through these states:

* ``received``: stored during an association that is still open;
* ``interrupted``: answered Success in an association that ended without release (A-ABORT, a
  dropped connection, a listener killed mid-association). A sender retries only what failed, so
  they are kept: they join their study (``committed``) when an association bringing instances of
  the same study is released (the sender came back), or after ``dicom_interrupted_wait_seconds``
  without it (:meth:`Inbox.promote_interrupted`); meanwhile their study is not stable;
* ``committed``: the association was released normally; the study waits for
  ``dicom_stable_seconds`` without a new instance;
* ``dispatched``: the study's jobs were created (``job_ids`` in :meth:`Inbox.mark_dispatched`);
* ``retrieving`` → ``retrieved``: sent by a peer because dsareg asked for it (a C-MOVE whose Move
  Originator is our AE title: a volume of the patient, or the inputs of a pull by reference);
  ``retrieved`` once its association ends, however it ends; never grouped into jobs of their own,
  read by :meth:`Inbox.series` for the job that asked.
* ``purging``: settled and past ``DSAREG_DICOM_INBOX_RETENTION_HOURS``, its file and row being removed
  (:mod:`.inbox_retention`); read by nothing.

Restarts: a listener that starts finds the ``received`` rows of associations that died with
the previous process and marks them ``interrupted`` (:meth:`interrupt_stale`); committed studies
are grouped as usual, and job creation is idempotent per (study, instances), so nothing is run twice.
"""

from __future__ import annotations

import time

import sqlalchemy as sa

from .records import StoredInstance
from .schema import dimse_instances as instances


class Inbox:
    """Received instances by study, on the job store's database (SQLite or PostgreSQL)."""

    def __init__(self, engine: sa.Engine, writer: sa.Engine | None = None):
        self.engine, self.writer = engine, writer or engine  # its table: the job store's migrations

    def add(self, item: StoredInstance, association: str, state: str = "received") -> None:
        """Index one stored instance (a re-sent instance replaces the earlier row); ``retrieving``: one we asked for."""
        values = {**vars(item), "association": association, "state": state}
        with self.writer.begin() as conn:
            conn.execute(instances.delete().where(instances.c.sop_instance_uid == item.sop_instance_uid))
            conn.execute(instances.insert().values(**values))

    def commit_association(self, association: str) -> int:
        """The association was released: its instances join their studies (``committed``) with the interrupted
        instances of those studies (their sender came back); those of a C-MOVE we asked for become ``retrieved``."""
        now = time.time()
        mine = instances.c.association == association
        with self.writer.begin() as conn:
            studies = sa.select(instances.c.study_uid).where(mine, instances.c.state == "received").distinct()
            conn.execute(instances.update().where(instances.c.state == "interrupted", instances.c.study_uid.in_(studies))
                         .values(state="committed", received_at=now))
            done = conn.execute(instances.update().where(mine, instances.c.state == "received")
                                .values(state="committed", received_at=now)).rowcount
            done += conn.execute(instances.update().where(mine, instances.c.state == "retrieving")
                                 .values(state="retrieved", received_at=now)).rowcount
        return done

    def interrupt_association(self, association: str) -> int:
        """The association ended without release: what it stored (answered Success) is kept, ``interrupted``;
        what a C-MOVE of ours brought is ``retrieved`` all the same."""
        mine = instances.c.association == association
        with self.writer.begin() as conn:
            done = conn.execute(instances.update().where(mine, instances.c.state == "received")
                                .values(state="interrupted")).rowcount
            done += conn.execute(instances.update().where(mine, instances.c.state == "retrieving")
                                 .values(state="retrieved")).rowcount
        return done

    def interrupt_stale(self, live: set[str], older_than_seconds: float = 0.0) -> int:
        """Mark ``interrupted`` the open rows of associations not in ``live`` (they died, or died with an earlier
        process), those received at least ``older_than_seconds`` ago; how many."""
        before = time.time() - older_than_seconds
        with self.engine.connect() as conn:
            dead = set(conn.execute(sa.select(instances.c.association).where(
                instances.c.state.in_(("received", "retrieving")), instances.c.received_at <= before)
                .distinct()).scalars()) - live
        return sum(self.interrupt_association(association) for association in dead)

    def promote_interrupted(self, wait_seconds: float, now: float | None = None) -> list[str]:
        """Interrupted instances whose sender did not come back within ``wait_seconds`` join their studies."""
        before = (time.time() if now is None else now) - wait_seconds
        waiting = sa.and_(instances.c.state == "interrupted", instances.c.received_at <= before)
        with self.writer.begin() as conn:
            studies = sorted(conn.execute(sa.select(instances.c.study_uid).where(waiting).distinct()).scalars())
            conn.execute(instances.update().where(waiting).values(state="committed"))
        return studies

    def series(self, series_uid: str, sop_instance_uid: str | None = None) -> list[StoredInstance]:
        """The ``retrieved`` instances of a series (or one of them), oldest first."""
        query = sa.select(instances).where(instances.c.series_uid == series_uid, instances.c.state == "retrieved")
        if sop_instance_uid:
            query = query.where(instances.c.sop_instance_uid == sop_instance_uid)
        with self.engine.connect() as conn:
            rows = conn.execute(query.order_by(instances.c.received_at)).mappings().all()
        fields = StoredInstance.__dataclass_fields__
        return [StoredInstance(**{k: row[k] for k in fields}) for row in rows]

    def stable_studies(self, quiet_seconds: float, now: float | None = None) -> list[str]:
        """Studies with committed instances and none received in the last ``quiet_seconds``."""
        now = time.time() if now is None else now
        with self.engine.connect() as conn:
            pending = set(conn.execute(sa.select(instances.c.study_uid).where(
                instances.c.state == "committed").distinct()).scalars())
            if not pending:
                return []
            latest = conn.execute(sa.select(instances.c.study_uid, sa.func.max(instances.c.received_at))
                                  .where(instances.c.study_uid.in_(pending))
                                  .group_by(instances.c.study_uid)).all()
            busy = set(conn.execute(sa.select(instances.c.study_uid).where(
                instances.c.study_uid.in_(pending), instances.c.state.in_(("received", "interrupted")))
                .distinct()).scalars())
        return sorted(study for study, last in latest if now - last >= quiet_seconds and study not in busy)

    def study(self, study_uid: str) -> list[StoredInstance]:
        """Every committed or dispatched instance of the study."""
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(instances).where(
                instances.c.study_uid == study_uid, instances.c.state.in_(("committed", "dispatched")))).mappings().all()
        fields = StoredInstance.__dataclass_fields__
        return [StoredInstance(**{k: row[k] for k in fields}) for row in rows]

    def mark_dispatched(self, study_uid: str, sop_instance_uids: list[str]) -> None:
        with self.writer.begin() as conn:
            conn.execute(instances.update().where(instances.c.study_uid == study_uid,
                                                  instances.c.sop_instance_uid.in_(sop_instance_uids),
                                                  instances.c.state == "committed").values(state="dispatched"))

    def counts(self) -> dict[str, int]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(instances.c.state, sa.func.count()).group_by(instances.c.state)).all()
        return {state: int(n) for state, n in rows}
