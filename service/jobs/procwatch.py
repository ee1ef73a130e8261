"""Parent ↔ child process links that survive any process dying at any moment.

Why not ``multiprocessing.Event``: it is a semaphore-backed condition shared by every
process. A process SIGKILLed while it holds the condition's internal lock (an idle
worker inside ``wait``/``clear``/``is_set``) leaves it locked forever, and every later
``set`` — the API's notify on each POST — blocks. Nothing held in shared memory can be
cleaned up after a SIGKILL, so the links here are kernel objects that need no cleanup:

* :class:`WakeLink` (server side): one pipe per worker. ``notify`` writes one byte,
  non-blocking (a full or broken pipe is ignored: the worker polls the store anyway);
  ``close`` is the stop request.
* :class:`WorkerControl` (worker side): a thread reads the pipe; a byte sets the local
  ``wake`` flag, end-of-file (the server closed the pipe, or died and the kernel closed
  it) sets ``stop``. So a worker never outlives its server, even a SIGKILLed one.
* :func:`die_with_parent`: ``prctl(PR_SET_PDEATHSIG)`` on Linux as a second line: the
  kernel sends SIGTERM when the parent dies, which also reaches a worker whose pipe
  thread is somehow stuck.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import sys
import threading
from typing import Any

log = logging.getLogger("dsareg.service.procwatch")

PR_SET_PDEATHSIG = 1
PR_SET_NAME = 15


def _libc() -> ctypes.CDLL:
    """The C library this process has loaded (``dlopen(NULL)``). Not ``ctypes.util.find_library("c")``: that forks
    ``ldconfig -p``, a child that carries this process's name until it execs (a test looking for the one
    ``dsareg-worker0`` found two) and costs a process start for one path."""
    return ctypes.CDLL(None, use_errno=True)


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux only).

    Returns False where unsupported. If the parent already died before the call (the
    signal would then never come), ``sig`` is sent to ourselves at once.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        if _libc().prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            return False
    except OSError:
        return False
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)
    return True


def set_process_name(name: str) -> bool:
    """Name this process for ``ps`` / ``top`` / ``/proc/<pid>/comm`` (Linux ``PR_SET_NAME``, at most 15
    bytes): an operator (and the fault tests) can tell a worker from a validator without guessing."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return _libc().prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0) == 0
    except OSError:
        return False


class WakeLink:
    """Server side of one worker's pipe: non-blocking wake-ups; closing it stops the worker."""

    def __init__(self, ctx: Any):
        self.reader, self.writer = ctx.Pipe(duplex=False)
        os.set_blocking(self.writer.fileno(), False)

    def child_end(self) -> Any:
        """The end to pass to the worker process (a picklable ``Connection``)."""
        return self.reader

    def started(self) -> None:
        """The child holds its own copy now; drop ours so only the writer remains here."""
        self.reader.close()

    def notify(self) -> None:
        with contextlib.suppress(OSError, ValueError):  # full (already woken), closed, or worker gone
            os.write(self.writer.fileno(), b"w")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.writer.close()


class WorkerControl:
    """Stop and wake flags of one worker process (plain thread-local objects, nothing shared)."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.wake = threading.Event()

    def watch(self, conn: Any) -> None:
        """Follow the server's pipe in a daemon thread (wake on a byte, stop on end-of-file)."""
        fd = conn.fileno()
        thread = threading.Thread(target=self._follow, args=(conn, fd), name="parent-link", daemon=True)
        thread.start()

    def _follow(self, conn: Any, fd: int) -> None:
        while True:
            try:
                data = os.read(fd, 4096)
            except InterruptedError:
                continue
            except OSError:
                data = b""
            if not data:
                log.info("server link closed: stopping")
                self.stop.set()
                self.wake.set()
                with contextlib.suppress(OSError):
                    conn.close()
                return
            self.wake.set()

    def request_stop(self, *_: Any) -> None:
        """Signal-handler safe: sets the flags from a new thread (the handler may have
        interrupted this process's main thread while it held an Event's lock)."""
        threading.Thread(target=self._stop_now, name="stop", daemon=True).start()

    def _stop_now(self) -> None:
        self.stop.set()
        self.wake.set()

    def wait_for_work(self, timeout: float) -> None:
        """Sleep until woken, stopped or ``timeout``; the caller then polls the store."""
        self.wake.wait(timeout)
        self.wake.clear()
