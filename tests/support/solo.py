"""The timed pass on 2 processes, with the tests that must have the machine to themselves run alone (issue 44, item 14).

``pytest -n 2 --dist loadfile -m timed tests/system``: most timed tests share the 2 cores with one other timed test,
their bounds stretched by the contention measured before each (:mod:`tests.support.time_bounds`). A test whose bound
would lose its meaning beside another one (``SOLO`` in ``tests/system/conftest.py``) holds this lock exclusively for
its whole run (set-up, call, teardown); every other timed test holds it shared. So a solo test starts once the other
process's current test has ended, and that process starts its next test only after the solo one (its module's
servers, if any, stay up idle). A turnstile keeps shared holders from starving a solo test that waits. In one process
(no xdist) nothing is locked.
"""

from __future__ import annotations

import contextlib
import fcntl
import tempfile
from collections.abc import Iterator
from pathlib import Path


def lock_folder(run_id: str) -> Path:
    """A folder that the processes of one xdist run (and only they) share."""
    folder = Path(tempfile.gettempdir()) / f"dsareg-solo-{run_id}"
    folder.mkdir(exist_ok=True)
    return folder


@contextlib.contextmanager
def holding(folder: Path, *, exclusive: bool) -> Iterator[None]:
    """Hold the run's lock: exclusively (a solo test) or shared with the other process's tests."""
    with open(folder / "turnstile", "a+") as turnstile, open(folder / "lock", "a+") as lock:
        fcntl.flock(turnstile, fcntl.LOCK_EX)  # while a solo test waits here or below, no shared holder gets past
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
