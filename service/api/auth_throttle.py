"""Failed API keys throttled per client address: a guessing client is answered 429, not 401 after 401.

:class:`FailureThrottle` keeps, per client address, the times of its last :attr:`~ThrottlePolicy.max_failures`
wrong keys (in memory, per API process; at most :attr:`~ThrottlePolicy.max_clients` addresses, the least
recently seen dropped first). A client whose last ``max_failures`` wrong keys all fell within ``window_s`` is
*blocked* until the oldest of them is ``window_s`` old: every request of it that needs a key is answered
``429`` with ``Retry-After`` (the key is not even looked at, so a blocked client learns nothing about it).
A request without a key is a plain 401 and does not count (a browser's first call before the key is typed).

Each wrong key is logged at WARNING with the client address and the count, never the key or its hash; the
block is logged once when it starts. Behind a reverse proxy the client address is the proxy's unless uvicorn
is told to trust its ``X-Forwarded-For`` (``--forwarded-allow-ips``; docs/deployment/security.md).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger("dsareg.service.auth")


@dataclass(frozen=True)
class ThrottlePolicy:
    """How many wrong keys a client may send within how long before it is blocked."""

    max_failures: int = 10
    window_s: float = 60.0
    max_clients: int = 10_000


class FailureThrottle:
    """Wrong keys per client address in a bounded map; thread-safe (the key check runs in the thread pool)."""

    def __init__(self, policy: ThrottlePolicy | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.policy = policy or ThrottlePolicy()
        self._clock = clock
        self._lock = threading.Lock()
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()

    def retry_after(self, client: str) -> int | None:
        """Seconds until ``client`` may try a key again, or None when it is not blocked."""
        with self._lock:
            times = self._failures.get(client)
            if times is None or len(times) < self.policy.max_failures:
                return None
            left = self.policy.window_s - (self._clock() - times[0])
            return max(1, math.ceil(left)) if left > 0 else None

    def failed(self, client: str) -> None:
        """Count a wrong key from ``client``; log it (address and count, never the key)."""
        now = self._clock()
        with self._lock:
            times = self._failures.pop(client, None) or deque(maxlen=self.policy.max_failures)
            times.append(now)
            self._failures[client] = times  # most recently seen last
            while len(self._failures) > self.policy.max_clients:
                self._failures.popitem(last=False)
            recent = sum(1 for t in times if now - t < self.policy.window_s)
        blocked = recent >= self.policy.max_failures
        log.warning("wrong API key from %s (%d within %.0f s)%s", client, recent, self.policy.window_s,
                    f"; its requests get 429 for {self.policy.window_s:.0f} s" if blocked else "")

    def forget(self, client: str) -> None:
        """A valid key from ``client``: its wrong ones no longer count."""
        with self._lock:
            self._failures.pop(client, None)

    def __len__(self) -> int:
        return len(self._failures)


def client_of(request) -> str:
    """The client's address as the server sees it (the proxy's unless uvicorn trusts its forwarded headers)."""
    return request.client.host if request.client is not None else "unknown"


def refuse_if_blocked(throttle: FailureThrottle | None, client: str) -> None:
    """Raise a 429 problem with ``Retry-After`` when ``client`` is blocked."""
    wait = throttle.retry_after(client) if throttle is not None else None
    if wait is not None:
        from ..problems import Problem

        raise Problem(429, f"too many wrong API keys from this address; retry in {wait} s",
                      headers={"Retry-After": str(wait)})
