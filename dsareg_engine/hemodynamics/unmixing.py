"""Points overlapped in both views, measured by unmixing: each curve is the sum of the vessels its footprint sees.

A point's curve in a view (:mod:`.sampling`: footprint mean minus background ring, baseline removed) is, by the
model at the pose, the sum over the vessel points ``j`` whose stretches cross its footprint of

    ``c_i(t) = s · Σ_j M_ij · q_j(t)``

``M_ij`` (mm): the footprint's mean path length through the stretches owned by point ``j`` (each stretch a ray
crosses, :func:`dsareg_engine.render.ray_layers.ray_stretches`, is owned by the vessel point nearest its middle);
``q_j(t)``: point ``j``'s contrast concentration, relative (1 = what a typical filled vessel of the run shows at its
peak); ``s``: the view's opacity per mm of filled vessel at the peak (the median over the points it sees clean and
filled, :func:`view_scale`).

**Known** points are those some view sees clean (:mod:`.overlap`): ``q_j = c_j / (s · Σ_j' M_jj')`` from that
view's own curve (a clean footprint sees one vessel), taken onto the other view's clock by linear interpolation
where only the other view sees it clean. **Unknown** points are measurable in the view but clean in none: per
view, their ``q`` solves the least-squares system of their own rows (known contributions subtracted) with a
smoothness prior along the model's edges (``SMOOTHNESS`` per edge, rows normalised by their path length):
a vessel's concentration changes little from one vertex to the next. The parameters of the unknown points are
then taken from ``q`` (:func:`.parameters.curve_parameters`, the fill test relative to 1: a typical filled vessel;
its noise in ``q`` is the curve's over ``s`` × the footprint's path through the point's own vessel, ``own_mm``: a
point whose footprint is mostly other vessels has little evidence of its own),
and an unmixed curve whose peak lies before contrast reached the run or at its last frame, or stands above
``MAX_RELATIVE_PEAK`` typical vessels, is not taken as filled
(:func:`within_run`: what an imperfect subtraction leaves, e.g. a blocked branch crossed by filled vessels).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ..geometry.rig import ViewGeometry
from ..render.ray_layers import RayStretches
from .parameters import CurveParameters, baseline_frames, curve_parameters

SMOOTHNESS = 0.3
MAX_RELATIVE_PEAK = 5.0
NEIGHBOUR_RINGS = 3
RIDGE = 1e-6


@dataclass(frozen=True)
class ViewMixing:
    """One view's curves and what they are made of: ``curves`` ``(N, T)`` (baseline removed), ``noise`` ``(N,)``,
    ``mixing`` ``(N, N)`` csr (``M`` of the module docstring, mm), ``times_s`` ``(T,)`` on the common clock,
    ``own_mm`` ``(N,)`` the part of each footprint's path through its own vessel (:func:`.overlap.own_path_mm`;
    ``None``: all of it)."""

    curves: np.ndarray
    noise: np.ndarray
    mixing: sparse.csr_matrix
    times_s: np.ndarray
    own_mm: np.ndarray | None = None

    @property
    def path_mm(self) -> np.ndarray:
        """``(N,)`` the footprint's mean path length through the model (``Σ_j M_ij``)."""
        return np.asarray(self.mixing.sum(axis=1)).ravel()


def stretch_owners(stretches: RayStretches, view: ViewGeometry, mesh_to_world: np.ndarray, centres: cKDTree,
                   count: int) -> sparse.csr_matrix:
    """``(H·W, N)`` csr: per pixel, the length (mm) of the stretches owned by each vessel point (the one whose
    centre, a ``cKDTree`` of ``(N, 3)`` mesh mm, is nearest the stretch's middle)."""
    pixel, length, middle = stretches.middles_in_view(view.focal_px, view.principal_point_px)
    view_to_mesh = np.linalg.inv(view.world_to_view @ np.asarray(mesh_to_world, float))
    middle_mesh = middle @ view_to_mesh[:3, :3].T + view_to_mesh[:3, 3]
    owner = centres.query(middle_mesh)[1] if len(pixel) else np.zeros(0, int)
    return sparse.csr_matrix((length, (pixel, owner)), shape=(stretches.covered.size, count))


