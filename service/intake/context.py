"""What a submission needs, as one typed object the API, the DICOM listener and the CLI build alike.

:class:`IntakeContext` holds the job store, the blob store, the input validator (``None``: inputs are not
parsed before a job is queued) and the executor jobs are handed to. The API's ``ServiceContext``
(:mod:`service.api.deps`) extends it with what only HTTP needs (metrics, the sweeper...);
``dsareg dicom-listener`` uses it as it is (:mod:`service.pacs.dimse.standalone`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Self

from ..jobs.executor import Executor
from ..settings import ServiceSettings
from ..storage.blobs import BlobStore
from ..storage.dbblobs import make_blob_store
from ..storage.interfaces import Jobs, JobStore
from ..storage.owners import ANONYMOUS  # noqa: F401 - the owner of jobs submitted while authentication is off
from ..storage.store import store_for
from .validator import ValidatorPool


@dataclass
class IntakeContext:
    settings: ServiceSettings
    store: JobStore
    blobs: BlobStore
    validator: ValidatorPool | None
    executor: Executor

    @classmethod
    def open(cls, settings: ServiceSettings, make_executor: Callable[[ServiceSettings, Any], Executor], *,
             validate: bool = True, **more: Any) -> Self:
        """The context of ``settings``: the data folder made, the store opened, the validator started when
        ``validate``, the executor made (not started); ``more``: the fields of a context extending this one."""
        settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
        store = store_for(settings)
        return cls(settings=settings, store=store, blobs=make_blob_store(settings, store.engine),
                   validator=start_validator(settings) if validate else None,
                   executor=make_executor(settings, store), **more)

    @property
    def jobs(self) -> Jobs:
        """The job table as a submission uses it (count the queue, find by idempotency key, create)."""
        return self.store


def start_validator(settings: ServiceSettings) -> ValidatorPool:
    """The validator processes of ``settings`` (``DSAREG_VALIDATION_*``), started (they warm up meanwhile)."""
    limits = settings.limits
    pool = ValidatorPool(limits.validation_processes, limits.validation_timeout_seconds, limits.validation_memory_mb,
                         threads=settings.jobs.threads_per_worker, volume_memory_mb=limits.validation_volume_memory_mb,
                         volume_timeout_seconds=limits.validation_volume_timeout_seconds)
    pool.start()
    return pool


def close_intake(ctx: IntakeContext) -> None:
    """Stop what :meth:`IntakeContext.open` started (the executor first: it may still hand jobs over)."""
    ctx.executor.stop()
    if ctx.validator is not None:
        ctx.validator.stop()
    ctx.store.dispose()
