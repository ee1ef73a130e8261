"""Completion callbacks: one signed POST of the job summary when a job ends.

* **Who may be called**: a job's ``callback_url`` must lie under one of the administrator's
  ``callback_allowed`` prefixes (:func:`url_problem`: same scheme, host and port, the path at a
  ``/`` boundary, no user info, no ``.``/``..`` segments), checked at submission; nothing else is
  ever requested, and redirects are never followed (a 3xx ends the delivery as failed).
* **Who delivers**: the API process (:class:`CallbackDeliverer`, a thread next to the sweeper,
  started by the lifespan), in both topologies (embedded workers or Celery): workers never make
  outbound calls and never wait on a receiver. Deliveries run on a small thread pool.
* **Exactly when**: every ``POLL_SECONDS`` (:mod:`.leased`, the loop shared with held PACS exports) the deliverer asks the store for callbacks of ended jobs
  (succeeded, failed, canceled — however they ended) that are due, claims each with a lease
  (a conditional UPDATE, so two API replicas never deliver the same attempt), POSTs, and records
  the outcome. A failed attempt is retried after ``callback_retry_backoff_seconds`` doubling
  (at most ``MAX_BACKOFF_SECONDS``), ``callback_max_attempts`` in all, then the state is ``failed``.
* **At least once**: an API that dies mid-delivery leaves the row ``delivering`` with a lease;
  once the lease has passed, a deliverer (after the restart, or another replica) sends it again.
  Every attempt carries the same ``X-Dsareg-Delivery`` id, so receivers can drop duplicates.
* **Signed**: ``X-Dsareg-Signature: sha256=<hex HMAC-SHA256 of the raw body, key callback_secret>``.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import unquote, urlsplit

import httpx

from ..settings import ServiceSettings
from ..storage.interfaces import DeliveryStore
from ..storage.store import JobRecord
from .leased import LeasedDeliverer

log = logging.getLogger("dsareg.service.callbacks")

SIGNATURE_HEADER = "X-Dsareg-Signature"
DELIVERY_HEADER = "X-Dsareg-Delivery"
ATTEMPT_HEADER = "X-Dsareg-Attempt"
JOB_HEADER = "X-Dsareg-Job"
MAX_BACKOFF_SECONDS = 300.0
LEASE_MARGIN_SECONDS = 5.0
MAX_URL_LENGTH = 2048


# ---- which URLs ----------------------------------------------------------------------------


def _origin(url: str) -> tuple[str, str, int, str] | None:
    """``(scheme, host, port, path)`` of an http(s) URL without user info; None when it is not one."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        return None
    if parts.scheme not in ("http", "https") or not parts.hostname or "@" in parts.netloc:
        return None
    return parts.scheme, parts.hostname.lower(), port or (443 if parts.scheme == "https" else 80), parts.path or "/"


def _under(path: str, prefix: str) -> bool:
    if not path.startswith(prefix):
        return False
    return prefix.endswith("/") or len(path) == len(prefix) or path[len(prefix)] in "/"


def url_problem(url: str, allowed: list[str]) -> str | None:
    """Why ``url`` may not be called back (a sentence), or None when it lies under an allowed prefix."""
    if not allowed:
        return "completion callbacks are not enabled on this server (the administrator sets DSAREG_CALLBACK_ALLOWED)"
    if len(url) > MAX_URL_LENGTH or any(ord(c) <= 32 or ord(c) == 127 for c in url):
        return f"must be a URL of at most {MAX_URL_LENGTH} characters without spaces or control characters"
    target = _origin(url)
    if target is None or "#" in url:
        return "must be an absolute http(s) URL without user info or fragment"
    segments = unquote(target[3]).split("/")
    if any(segment in (".", "..") for segment in segments) or "\\" in unquote(target[3]):
        return "must not contain '.' or '..' path segments"
    for prefix in allowed:
        origin = _origin(prefix)
        if origin is not None and origin[:3] == target[:3] and _under(target[3], origin[3]):
            return None
    return "is not under a callback prefix this server allows (DSAREG_CALLBACK_ALLOWED)"


# ---- signing --------------------------------------------------------------------------------


def signature(body: bytes, secret: str) -> str:
    """The ``X-Dsareg-Signature`` value of ``body``: ``sha256=<hex HMAC-SHA256>``."""
    return "sha256=" + hmac.new(secret.encode("utf-8"), body, hashlib.sha256).hexdigest()


def verify(body: bytes, secret: str, header: str | None) -> bool:
    """What a receiver does (docs/api/callbacks.md): recompute and compare in constant time."""
    return header is not None and hmac.compare_digest(signature(body, secret), header)


def backoff_seconds(settings: ServiceSettings, attempts: int) -> float:
    """Delay after the ``attempts``-th failed attempt."""
    return min(MAX_BACKOFF_SECONDS, settings.callbacks.callback_retry_backoff_seconds * 2.0 ** max(0, attempts - 1))


# ---- delivering -----------------------------------------------------------------------------


class CallbackDeliverer(LeasedDeliverer):
    """The API process's delivery loop (see the module docstring). ``payload(job)`` → the body bytes."""

    name = "callbacks"

    def __init__(self, store: DeliveryStore, settings: ServiceSettings, payload: Callable[[JobRecord], bytes],
                 user_agent: str = "dsareg"):
        super().__init__()
        self.store, self.settings, self.payload = store, settings, payload
        self.lease_seconds = settings.callbacks.callback_timeout_seconds + LEASE_MARGIN_SECONDS
        self.headers = {"Content-Type": "application/json", "User-Agent": user_agent}
        self._http = httpx.Client(timeout=settings.callbacks.callback_timeout_seconds, follow_redirects=False)

    def due(self, now: float) -> list[str]:
        return self.store.due_callbacks(now)

    def claim(self, job_id: str, now: float) -> dict[str, Any] | None:
        return self.store.claim_callback(job_id, now, self.lease_seconds)

    def deliver(self, row: dict[str, Any]) -> str:
        """One attempt of a claimed delivery; the state it left (delivered / pending / failed)."""
        job = self.store.get(row["job_id"])
        if job is None:
            return "gone"
        body = self.payload(job)
        headers = {**self.headers, SIGNATURE_HEADER: signature(body, self.settings.callbacks.callback_secret),
                   DELIVERY_HEADER: row["delivery_id"], ATTEMPT_HEADER: str(row["attempts"]), JOB_HEADER: job.id}
        status, error = None, None
        try:
            response = self._http.post(row["url"], content=body, headers=headers)
            status = response.status_code
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {str(exc)[:200]}"
        return self._record(row, status, error)

    def _record(self, row: dict[str, Any], status: int | None, error: str | None) -> str:
        attempt = row["attempts"]
        if status is not None and 200 <= status < 300:
            state, next_at = "delivered", None
        elif status is not None and (300 <= status < 400 or status == 410):
            state, next_at = "failed", None
            error = f"HTTP {status}: " + ("redirects are not followed" if status < 400 else "the receiver is gone")
        elif attempt >= self.settings.callbacks.callback_max_attempts:
            state, next_at = "failed", None
        else:
            state, next_at = "pending", time.time() + backoff_seconds(self.settings, attempt)
        if status is not None and error is None and state != "delivered":
            error = f"HTTP {status}"
        self.store.finish_callback(row["job_id"], attempt, state=state, status_code=status, error=error,
                                   next_attempt_at=next_at)
        level = logging.INFO if state == "delivered" else logging.WARNING
        log.log(level, "job %s: callback attempt %d %s%s", row["job_id"], attempt, state,
                f" ({error})" if error else "")
        return state
