"""The job store: the single record of every job, by concern on one database.

:class:`SqlJobStore` is :class:`~service.storage.interfaces.JobStore` — jobs (:mod:`~service.storage.jobrows`),
leases (:mod:`~service.storage.leases`, with the lease protocol), reviews and audit
(:mod:`~service.storage.reviews`), callbacks and exports (:mod:`~service.storage.deliveries`) — on one
:class:`~service.storage.database.Database` (one pool), its schema migrated at construction
(:mod:`~service.storage.migrate`). Each concern is also a class of its own over a ``Database``; code that needs
one takes its interface. The DICOM node's inbox (:class:`~service.storage.inbox.Inbox`) shares the engine.

The names callers import from here (records, ids, cursors, the outage errors) live in
:mod:`~service.storage.records` and :mod:`~service.storage.database`.
"""

from __future__ import annotations

from typing import Any

from .database import Database, store_outage_errors
from .dbtimeouts import StoreTimeouts
from .deliveries import SqlDeliveries
from .interfaces import JobStore
from .jobrows import SqlJobs
from .leases import SqlLeases
from .migrate import upgrade_database
from .records import (
    DECISIONS,
    EXPORT_STATES,
    FINISHED,
    REVIEW_FILTERS,
    STATUSES,
    ConflictError,
    InputFile,
    JobRecord,
    decode_cursor,
    is_job_id,
    new_job_id,
    random_token,
)
from .reviews import SqlReviews
from .schema import job_exports, metadata

__all__ = [  # what callers import from here (the records and schema names for code written against one module)
    "DECISIONS", "EXPORT_STATES", "FINISHED", "REVIEW_FILTERS", "STATUSES", "ConflictError", "InputFile", "JobRecord",
    "JobStore", "SqlJobStore", "decode_cursor", "is_job_id", "job_exports", "metadata", "new_job_id", "random_token",
    "store_for", "store_outage_errors",
]


class SqlJobStore(SqlJobs, SqlLeases, SqlReviews, SqlDeliveries):
    """Every concern of :class:`JobStore` on one database; ``create_schema``: migrate it first (under a lock)."""

    def __init__(self, url: str, *, create_schema: bool = True, timeouts: StoreTimeouts | None = None):
        database = Database(url, timeouts)
        super().__init__(database)
        self.url, self.is_sqlite, self.timeouts = url, database.is_sqlite, database.timeouts
        if create_schema:
            upgrade_database(self.engine)

    def dispose(self) -> None:
        self.database.dispose()


def store_for(settings: Any, *, create_schema: bool = True) -> SqlJobStore:
    """The job store of ``settings`` with its database timeouts."""
    return SqlJobStore(settings.effective_database_url, create_schema=create_schema,
                       timeouts=StoreTimeouts.from_settings(settings))
