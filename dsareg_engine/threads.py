"""CPU thread budget of one process: torch's pool and the numba kernels' pool together."""

from __future__ import annotations

import os


def default_cpu_threads(processes: int = 1) -> int:
    """Cores this process may use (cgroup/affinity aware) shared among ``processes``, at least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, cores // max(1, processes))


def set_cpu_threads(count: int) -> int:
    """Use ``count`` threads for torch and for the numba rendering kernels; returns what was set.

    Several worker processes on one machine must not each take every core; numba in
    particular defaults to the machine's core count, not the container's limit.
    """
    import numba
    import torch

    count = max(1, int(count))
    torch.set_num_threads(count)
    numba_count = min(count, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(numba_count)
    return numba_count
