"""The service context and the typed dependencies of the routes.

``Ctx`` is the running service (the intake's store, blobs, validator, executor and what only HTTP needs),
``Principal`` the caller (``'anonymous'`` or ``'key:<hash prefix>'``) and ``OwnedJob`` the path's ``job_id`` looked up
and checked to belong to the caller (404 otherwise, for another key's job too: its existence is not told).
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CollectorRegistry, Counter

from ..intake.context import ANONYMOUS, IntakeContext
from .auth_throttle import client_of, refuse_if_blocked
from ..problems import Problem
from ..settings import hash_api_key
from ..storage.interfaces import JobReader, Jobs, Reviews
from ..storage.store import JobRecord, is_job_id

if TYPE_CHECKING:
    from ..jobs.callbacks import CallbackDeliverer
    from ..jobs.sweeper import Sweeper

@dataclass
class ServiceContext(IntakeContext):
    """The intake (:class:`service.intake.context.IntakeContext`) and what the HTTP service adds to it."""

    registry: CollectorRegistry
    uploads: Counter
    sweeper: Sweeper | None = None
    callbacks: CallbackDeliverer | None = None
    extra: dict[str, Any] = field(default_factory=dict)


bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`.")


def get_ctx(request: Request) -> ServiceContext:
    return request.app.state.ctx


Ctx = Annotated[ServiceContext, Depends(get_ctx)]


def principal(request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(bearer)) -> str:  # noqa: B008
    """The caller: ``'anonymous'`` without configured keys, else ``'key:<hash prefix>'``."""
    ctx = get_ctx(request)
    if not ctx.settings.auth.auth_enabled:
        return ANONYMOUS
    if credentials is None or not credentials.credentials:
        raise Problem(401, "send 'Authorization: Bearer <API key>'", headers={"WWW-Authenticate": "Bearer"})
    throttle, client = getattr(request.app.state, "auth_throttle", None), client_of(request)
    refuse_if_blocked(throttle, client)  # 429 + Retry-After after too many wrong keys (auth_throttle.py)
    digest = hash_api_key(credentials.credentials)
    match = None
    for known in ctx.settings.auth.api_key_hashes:  # compare against all, in constant time each
        if hmac.compare_digest(digest, known):
            match = known
    if match is None:
        if throttle is not None:
            throttle.failed(client)
        raise Problem(401, "the API key is not valid", headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})
    if throttle is not None:
        throttle.forget(client)
    return "key:" + match[:16]


Principal = Annotated[str, Depends(principal)]


def get_jobs(request: Request) -> Jobs:
    return get_ctx(request).jobs


JobsStore = Annotated[Jobs, Depends(get_jobs)]
"""The job table as the routes use it (:class:`~service.storage.interfaces.Jobs`)."""


def get_reviews(request: Request) -> Reviews:
    return get_ctx(request).store


ReviewStore = Annotated[Reviews, Depends(get_reviews)]
"""Reviews and the audit log (:class:`~service.storage.interfaces.Reviews`)."""


def owned_job(jobs: JobReader, job_id: str, who: str) -> JobRecord:
    """The job ``job_id`` of the caller; an id that cannot be one (syntax) never reaches the database."""
    if not is_job_id(job_id):
        raise Problem(404, "no registration job with this id", kind="job-not-found", field="job_id",
                      accepted="a job id as returned by POST /v1/registrations (1 to 64 of A-Z a-z 0-9 _ -)")
    job = jobs.get(job_id)
    if job is None or job.owner != who:  # another key's job answers as if it did not exist (no existence leak)
        raise Problem(404, f"no registration job with id '{job_id}'", kind="job-not-found")
    return job


def _owned_job(job_id: str, jobs: JobsStore, who: Principal) -> JobRecord:
    return owned_job(jobs, job_id, who)


OwnedJob = Annotated[JobRecord, Depends(_owned_job)]
"""The path's ``job_id``, owned by the caller. Only for routes without other validated path
parameters (a dependency runs before them, so it would turn their 422 into a 404)."""
