"""Serial twins of the parallel numba kernels, for a thread budget of one thread.

numba's ``workqueue`` layer runs a ``parallel=True`` kernel on its pool threads even when
``numba.get_num_threads()`` is 1: the calling thread hands the work to a pool thread and sleeps
until it is done, two context switches per launch (a registration launches ~400 kernels) and,
when other processes hold the cores, a wait for the pool thread to be scheduled. Measured on
2 x86_64 cores shared with other work: a 128 px, 60-iteration registration took 0.91–0.96 s
wall for 0.45–0.47 CPU-s with the parallel kernels on one thread, 0.73–0.78 s for the same CPU
with the twins. A service worker runs with a 1-thread budget (``THREADS_PER_WORKER``).

A twin is the kernel's own Python function compiled without ``parallel=True``: ``prange`` runs
as ``range`` on the calling thread, visiting the same work in the same order as the parallel
kernel's single thread (``tests/unit/render/test_serial_kernels.py`` holds their outputs equal). It
is cached on disk under its own name (numba's cache key ignores ``parallel``, so a twin of the
same function object would load the parallel build, or the other way round).
"""

from __future__ import annotations

import types
from typing import Any

import numba

SERIAL_SUFFIX = "_serial"
_KEPT_OPTIONS = ("fastmath", "boundscheck", "error_model")


def serial_twin(kernel: Any) -> Any:
    """``kernel`` (a ``numba.njit(parallel=True)`` dispatcher) compiled serially, cached as ``<name>_serial``."""
    source = kernel.py_func
    twin = types.FunctionType(source.__code__, source.__globals__, source.__name__ + SERIAL_SUFFIX,
                              source.__defaults__, source.__closure__)
    twin.__qualname__ = source.__qualname__ + SERIAL_SUFFIX
    twin.__doc__ = source.__doc__
    options = {k: v for k, v in kernel.targetoptions.items() if k in _KEPT_OPTIONS and v is not None}
    return numba.njit(cache=True, **options)(twin)


class KernelPair:
    """A parallel kernel and its serial twin; :meth:`pick` chooses by the calling thread's budget."""

    def __init__(self, parallel: Any):
        self.parallel = parallel
        self.serial = serial_twin(parallel)

    def pick(self, n_threads: int) -> Any:
        """The serial twin for ``n_threads`` ≤ 1, else the parallel kernel."""
        return self.serial if n_threads <= 1 else self.parallel


__all__ = ["KernelPair", "serial_twin"]
