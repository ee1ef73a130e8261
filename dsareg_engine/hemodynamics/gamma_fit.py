"""A gamma-variate fit of each curve's first pass: mean transit time and area under the curve.

The first pass of a bolus is modelled as ``g(t) = K · (t − t0)^α · exp(−(t − t0) / β)`` for ``t > t0``. For a given
onset ``t0``, ``ln g`` is linear in ``(ln K, α, 1/β)``: the fit is a weighted linear least squares on the samples
of the first pass (from ``t0`` to the last sample still above ``TAIL_FRACTION`` of the peak after it: the tail
where recirculation begins is left out), weights ``c²`` (the log of a small sample is noise). The onset is the
candidate, among ``ONSET_CANDIDATES`` between ``arrival − ONSET_REACH × (peak − arrival)`` and the arrival, whose
fit leaves the least squared residual (then ``ONSET_CANDIDATES`` more within one step of it) in opacity over the whole first pass (the fit is 0 before its onset).

* ``mtt_s``: the fitted first pass's mean time after its onset, ``(α + 1) β`` (its first moment about ``t0``);
* ``area``: its area, ``K β^(α+1) Γ(α + 1)`` (opacity × s).

NaN where the curve is not filled, the fit has fewer than ``MIN_SAMPLES`` samples, or α or β is not positive,
and where the fitted first pass starts before the run's first frame or reaches its mean time (onset + ``mtt_s``)
after its last: the run did not see the bolus from its start to half its passage, so the fit's ends, and with
them both values, would be a guess beyond the data (a 2.25 s run gave ``mtt_s`` 6.08 s).
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln

ONSET_CANDIDATES = 8
ONSET_REACH = 2.0
TAIL_FRACTION = 0.3
MIN_SAMPLES = 4


def _fit_at(times: np.ndarray, curves: np.ndarray, onset: np.ndarray, use: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(ln K, α, 1/β, squared residual)`` per curve ``(N,)`` with onsets ``onset`` ``(N,)`` on samples ``use``."""
    tau = times[None, :] - onset[:, None]
    window = use
    use = use & (tau > 0) & (curves > 0)
    safe_tau = np.where(use, tau, 1.0)
    log_tau = np.log(safe_tau)
    weight = np.where(use, curves, 0.0) ** 2
    target = np.log(np.where(use, curves, 1.0))
    columns = (np.ones_like(safe_tau), log_tau, -safe_tau)  # the design's columns, (N, T) each
    normal = np.empty((len(curves), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            normal[:, i, j] = normal[:, j, i] = (weight * columns[i] * columns[j]).sum(axis=1)
    normal += 1e-9 * np.eye(3)
    rhs = np.stack([(weight * column * target).sum(axis=1) for column in columns], axis=1)
    coefficients = np.linalg.solve(normal, rhs[..., None])[..., 0]
    log_fit = coefficients[:, :1] + coefficients[:, 1:2] * log_tau - coefficients[:, 2:] * safe_tau
    fitted = np.where(tau > 0, np.exp(np.clip(log_fit, -50, 50)), 0.0)
    residual = np.where(window, (fitted - curves) ** 2, 0.0).sum(axis=1)  # the same samples for every onset
    enough = use.sum(axis=1) >= MIN_SAMPLES
    return coefficients[:, 0], coefficients[:, 1], coefficients[:, 2], np.where(enough, residual, np.inf)


def _better(best: tuple, times: np.ndarray, curves: np.ndarray, onset: np.ndarray, use: np.ndarray) -> tuple:
    """``best`` ``(residual, ln K, α, 1/β, onset)`` updated where the fit at ``onset`` leaves less residual."""
    ln_k, alpha, inverse_beta, residual = _fit_at(times, curves, onset, use)
    better = residual < best[0]
    return tuple(np.where(better, new, old) for new, old in zip((residual, ln_k, alpha, inverse_beta, onset), best))


def first_pass(times: np.ndarray, curves: np.ndarray, peak_s: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """``(N, T)`` bool: the samples up to the last one still above ``TAIL_FRACTION`` of the peak after it."""
    after = times[None, :] > peak_s[:, None]
    low = after & (curves < TAIL_FRACTION * peak[:, None])
    first_low = np.where(low.any(axis=1), np.argmax(low, axis=1), curves.shape[1])
    return np.arange(curves.shape[1])[None, :] < first_low[:, None]


def gamma_variate(times_s: np.ndarray, curves: np.ndarray, arrival_s: np.ndarray, peak_s: np.ndarray,
                  peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mtt_s (N,), area (N,))`` of baseline-free ``curves`` ``(N, T)`` at ``times_s`` with their arrival, peak
    time and peak value ``(N,)`` (NaN where not filled): see the module docstring."""
    times = np.asarray(times_s, float)
    count = len(curves)
    mtt, area = np.full(count, np.nan), np.full(count, np.nan)
    rows = np.flatnonzero(np.isfinite(arrival_s) & np.isfinite(peak_s) & (peak > 0))
    if not len(rows):
        return mtt, area
    c, arrival, rise = curves[rows], arrival_s[rows], np.maximum(peak_s[rows] - arrival_s[rows], 1e-3)
    use = first_pass(times, c, peak_s[rows], peak[rows])
    best = (np.full(len(rows), np.inf),) + tuple(np.full(len(rows), np.nan) for _ in range(4))
    step = ONSET_REACH / (ONSET_CANDIDATES - 1)
    for fraction in np.linspace(ONSET_REACH, 0.0, ONSET_CANDIDATES):
        best = _better(best, times, c, arrival - fraction * rise, use)
    coarse = best[4].copy()
    for offset in np.linspace(-step, step, ONSET_CANDIDATES):  # refined around the best coarse onset
        best = _better(best, times, c, coarse + offset * rise, use)
    _, ln_k, alpha, inverse_beta, onset = best
    good = np.isfinite(alpha) & (alpha > 0) & (inverse_beta > 0)
    beta = np.where(good, 1.0 / np.where(good, inverse_beta, 1.0), np.nan)
    seen = (onset >= times[0]) & (onset + (alpha + 1.0) * np.where(good, beta, 0.0) <= times[-1])
    good &= seen  # the fitted bolus starts and reaches its mean time within the run: its values are not guesses
    mtt[rows] = np.where(good, (alpha + 1.0) * beta, np.nan)
    with np.errstate(over="ignore", invalid="ignore"):
        area[rows] = np.where(good, np.exp(ln_k + (alpha + 1.0) * np.log(np.where(good, beta, 1.0))
                                           + gammaln(alpha + 1.0)), np.nan)
    return mtt, area
