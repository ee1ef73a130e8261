"""A process's exit without the interpreter's final garbage collections over everything it loaded.

At exit CPython clears its modules and runs full garbage collections over what is left. A process that
loaded the engine (torch, scipy, numba, the image readers: millions of tracked objects) spent about
1 CPU-s and 4-5 s of wall time there on a loaded 2-core machine (2026-12-03): every worker, input
validator and command-line run paid it, and a server's stop waited for it twice (its workers, then its
validators). :func:`gc.freeze` at exit moves every object into the permanent generation, which those
collections do not walk: the exit took 0.9 s. Reference counting still frees what it frees, the
``atexit`` handlers and the flush of the standard streams run as before; only unreachable cycles are
left to the operating system, which reclaims the whole process anyway.
"""

from __future__ import annotations

import atexit
import gc

_registered = False


def skip_exit_collections() -> None:
    """Freeze the heap when this process exits (registered once; call it at a process's start)."""
    global _registered
    if not _registered:
        atexit.register(gc.freeze)
        _registered = True