def view_scale(peak: np.ndarray, path_mm: np.ndarray, reference: np.ndarray) -> float:
    """Opacity per mm of filled vessel at the peak: the median of ``peak / path_mm`` over ``reference`` (bool)."""
    ratio = peak[reference] / np.maximum(path_mm[reference], 1e-6)
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    return float(np.median(ratio)) if len(ratio) else 0.0


def known_concentration(mix: ViewMixing, clean: np.ndarray, scale: float) -> np.ndarray:
    """``(N, T)`` ``q`` of the points ``clean`` (bool) in this view from their own curves; NaN elsewhere."""
    path = mix.path_mm
    usable = clean & (path > 0) & (scale > 0)
    out = np.full(mix.curves.shape, np.nan)
    out[usable] = mix.curves[usable] / (scale * path[usable])[:, None]
    return out


def on_clock(q: np.ndarray, from_s: np.ndarray, to_s: np.ndarray) -> np.ndarray:
    """Rows of ``q`` ``(N, T)`` sampled at ``from_s`` moved to ``to_s`` (linear, the ends held)."""
    if len(from_s) == len(to_s) and np.allclose(from_s, to_s):
        return q
    return np.array([np.interp(to_s, from_s, row) for row in q]) if len(q) else np.zeros((0, len(to_s)))


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """``(E, 2)`` the model's unique edges."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def solve_unknown(mix: ViewMixing, rows: np.ndarray, known: np.ndarray, q_known: np.ndarray, scale: float,
                  edges: np.ndarray) -> np.ndarray:
    """``(len(rows), T)`` ``q`` of the points ``rows`` (indices) from their curves, the ``known`` points' ``q_known``
    ``(N, T)`` subtracted (bool ``known``), with the smoothness prior over ``edges``."""
    count = len(known)
    path = mix.path_mm[rows]
    data = sparse.diags(1.0 / np.maximum(path, 1e-6)) @ mix.mixing[rows]  # rows sum to 1
    target = mix.curves[rows] / (scale * np.maximum(path, 1e-6))[:, None]
    known_q = np.where(known[:, None], np.nan_to_num(q_known), 0.0)
    target = target - data @ known_q
    unknown = ~known
    unknown_cols = np.union1d(rows, np.flatnonzero(np.asarray(abs(data).sum(axis=0)).ravel() > 0))
    unknown_cols = unknown_cols[unknown[unknown_cols]]
    column = np.full(count, -1)
    column[unknown_cols] = np.arange(len(unknown_cols))
    a_data = data[:, unknown_cols]
    a, b = edges[:, 0], edges[:, 1]
    tied = ((column[a] >= 0) & ((column[b] >= 0) | known[b])) | ((column[b] >= 0) & known[a])
    a, b = a[tied], b[tied]
    swap = column[a] < 0  # the unknown end first
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    both = column[b] >= 0
    n_edges = len(a)
    smooth_rows = np.concatenate([np.arange(n_edges), np.flatnonzero(both)])
    smooth_cols = np.concatenate([column[a], column[b[both]]])
    smooth_vals = np.concatenate([np.full(n_edges, SMOOTHNESS), np.full(int(both.sum()), -SMOOTHNESS)])
    a_smooth = sparse.csr_matrix((smooth_vals, (smooth_rows, smooth_cols)), shape=(n_edges, len(unknown_cols)))
    smooth_target = np.where(both[:, None], 0.0, SMOOTHNESS * known_q[b])
    system = sparse.vstack([a_data, a_smooth]).tocsc()
    rhs = np.vstack([target, smooth_target])
    normal = (system.T @ system + RIDGE * sparse.identity(len(unknown_cols))).tocsc()
    solution = splu(normal).solve(np.asarray(system.T @ rhs))
    return solution[column[rows]]


def unmix_view(mix: ViewMixing, rows: np.ndarray, known: np.ndarray, q_known: np.ndarray, scale: float,
               edges: np.ndarray) -> CurveParameters:
    """Parameters of the points ``rows`` from their unmixed ``q`` (see the module docstring); ``peak_opacity`` and
    ``area`` back in opacity: what the point's footprint would show were it clean (``q · s · Σ_j M_ij``)."""
    q = solve_unknown(mix, rows, known, q_known, scale, edges)
    opacity_per_q = scale * np.maximum(mix.path_mm[rows], 1e-6)
    own_mm = mix.path_mm[rows] if mix.own_mm is None else mix.own_mm[rows]
    found = curve_parameters(q, mix.times_s, mix.noise[rows] / (scale * np.maximum(own_mm, 1e-6)), np.ones(len(rows)),
                             np.ones(len(rows), bool), typical_per_mm=1.0, gamma_fit=True)
    found = within_run(found, mix.times_s, mix.times_s[baseline_frames(mix.curves)])
    return replace(found, peak_opacity=found.peak_opacity * opacity_per_q, area=found.area * opacity_per_q,
                   noise=mix.noise[rows])


