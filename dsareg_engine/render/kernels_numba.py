"""Fused CPU kernels (numba) for soft and hard silhouettes, with an analytic backward.

Same mathematics as :mod:`.rasterize_torch` + :mod:`.shade` — the tests hold them equal —
but one pass per face over its pixel box, no per-pair tensors. ``n_threads`` is passed in
(``numba.get_num_threads()``) so the compiled kernels can be cached on disk. Work is split over
threads by interleaved image row bands (forward: each band owns its output rows, so
no write conflicts) and interleaved faces (backward: each face owns its gradient).

Per pixel, the signed distance to a triangle is found cheaply: inside (all edge
functions agree with the winding) it is minus the distance to the nearest edge *line*
(exact for a convex polygon); outside, the distance to the farthest violated edge line
is a lower bound that rejects most far pixels before the exact point–segment distances.
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np
from numba import njit, prange

# The work is split into exactly n_threads coarse chunks, so the simple, non-spinning
# "workqueue" layer loses nothing; OpenMP's spinning threads collapse (20x slower seen)
# when other processes — service workers, torch's own pool — compete for the cores.
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"

BANDS_PER_THREAD = 8


@njit(inline="always")
def _face_setup(tri_x, tri_y):
    """Per-face constants: corners, edges, 1/|e|², 1/|e| (0 for a zero-length edge), winding."""
    ax, ay, bx, by, cx, cy = tri_x[0], tri_y[0], tri_x[1], tri_y[1], tri_x[2], tri_y[2]
    e0x, e0y, e1x, e1y, e2x, e2y = bx - ax, by - ay, cx - bx, cy - by, ax - cx, ay - cy
    l0, l1, l2 = e0x * e0x + e0y * e0y, e1x * e1x + e1y * e1y, e2x * e2x + e2y * e2y
    il0 = 1.0 / l0 if l0 > 0.0 else 0.0
    il1 = 1.0 / l1 if l1 > 0.0 else 0.0
    il2 = 1.0 / l2 if l2 > 0.0 else 0.0
    area2 = e0x * (cy - ay) - e0y * (cx - ax)
    winding = 1.0 if area2 > 0.0 else (-1.0 if area2 < 0.0 else 0.0)
    return (ax, ay, bx, by, cx, cy, e0x, e0y, e1x, e1y, e2x, e2y, il0, il1, il2,
            math.sqrt(il0), math.sqrt(il1), math.sqrt(il2), winding)


@njit(inline="always")
def _segment(px, py, sx, sy, ex, ey, inv_len2):
    """(squared distance, t, qx, qy) from p to the segment s + t·e, t ∈ [0, 1]."""
    t = ((px - sx) * ex + (py - sy) * ey) * inv_len2
    t = min(max(t, 0.0), 1.0)
    qx = sx + t * ex
    qy = sy + t * ey
    return (px - qx) * (px - qx) + (py - qy) * (py - qy), t, qx, qy


@njit(inline="always")
def _signed_distance(px, py, s, radius):
    """Signed distance (px, negative inside) from pixel centre p to the face ``s``.

    Returns (d, edge, t, qx, qy) with q the nearest boundary point on edge
    (0 = ab, 1 = bc, 2 = ca) at parameter t. When p is provably farther than
    ``radius`` the call returns d = radius early (edge = -1).
    """
    (ax, ay, bx, by, cx, cy, e0x, e0y, e1x, e1y, e2x, e2y, il0, il1, il2, i0, i1, i2, winding) = s
    # Edge functions scaled by 1/|e|: signed distance to each edge line, positive inside.
    h0 = winding * (e0x * (py - ay) - e0y * (px - ax)) * i0
    h1 = winding * (e1x * (py - by) - e1y * (px - bx)) * i1
    h2 = winding * (e2x * (py - cy) - e2y * (px - cx)) * i2
    if winding != 0.0 and h0 >= 0.0 and h1 >= 0.0 and h2 >= 0.0:
        if h0 <= h1 and h0 <= h2:
            t = ((px - ax) * e0x + (py - ay) * e0y) * il0
            return -h0, 0, t, ax + t * e0x, ay + t * e0y
        if h1 <= h2:
            t = ((px - bx) * e1x + (py - by) * e1y) * il1
            return -h1, 1, t, bx + t * e1x, by + t * e1y
        t = ((px - cx) * e2x + (py - cy) * e2y) * il2
        return -h2, 2, t, cx + t * e2x, cy + t * e2y
    if winding != 0.0 and -min(h0, min(h1, h2)) >= radius:
        return radius, -1, 0.0, 0.0, 0.0
    # Outside a proper triangle the nearest point lies on an edge whose line p violates
    # (h_k < 0), so only those edges need the exact point–segment distance.
    big = 1e300
    d0 = d1 = d2 = big
    t0 = t1 = t2 = q0x = q0y = q1x = q1y = q2x = q2y = 0.0
    if winding == 0.0 or h0 < 0.0:
        d0, t0, q0x, q0y = _segment(px, py, ax, ay, e0x, e0y, il0)
    if winding == 0.0 or h1 < 0.0:
        d1, t1, q1x, q1y = _segment(px, py, bx, by, e1x, e1y, il1)
    if winding == 0.0 or h2 < 0.0:
        d2, t2, q2x, q2y = _segment(px, py, cx, cy, e2x, e2y, il2)
    if d0 <= d1 and d0 <= d2:
        return math.sqrt(d0), 0, t0, q0x, q0y
    if d1 <= d2:
        return math.sqrt(d1), 1, t1, q1x, q1y
    return math.sqrt(d2), 2, t2, q2x, q2y


TABLE_STEP = 1.0 / 128.0
TABLE_MAX = 24.0


def make_tables() -> tuple[np.ndarray, np.ndarray]:
    """Tables of log1p(exp(−a)) and sigmoid(−a) for a ∈ [0, TABLE_MAX] in steps of TABLE_STEP.

    Linear interpolation in them is accurate to ~2e-6, well below float32 image noise,
    and replaces two transcendental calls per face–pixel pair.
    """
    a = np.arange(0.0, TABLE_MAX + 2 * TABLE_STEP, TABLE_STEP)
    return np.log1p(np.exp(-a)), 1.0 / (1.0 + np.exp(a))


@njit(inline="always")
def _lookup(table, a):
    """Linear interpolation of a table sampled at a = k·TABLE_STEP (a ≥ 0); 0 past the end."""
    if a >= TABLE_MAX:
        return 0.0
    position = a * (1.0 / TABLE_STEP)
    k = int(position)
    w = position - k
    return table[k] + w * (table[k + 1] - table[k])


@njit(inline="always")
def _log_keep(d, inv_sigma, exact, softplus_table):
    """log(1 − sigmoid(−d/σ)) = −softplus(−d/σ) = −(max(x, 0) + log1p(exp(−|x|))), x = −d/σ."""
    x = -d * inv_sigma
    a = abs(x)
    if exact:
        tail = math.log1p(math.exp(-a))
    else:
        tail = _lookup(softplus_table, a)
    return -(max(x, 0.0) + tail)


@njit(inline="always")
def _sigmoid(x, exact, sigmoid_table):
    """sigmoid(x)."""
    a = abs(x)
    if exact:
        low = math.exp(-a) / (1.0 + math.exp(-a))
    else:
        low = _lookup(sigmoid_table, a)
    return 1.0 - low if x >= 0.0 else low


@njit(inline="always")
def _row_lines(s, v):
    """Edge-line distances along row v as h_k(u) = a_k + b_k·u (positive inside)."""
    (ax, ay, bx, by, cx, cy, e0x, e0y, e1x, e1y, e2x, e2y, il0, il1, il2, i0, i1, i2, winding) = s
    a0 = winding * (e0x * (v - ay) + e0y * ax) * i0
    a1 = winding * (e1x * (v - by) + e1y * bx) * i1
    a2 = winding * (e2x * (v - cy) + e2y * cx) * i2
    return a0, -winding * e0y * i0, a1, -winding * e1y * i1, a2, -winding * e2y * i2


@njit(inline="always")
def _span(a0, b0, a1, b1, a2, b2, level, lo, hi):
    """Integer u in [lo, hi] where every h_k(u) ≥ level, as (first, last); empty if first > last."""
    first = float(lo)
    last = float(hi)
    for a, b in ((a0, b0), (a1, b1), (a2, b2)):
        if b > 0.0:
            first = max(first, (level - a) / b)
        elif b < 0.0:
            last = min(last, (level - a) / b)
        elif a < level:
            return lo, lo - 1
    if first > last:
        return lo, lo - 1
    return max(lo, int(math.ceil(first))), min(hi, int(math.floor(last)))


@njit(inline="always")
def _band(job, n_bands, height):
    return job // n_bands, (job % n_bands) * height // n_bands, ((job % n_bands) + 1) * height // n_bands - 1


@njit(inline="always")
def _accumulate_row(s, b, v, x0, x1, radius, inv_sigma, exact, softplus_table, floor, out):
    """Add one face's log-keep terms to row v of image b, visiting only pixels that can be near."""
    fv = float(v)
    if s[18] == 0.0:  # degenerate face: no inside, no line bound; exact distances over the box row
        for u in range(x0, x1 + 1):
            d, _, _, _, _ = _signed_distance(float(u), fv, s, radius)
            if d < radius:
                out[b, v, u] += _log_keep(d, inv_sigma, exact, softplus_table) - floor
        return
    a0, b0, a1, b1, a2, b2 = _row_lines(s, fv)
    near_lo, near_hi = _span(a0, b0, a1, b1, a2, b2, -radius, x0, x1)
    in_lo, in_hi = _span(a0, b0, a1, b1, a2, b2, 0.0, near_lo, near_hi)
    if in_lo > in_hi:
        in_lo, in_hi = near_hi + 1, near_hi
    for u in range(near_lo, in_lo):
        d, _, _, _, _ = _signed_distance(float(u), fv, s, radius)
        if d < radius:
            out[b, v, u] += _log_keep(d, inv_sigma, exact, softplus_table) - floor
    for u in range(in_lo, in_hi + 1):
        fu = float(u)
        d = -min(a0 + b0 * fu, min(a1 + b1 * fu, a2 + b2 * fu))
        if d <= 0.0:
            out[b, v, u] += _log_keep(d, inv_sigma, exact, softplus_table) - floor
        else:  # rounding at the span's ends: fall back to the exact test
            d, _, _, _, _ = _signed_distance(fu, fv, s, radius)
            if d < radius:
                out[b, v, u] += _log_keep(d, inv_sigma, exact, softplus_table) - floor
    for u in range(in_hi + 1, near_hi + 1):
        d, _, _, _, _ = _signed_distance(float(u), fv, s, radius)
        if d < radius:
            out[b, v, u] += _log_keep(d, inv_sigma, exact, softplus_table) - floor


