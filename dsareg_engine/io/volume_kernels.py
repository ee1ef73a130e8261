"""When and how a volume reading uses the ``volumes`` kernel group (numba, :mod:`dsareg_engine.warmup`): the
distance transform of its wide bands (:mod:`.distance_kernels`), its smoothing (:mod:`.smoothing_kernels`), the
plate search's kernels (:mod:`.medial_kernels`), its labelling (:mod:`.label_kernels`) and whole-box steps
(:mod:`.voxel_kernels`).

The smoothing and these kernels give the numpy / scipy values to the bit, so only the time differs:
they run where numba's runtime is loaded already (a worker and ``dsareg register``: the renderer's kernels,
:func:`kernels_here`), and for a grid of at least ``KERNEL_VOXELS`` voxels in any process (:func:`load_kernels_for`:
the service's validator reading a whole head). A smaller volume read without numba keeps scipy's: loading numba
adds 190 MB of address space and 0.5 CPU s, more than a small CTA's allowance (:mod:`.volume_cost`) holds and more
than its reading saves. The transform has no scipy twin that fits a TOF slab's memory: a TOF reading loads numba in
any process.
"""

from __future__ import annotations

import sys

KERNEL_VOXELS = 60_000_000
"""A grid this large (a scanner's whole-head grid: 512² × 300 slices and more) is read with the kernels in any
process. The whole-head CTA (512 × 512 × 440) read as the validator reads it: 11.2 → 8.4 CPU s, address space 712 →
894 MB (its allowance: 1,633 MB), resident 668 → 771 MB. A 33 M-voxel crop without a skull (generator A's CTA at
0.4 mm) gained nothing and paid numba's load (2.5 → 3.2 CPU s)."""
KERNEL_WAIT_S = 20.0  # at most this long behind another process compiling the group (~14 s; more on a loaded machine)


def kernels_here() -> bool:
    """Whether this process smooths and measures with the group's kernels: numba is loaded already."""
    return "numba" in sys.modules


def kernels_in_use() -> bool:
    """Whether this step of a reading uses the group's kernels (:func:`kernels_here`); when it does, the group is
    ready (:func:`kernels_ready`: compiled, or waited for)."""
    if not kernels_here():
        return False
    kernels_ready()
    return True


def load_kernels_for(voxels: int) -> None:
    """Before reading a grid of ``voxels`` voxels: numba loaded when the grid holds at least ``KERNEL_VOXELS`` (then
    :func:`kernels_here` holds for the whole reading)."""
    if voxels >= KERNEL_VOXELS and not kernels_here():
        import numba  # noqa: F401 - its runtime, for the kernels of this reading


def kernels_ready() -> None:
    """Before a reading first uses a kernel of the group: a worker's background helper may be compiling it right now
    (once a process); a submission's check reads volumes too, so a frozen helper holds a read up to
    ``KERNEL_WAIT_S``, not the lock's 300 s: then this process compiles what it uses itself."""
    from ..kernels.compile_lock import wait_for_group

    wait_for_group("volumes", wait_limit_s=KERNEL_WAIT_S)


__all__ = ["KERNEL_VOXELS", "KERNEL_WAIT_S", "kernels_here", "kernels_in_use", "kernels_ready", "load_kernels_for"]
