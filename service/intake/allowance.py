"""One submission's parse allowance: the validator's base limits, or more for a volume whose header says it needs it.

Why (issue 41): the validator parses every submission under ``validation_memory_mb`` of address space and
``validation_timeout_seconds`` (sized for images and models: a decompression bomb must fail fast). A whole-head CTA
(512 × 512 × 440 voxels) needs ~1.5 GB and ~50 CPU s for its first read, so a default deployment refused it. Raising
the base limits for every submission would let any small file decode to gigabytes; moving the read to the worker
would accept a job whose volume may not be readable. Instead the validator reads the volume's *header* first (no
voxel decoded: ``engine.volume_read_cost``), and this module sizes that submission's allowance from the voxel count:

* memory: the volume's file bytes (held during the read) + :data:`MEMORY_MARGIN` × the measured address-space growth
  for that many voxels;
* time: :data:`TIME_MARGIN` × the measured CPU s, counted in the validator's **CPU** seconds (what the input costs:
  on 2 cores loaded by other work the whole-head read's 40 CPU s took 235 s of wall-clock, which a wall-clock
  allowance of a few times its CPU s refuses or barely admits), and the wall-clock bounded by the ceiling;
* never below the base limits, never above the operator's ceilings (``validation_volume_memory_mb``,
  ``validation_volume_timeout_seconds``); a volume expected to need more than a ceiling is refused at once, naming
  its shape, the expected cost and the setting (not after a minute of work);
* a volume whose model is kept (the model cache) or that fits the base limits: the base limits, unchanged.

The model the validator makes is kept in the model cache, so the worker (and every later job on the series) takes
it instead of reading the volume again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

MEMORY_MARGIN = 1.5  # the measured growth varies with the content (bone, vessels kept); the allocator's slack
TIME_MARGIN = 3.0  # of the validator's CPU s (the measured reads vary by ~20 % with the content and the machine)
MB = 1 << 20


@dataclass(frozen=True)
class AllowancePolicy:
    """The validator's base limits and the ceilings of what one volume's parse may be given (0: none above base)."""

    memory_mb: int  # validation_memory_mb (0: no memory limit at all)
    timeout_s: float  # validation_timeout_seconds
    volume_memory_mb: int = 0  # validation_volume_memory_mb
    volume_timeout_s: float = 0.0  # validation_volume_timeout_seconds

    @property
    def ceiling_mb(self) -> int:
        """The hard address-space limit of a validator (0: none)."""
        return 0 if self.memory_mb == 0 else max(self.memory_mb, self.volume_memory_mb)

    @property
    def ceiling_s(self) -> float:
        return max(self.timeout_s, self.volume_timeout_s)

    def base(self) -> Allowance:
        return Allowance(self.memory_mb, self.timeout_s)


@dataclass(frozen=True)
class Allowance:
    """What one parse may use: ``memory_mb`` over the validator's warmed-up size (0: unlimited), ``timeout_s`` of
    wall-clock and, for a large volume, ``cpu_s`` of the validator's CPU time (0: none counted); ``volume``: the
    volume it was sized for (``512x512x440``), empty when these are the base limits."""

    memory_mb: int
    timeout_s: float
    volume: str = ""
    cpu_s: float = 0.0

    @property
    def raised(self) -> bool:
        return bool(self.volume)

    def as_json(self) -> dict[str, Any]:
        return {"memory_mb": self.memory_mb, "timeout_s": self.timeout_s, "volume": self.volume, "cpu_s": self.cpu_s}

    def describe(self) -> str:
        """The time it allowed, for a refusal: ``60 s``, or ``121 CPU s (300 s)``."""
        return f"{self.cpu_s:g} CPU s ({self.timeout_s:g} s)" if self.cpu_s > 0 else f"{self.timeout_s:g} s"


class TooLarge(Exception):  # noqa: N818 - a refusal carried to the validator's reply
    """The volume is expected to need more than the ceilings: ``message``, ``accepted`` for the client."""

    def __init__(self, message: str, accepted: str):
        super().__init__(message)
        self.message, self.accepted = message, accepted


def size_allowance(cost: Any, volume_bytes: int, policy: AllowancePolicy) -> Allowance:
    """The allowance of a submission whose volume is ``cost`` (``engine.VolumeCost``; None: no volume, or no shape
    declared) and ``volume_bytes`` of files; raises :class:`TooLarge` when even the ceilings are expected to fall
    short."""
    if cost is None or cost.cached:
        return policy.base()
    need_mb = volume_bytes / MB + cost.memory_mb
    memory = 0 if policy.memory_mb == 0 else max(policy.memory_mb, math.ceil(volume_bytes / MB
                                                                              + MEMORY_MARGIN * cost.memory_mb))
    cpu = max(policy.timeout_s, TIME_MARGIN * cost.cpu_s)
    if memory == policy.memory_mb and cpu == policy.timeout_s:
        return policy.base()
    shape = "x".join(str(n) for n in cost.shape)
    if (policy.memory_mb and need_mb > policy.ceiling_mb) or cost.cpu_s > policy.ceiling_s:
        raise TooLarge(
            f"a volume of {shape} voxels is expected to need about {need_mb:.0f} MB and {cost.cpu_s:.0f} CPU s to "
            f"read, more than this server gives one submission's check ({_ceilings(policy)})",
            accepted="a smaller volume (fewer slices, or cropped to the head), or a server whose operator raised "
                     "DSAREG_VALIDATION_VOLUME_MEMORY_MB / DSAREG_VALIDATION_VOLUME_TIMEOUT_SECONDS")
    memory = memory if policy.memory_mb == 0 else min(memory, policy.ceiling_mb)
    return Allowance(memory, policy.ceiling_s, shape, cpu_s=min(cpu, policy.ceiling_s))


def _ceilings(policy: AllowancePolicy) -> str:
    memory = "no memory limit" if policy.memory_mb == 0 else f"{policy.ceiling_mb} MB"
    return f"{memory}, {policy.ceiling_s:g} s"


__all__ = ["MEMORY_MARGIN", "TIME_MARGIN", "Allowance", "AllowancePolicy", "TooLarge", "size_allowance"]