@njit(parallel=True, cache=True)
def soft_log_keep(triangles, boxes, height, width, sigma, radius, exact, softplus_table, n_threads, out):
    """out[b, v, u] = Σ_f [log(1 − sigmoid(−d_f/σ)) − log(1 − sigmoid(−r/σ))] over faces with d_f < r.

    triangles (B, F, 3, 2) float; boxes (B, F, 4) int32 [x0, x1, y0, y1]; out (B, H, W), zeroed.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    n_bands = min(height, n_threads * BANDS_PER_THREAD)
    inv_sigma = 1.0 / sigma
    # Subtracting the value at the radius makes each face's term reach 0 continuously there.
    floor = _log_keep(radius, inv_sigma, exact, softplus_table)
    for thread in prange(n_threads):
        for job in range(thread, batch * n_bands, n_threads):
            b, row_lo, row_hi = _band(job, n_bands, height)
            for f in range(n_faces):
                y0 = max(boxes[b, f, 2], row_lo)
                y1 = min(boxes[b, f, 3], row_hi)
                x0 = boxes[b, f, 0]
                x1 = boxes[b, f, 1]
                if y0 > y1 or x0 > x1:
                    continue
                s = _face_setup(triangles[b, f, :, 0], triangles[b, f, :, 1])
                for v in range(y0, y1 + 1):
                    _accumulate_row(s, b, v, x0, x1, radius, inv_sigma, exact, softplus_table, floor, out)


@njit(inline="always")
def _pair_gradient(d, edge, t, qx, qy, u, v, upstream, inv_sigma, exact, sigmoid_table):
    """Gradient of one pair w.r.t. its nearest edge's two corners: (first_x, first_y, t)."""
    # d(log_keep)/dd = sigmoid(−d/σ)/σ ; d|d|/dq = (q − p)/|d| ; dividing by the signed d applies the sign.
    scale = upstream * _sigmoid(-d * inv_sigma, exact, sigmoid_table) * inv_sigma / d
    return scale * (qx - u), scale * (qy - v)


