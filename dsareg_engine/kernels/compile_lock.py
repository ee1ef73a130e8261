"""One writer per kernel group: a file lock per (install, group, thread budget) around numba compiles.

numba's on-disk cache keeps one index file per function and rewrites it on every save without a lock,
so two processes compiling different specializations of one function at once can lose or mix entries.
:mod:`dsareg_engine.warmup` compiles each group of kernels under :func:`compiling_group`; code that
uses a group's kernels first calls :func:`wait_for_group`, which returns at once unless another process
(the background helper) is compiling that group right now, and then only once per process.

The wait is bounded: a holder that is frozen (SIGSTOP, a stalled disk) keeps its lock forever, so
after :data:`WAIT_LIMIT_S` the waiter logs a warning and goes on without it (it compiles the kernels
itself, in memory if the cache cannot be written). A holder that dies releases its lock at once (the
kernel drops a dead process's ``flock``).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parents[1]  # the installed package (its lock files: one install's)
_LOG = logging.getLogger(__name__)
WAIT_LIMIT_S = 300.0
"""Longest wait for another process's compile of a group (a cold group takes 20–70 s on 2 loaded cores)."""
_POLL_S = 0.05
_DONE: set[tuple[str, int]] = set()
"""(group, thread budget) pairs this process compiled or waited for."""


def _threads() -> int:
    import numba

    return numba.get_num_threads()


def lock_path(name: str) -> Path:
    """The lock file of group ``name`` for this install and this process's thread budget."""
    key = hashlib.sha256(f"{_PACKAGE}|{name}|{_threads()}".encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"dsareg-kernels-{key}.lock"


@contextlib.contextmanager
def _group_lock(name: str, wait_limit_s: float | None) -> Iterator[bool]:
    """Exclusive while held: one process at a time compiles the group (other workers of a fresh install wait).
    Yields whether the lock is held: False when ``wait_limit_s`` (None: no limit) passed first, or no lock exists here."""
    try:
        import fcntl

        handle = open(lock_path(name), "a")  # noqa: SIM115 - closed below
    except (ImportError, OSError):  # not POSIX, or no temp dir: no lock
        yield False
        return
    try:
        yield _acquire(handle, fcntl, wait_limit_s)
    finally:
        handle.close()


def _acquire(handle, fcntl, wait_limit_s: float | None) -> bool:
    if wait_limit_s is None:
        fcntl.flock(handle, fcntl.LOCK_EX)
        return True
    deadline = time.monotonic() + wait_limit_s
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(_POLL_S)


@contextlib.contextmanager
def compiling_group(name: str) -> Iterator[None]:
    """Hold the group's lock while this process compiles it (its own kernel calls then do not wait for it);
    waits for another holder at most :data:`WAIT_LIMIT_S`."""
    with _bounded(name, WAIT_LIMIT_S):
        yield


def wait_for_group(name: str, wait_limit_s: float | None = None) -> None:
    """Before this process first uses the group's kernels: wait while another process compiles them, at most
    ``wait_limit_s`` (default :data:`WAIT_LIMIT_S`)."""
    if (name, _threads()) in _DONE:
        return
    with _bounded(name, WAIT_LIMIT_S if wait_limit_s is None else wait_limit_s):
        pass


@contextlib.contextmanager
def _bounded(name: str, limit_s: float) -> Iterator[None]:
    started = time.monotonic()
    with _group_lock(name, limit_s) as held:
        if not held and time.monotonic() - started >= limit_s:
            _LOG.warning("kernel group %r: another process has held its compile lock for over %.0f s (frozen?); "
                         "going on without it", name, limit_s)
        _DONE.add((name, _threads()))
        yield
