"""A submission's parse allowance, sized from its volume's header (issue 41): small inputs keep the base limits, a
whole-head CTA gets what its first read needs (within the operator's ceilings), a volume beyond them is refused
at once."""

import pytest

from dsareg_engine.io.volume_cost import MEASURED, VolumeCost, expected_read_cost
from service.intake.allowance import MEMORY_MARGIN, TIME_MARGIN, AllowancePolicy, TooLarge, size_allowance
from service.settings import LimitSettings

DEFAULTS = LimitSettings()
POLICY = AllowancePolicy(DEFAULTS.validation_memory_mb, DEFAULTS.validation_timeout_seconds,
                         DEFAULTS.validation_volume_memory_mb, DEFAULTS.validation_volume_timeout_seconds)
WHOLE_HEAD = (512, 512, 440)


def _cost(shape, cached=False) -> VolumeCost:
    voxels = shape[0] * shape[1] * shape[2]
    return VolumeCost(tuple(shape), *expected_read_cost(voxels), cached=cached)


def _bytes(shape) -> int:
    return shape[0] * shape[1] * shape[2] * 2 + 400 * len(shape)  # 16-bit slices and their headers


def test_inputs_without_a_large_volume_keep_the_base_limits():
    base = POLICY.base()
    assert size_allowance(None, 0, POLICY) == base  # a mesh, or a volume declaring no shape
    small = (128, 128, 96)  # a 3D-RA crop: its first read fits the base limits
    assert _bytes(small) / 2**20 + MEMORY_MARGIN * _cost(small).memory_mb < POLICY.memory_mb
    assert size_allowance(_cost(small), _bytes(small), POLICY) == base and not base.raised
    assert size_allowance(_cost(WHOLE_HEAD, cached=True), _bytes(WHOLE_HEAD), POLICY) == base  # its model is kept


def test_a_whole_head_cta_gets_what_its_first_read_needs_with_the_default_settings():
    cost = _cost(WHOLE_HEAD)
    given = size_allowance(cost, _bytes(WHOLE_HEAD), POLICY)
    assert given.raised and given.volume == "512x512x440"
    assert given.memory_mb >= _bytes(WHOLE_HEAD) / 2**20 + MEMORY_MARGIN * cost.memory_mb > POLICY.memory_mb
    assert given.memory_mb <= POLICY.ceiling_mb and given.cpu_s <= POLICY.ceiling_s
    assert given.cpu_s >= TIME_MARGIN * cost.cpu_s > POLICY.timeout_s  # counted in the validator's CPU seconds
    assert given.timeout_s == POLICY.ceiling_s  # the wall-clock: a loaded machine slows the read, not the input
    measured_mb, measured_s = MEASURED[-1][1:]  # the whole-head read that was measured fits what it is given
    assert given.memory_mb > measured_mb and given.cpu_s > measured_s


def test_the_ceilings_bound_the_allowance_and_a_volume_beyond_them_is_refused_at_once():
    cost = _cost(WHOLE_HEAD)
    tight = AllowancePolicy(512, 60.0, volume_memory_mb=int(_bytes(WHOLE_HEAD) / 2**20 + cost.memory_mb) + 10,
                            volume_timeout_s=2 * cost.cpu_s)
    given = size_allowance(cost, _bytes(WHOLE_HEAD), tight)  # expected to fit, its margin does not: the ceiling
    assert (given.memory_mb, given.cpu_s, given.timeout_s) == (tight.volume_memory_mb, tight.volume_timeout_s,
                                                                tight.volume_timeout_s)
    small = AllowancePolicy(512, 60.0, volume_memory_mb=1024, volume_timeout_s=300.0)
    with pytest.raises(TooLarge) as refused:
        size_allowance(cost, _bytes(WHOLE_HEAD), small)
    assert "512x512x440" in refused.value.message and "1024 MB" in refused.value.message
    assert "DSAREG_VALIDATION_VOLUME_MEMORY_MB" in refused.value.accepted
    slow = AllowancePolicy(512, cost.cpu_s / 4, volume_memory_mb=8192, volume_timeout_s=cost.cpu_s / 2)
    with pytest.raises(TooLarge, match="CPU s"):
        size_allowance(cost, _bytes(WHOLE_HEAD), slow)


def test_without_a_memory_limit_only_the_time_is_sized():
    unlimited = AllowancePolicy(0, 60.0, volume_memory_mb=4096, volume_timeout_s=300.0)
    given = size_allowance(_cost(WHOLE_HEAD), _bytes(WHOLE_HEAD), unlimited)
    assert given.memory_mb == 0 and given.cpu_s > 60.0 and given.raised
    assert unlimited.ceiling_mb == 0  # the validator gets no address-space limit at all