def within_run(found: CurveParameters, times_s: np.ndarray, run_arrival_s: float) -> CurveParameters:
    """``found`` (in ``q``: 1 = a typical filled vessel's peak) with the implausible unmixed curves made not filled
    (every value NaN): a peak before contrast reached the run anywhere (``run_arrival_s``), at its last frame (no
    peak seen), or above ``MAX_RELATIVE_PEAK`` (an ill-conditioned solve) is what a subtraction of the crossing
    vessels left, not a bolus."""
    inside = (found.peak_s >= run_arrival_s) & (found.peak_s < times_s[-1]) & (found.peak_opacity <= MAX_RELATIVE_PEAK)
    return not_filled(found, ~inside)


def measured_within_run(found: CurveParameters, times_s: np.ndarray, run_arrival_s: float, own_mm: np.ndarray | None,
                        scale: float) -> CurveParameters:
    """``found`` (measured curves, opacity) with the implausible ones made not filled: a peak before contrast
    reached the run anywhere (``run_arrival_s``: a noise spike), or above ``MAX_RELATIVE_PEAK`` times what the
    footprint's path through the point's own vessel shows at the peak (``scale · own_mm`` ``(N,)``: the contrast
    is another vessel's, or the vessel is barely in the footprint)."""
    early = found.peak_s < run_arrival_s
    if own_mm is not None and scale > 0:
        early = early | (found.peak_opacity > MAX_RELATIVE_PEAK * scale * own_mm)
    return not_filled(found, early)


def not_filled(found: CurveParameters, drop: np.ndarray) -> CurveParameters:
    """``found`` with the points ``drop`` (bool) not filled: every value NaN."""
    keep = found.filled & ~drop
    fields = {name: np.where(keep, getattr(found, name), np.nan)
              for name in ("arrival_s", "peak_s", "peak_opacity", "mtt_s", "area")}
    return replace(found, filled=keep, **fields)


def empty_around(edges: np.ndarray, known_empty: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: most of the known points within ``NEIGHBOUR_RINGS`` edges of each point are known empty (a
    clean view saw no contrast there). An unmixed value there contradicts the clean measurements of its own
    vessel around it, as a clean view that sees it empty would (:mod:`.combine`'s ``views_disagree``)."""
    count = len(known)
    adjacency = sparse.csr_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                                  shape=(count, count)) + sparse.identity(count, format="csr")
    reach = adjacency
    for _ in range(NEIGHBOUR_RINGS - 1):
        reach = ((reach @ adjacency) > 0).astype(float)
    empty, seen = reach @ known_empty.astype(float), reach @ known.astype(float)
    return empty > 0.5 * np.maximum(seen, 1e-9)
