"""Why the intake did not accept a submission: the domain errors it raises.

Each says what was wrong in plain words (``detail``), and for an input the field at fault and what
would have been accepted. ``kind`` names the refusal (the last part of an HTTP problem's ``type``).
The callers decide what a refusal means to them: the API maps each class to one HTTP status in one
place (:mod:`service.api.handlers`), the DICOM dispatcher submits again later after :class:`Overloaded`
and records any other refusal.
"""

from __future__ import annotations

from typing import Any


class Refusal(Exception):
    """A submission the intake did not accept."""

    default_kind = "refused"

    def __init__(self, detail: str, *, kind: str | None = None, field: str | None = None,
                 accepted: str | None = None, extra: dict[str, Any] | None = None):
        super().__init__(detail)
        self.detail = detail
        self.kind = kind or self.default_kind
        self.field = field
        self.accepted = accepted
        self.extra = extra or {}


class InvalidInput(Refusal):
    """An input that cannot be used as given (``field`` names it, ``accepted`` says what can)."""

    default_kind = "invalid-input"


class Overloaded(Refusal):
    """Not now: the server has no room for the job (queue full, validators busy); submit again after
    ``retry_after_s`` seconds. Nothing was wrong with the request."""

    default_kind = "unavailable"

    def __init__(self, detail: str, *, retry_after_s: int, kind: str | None = None):
        super().__init__(detail, kind=kind)
        self.retry_after_s = int(retry_after_s)


class QuotaExceeded(Overloaded):
    """This owner already has as many queued jobs as one owner may; submit again after ``retry_after_s``."""

    default_kind = "too-many-requests"


class IdempotencyConflict(Refusal):
    """The idempotency key was used before with a different request (``job_id``: the job it made)."""

    default_kind = "idempotency-conflict"

    def __init__(self, detail: str, *, job_id: str, field: str | None = None):
        super().__init__(detail, field=field, extra={"job_id": job_id})
        self.job_id = job_id
