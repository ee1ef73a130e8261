"""Progress as a monotone fraction of the expected work."""

import numpy as np

from dsareg_engine.registration.progress import REGISTRATION_SHARE, ProgressPlan
from dsareg_engine.registration.schedule import build_schedule


def test_fraction_is_monotone_and_spread_over_all_stages():
    stages = build_schedule("simultaneous", 800, 300)
    plan = ProgressPlan(stages, starts=4)
    seen = []
    rng = np.random.default_rng(0)
    for index, stage in enumerate(stages):
        ran = int(rng.integers(1, stage.max_iterations))  # stages stop early or late
        for iteration in range(1, ran + 1):
            seen.append(plan.fraction(index, iteration))
        seen.append(plan.stage_done(index))
    assert seen == sorted(seen)
    assert seen[-1] == round(REGISTRATION_SHARE, 4)
    assert all(0 < share < 0.6 for share in plan.shares)  # no stage owns the whole bar


def test_a_stage_that_runs_long_never_overtakes_the_next():
    stages = build_schedule("ap_then_lat", 400, 300)
    plan = ProgressPlan(stages, starts=2)
    late = plan.fraction(0, 10_000)
    assert late <= round(plan.starts_at[1], 4)
    assert plan.fraction(1, 1) >= late