@njit(parallel=True, cache=True)
def soft_log_keep_backward(triangles, boxes, sigma, radius, exact, sigmoid_table, n_threads, grad_log_keep, grad_triangles):
    """grad_triangles (B, F, 3, 2) = d(loss)/d(corners) given d(loss)/d(log_keep) (B, H, W).

    The gradient of a pair flows to the two corners of the face's nearest edge, split
    (1 − t, t) by where the nearest boundary point q lies on it.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    inv_sigma = 1.0 / sigma
    for thread in prange(n_threads):
        for job in range(thread, batch * n_faces, n_threads):
            b = job // n_faces
            f = job % n_faces
            x0, x1, y0, y1 = boxes[b, f, 0], boxes[b, f, 1], boxes[b, f, 2], boxes[b, f, 3]
            if x0 > x1 or y0 > y1:
                continue
            s = _face_setup(triangles[b, f, :, 0], triangles[b, f, :, 1])
            degenerate = s[18] == 0.0
            gax = gay = gbx = gby = gcx = gcy = 0.0
            for v in range(y0, y1 + 1):
                u_lo, u_hi = x0, x1
                if not degenerate:
                    a0, b0, a1, b1, a2, b2 = _row_lines(s, float(v))
                    u_lo, u_hi = _span(a0, b0, a1, b1, a2, b2, -radius, x0, x1)
                for u in range(u_lo, u_hi + 1):
                    upstream = grad_log_keep[b, v, u]
                    if upstream == 0.0:
                        continue
                    d, edge, t, qx, qy = _signed_distance(float(u), float(v), s, radius)
                    if d >= radius or d == 0.0:
                        continue
                    gx, gy = _pair_gradient(d, edge, t, qx, qy, u, v, upstream, inv_sigma, exact, sigmoid_table)
                    w0 = 1.0 - t
                    if edge == 0:
                        gax += w0 * gx
                        gay += w0 * gy
                        gbx += t * gx
                        gby += t * gy
                    elif edge == 1:
                        gbx += w0 * gx
                        gby += w0 * gy
                        gcx += t * gx
                        gcy += t * gy
                    else:
                        gcx += w0 * gx
                        gcy += w0 * gy
                        gax += t * gx
                        gay += t * gy
            grad_triangles[b, f, 0, 0] = gax
            grad_triangles[b, f, 0, 1] = gay
            grad_triangles[b, f, 1, 0] = gbx
            grad_triangles[b, f, 1, 1] = gby
            grad_triangles[b, f, 2, 0] = gcx
            grad_triangles[b, f, 2, 1] = gcy


@njit(parallel=True, cache=True)
def coverage(triangles, boxes, height, width, n_threads, out):
    """out[b, v, u] = True where the pixel centre lies in or on some face (d ≤ 0)."""
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    n_bands = min(height, n_threads * BANDS_PER_THREAD)
    for thread in prange(n_threads):
        for job in range(thread, batch * n_bands, n_threads):
            b, row_lo, row_hi = _band(job, n_bands, height)
            for f in range(n_faces):
                y0 = max(boxes[b, f, 2], row_lo)
                y1 = min(boxes[b, f, 3], row_hi)
                x0 = boxes[b, f, 0]
                x1 = boxes[b, f, 1]
                if y0 > y1 or x0 > x1:
                    continue
                s = _face_setup(triangles[b, f, :, 0], triangles[b, f, :, 1])
                winding = s[18]
                if winding == 0.0:
                    continue
                ax, ay, bx, by, cx, cy, e0x, e0y, e1x, e1y, e2x, e2y = s[:12]
                for v in range(y0, y1 + 1):
                    for u in range(x0, x1 + 1):
                        if out[b, v, u]:
                            continue
                        w0 = winding * (e0x * (v - ay) - e0y * (u - ax))
                        w1 = winding * (e1x * (v - by) - e1y * (u - bx))
                        w2 = winding * (e2x * (v - cy) - e2y * (u - cx))
                        out[b, v, u] = w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0
