"""One long-lived thread that starts every validator process of a pool.

Why: a validator asks the kernel to SIGKILL it when the server dies (``PR_SET_PDEATHSIG`` through
:func:`service.jobs.procwatch.die_with_parent`), and the kernel sends that signal when the *thread* that
started the process ends, not when the process does. A validator started by a thread that ends before it
(a request's worker thread that its pool retires, the executor of an ``asyncio.run``) was SIGKILLed then,
idle or in the middle of a parse, and a request sent to it found it dead. Every start made here runs on one
thread that lives as long as the pool, so a validator dies with the server and only with it.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor


class Spawner:
    """Runs process starts on one thread of its own (started on first use, ended by :meth:`stop`)."""

    def __init__(self, name: str = "validator-spawner"):
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._stopped = False

    def run(self, start: Callable[[], None]) -> None:
        """Call ``start`` (e.g. ``process.start``) on the spawner's thread and wait for it; its exception is
        raised here. After :meth:`stop` (the pool is stopping) ``start`` runs on the caller's thread."""
        try:
            started = None if self._stopped else self._thread.submit(start)
        except RuntimeError:  # stopped meanwhile
            started = None
        if started is None:
            start()
        else:
            started.result()

    def stop(self) -> None:
        """End the thread (call it once the processes it started are stopped: its end SIGKILLs them)."""
        self._stopped = True
        self._thread.shutdown(wait=True)
