"""One writer per kernel group: a file lock per (install, group, thread budget) around numba compiles.

numba's on-disk cache keeps one index file per function and rewrites it on every save without a lock,
so two processes compiling different specializations of one function at once can lose or mix entries.
:mod:`dsareg_engine.warmup` compiles each group of kernels under :func:`compiling_group`; code that
uses a group's kernels first calls :func:`wait_for_group`, which returns at once unless another process
(the background helper) is compiling that group right now, and then only once per process.
"""

from __future__ import annotations

import contextlib
import hashlib
import tempfile
from collections.abc import Iterator
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parents[1]
_DONE: set[tuple[str, int]] = set()
"""(group, thread budget) pairs this process compiled or waited for."""


def _threads() -> int:
    import numba

    return numba.get_num_threads()


@contextlib.contextmanager
def _group_lock(name: str) -> Iterator[None]:
    """Exclusive while held: one process at a time compiles the group (other workers of a fresh install wait)."""
    key = hashlib.sha256(f"{_PACKAGE}|{name}|{_threads()}".encode()).hexdigest()[:16]
    try:
        import fcntl

        handle = open(Path(tempfile.gettempdir()) / f"dsareg-kernels-{key}.lock", "a")  # noqa: SIM115 - closed below
    except (ImportError, OSError):  # not POSIX, or no temp dir: no lock
        yield
        return
    try:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield
    finally:
        handle.close()


@contextlib.contextmanager
def compiling_group(name: str) -> Iterator[None]:
    """Hold the group's lock while this process compiles it (its own kernel calls then do not wait for it)."""
    with _group_lock(name):
        _DONE.add((name, _threads()))
        yield


def wait_for_group(name: str) -> None:
    """Before this process first uses the group's kernels: wait while another process compiles them."""
    if (name, _threads()) not in _DONE:
        with _group_lock(name):
            _DONE.add((name, _threads()))
