"""Which executor runs the jobs: the one place that knows every kind (so the executors do not import each other)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..settings import ServiceSettings
from .executor import EmbeddedProcessExecutor, Executor, NoExecutor

if TYPE_CHECKING:
    from ..storage.interfaces import Leases


def make_executor(settings: ServiceSettings, store: Leases | None = None) -> Executor:
    """The executor the settings ask for (the one place that knows every kind)."""
    if settings.jobs.executor == "celery":
        from .celery.executor import CeleryExecutor

        return CeleryExecutor(settings, store)
    return EmbeddedProcessExecutor(settings, store=store) if settings.jobs.workers > 0 else NoExecutor()
