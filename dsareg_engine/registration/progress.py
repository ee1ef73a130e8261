"""Progress of one registration as a monotone fraction of the expected work.

Each stage of the schedule gets a share of the registration's part of the bar in proportion
to its expected cost: iterations it usually runs (Adam stages stop on a plateau long before
their cap) × work per iteration (pixels at its scale × views × starts it optimizes). Within a
stage the fraction grows linearly up to 80 % of the share at the expected iteration count
and then approaches the share without reaching it, so a stage that runs longer than expected
slows the bar instead of overtaking the next stage. The fraction never goes back.

The registration fills ``[0, REGISTRATION_SHARE]``; the rest is writing the outputs
(overlays, plots, the animation), reported by :mod:`dsareg_engine.pipeline`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

REGISTRATION_SHARE = 0.92
EXPECTED_ADAM_ITERATIONS = 40
EXPECTED_LBFGS_EVALUATIONS = 20
EXPECTED_GAUSS_NEWTON_ITERATIONS = 5
EXPECTED = {"adam": EXPECTED_ADAM_ITERATIONS, "lbfgs": EXPECTED_LBFGS_EVALUATIONS, "gauss_newton": EXPECTED_GAUSS_NEWTON_ITERATIONS}
PER_ITERATION_OVERHEAD = 0.15
"""Work per iteration that does not shrink with the image (faces, optimizer, bookkeeping),
relative to one full-size view."""


class ProgressPlan:
    """Fractions for ``(stage index, iteration)`` over a list of :class:`~.schedule.Stage`."""

    def __init__(self, stages: Sequence, starts: int, share: float = REGISTRATION_SHARE):
        self.expected = [
            max(1, min(stage.max_iterations, EXPECTED[stage.optimizer]))
            for stage in stages
        ]
        costs = []
        for stage, expected in zip(stages, self.expected):
            active = starts if stage.all_starts else 1
            per_iteration = active * len(stage.views) * (stage.scale ** 2 + PER_ITERATION_OVERHEAD)
            costs.append(expected * per_iteration)
        total = sum(costs) or 1.0
        self.shares = [share * cost / total for cost in costs]
        self.starts_at = [sum(self.shares[:i]) for i in range(len(self.shares))]
        self.share = share
        self.last = 0.0

    def fraction(self, stage_index: int, iteration: int) -> float:
        """Fraction done at ``iteration`` of stage ``stage_index`` (monotone over calls)."""
        x = max(0, iteration) / self.expected[stage_index]
        within = x if x <= 0.8 else 1.0 - 0.2 * math.exp(-(x - 0.8) / 0.2)
        value = self.starts_at[stage_index] + self.shares[stage_index] * within
        self.last = max(self.last, min(value, self.share))
        return round(self.last, 4)

    def stage_done(self, stage_index: int) -> float:
        """Fraction once stage ``stage_index`` has finished."""
        value = self.starts_at[stage_index] + self.shares[stage_index]
        self.last = max(self.last, min(value, self.share))
        return round(self.last, 4)
