"""Fused CPU kernels (numba) for soft and hard silhouettes, with an analytic backward.

Same mathematics as :mod:`.rasterize_torch` + :mod:`.shade` — the tests hold them equal —
but one pass per face over its pixel box, no per-pair tensors. Work is split over
threads by interleaved image row bands (forward: each band owns its output rows, so
no write conflicts) and interleaved faces (backward: each face owns its gradient).
"""

from __future__ import annotations

import math

import numba
from numba import njit, prange

BANDS_PER_THREAD = 8


@njit(inline="always")
def _signed_distance(px, py, ax, ay, bx, by, cx, cy, area2):
    """Signed distance (negative inside) from (px, py) to triangle abc; nearest edge and t.

    Returns (d, edge, t, qx, qy): edge 0=ab, 1=bc, 2=ca; t the position of the nearest
    point q on that edge (0 at its first corner).
    """
    best = 1e300
    edge = 0
    best_t = 0.0
    qx = 0.0
    qy = 0.0
    for k in range(3):
        if k == 0:
            sx, sy, ex, ey = ax, ay, bx - ax, by - ay
        elif k == 1:
            sx, sy, ex, ey = bx, by, cx - bx, cy - by
        else:
            sx, sy, ex, ey = cx, cy, ax - cx, ay - cy
        length2 = ex * ex + ey * ey
        t = 0.0
        if length2 > 0.0:
            t = ((px - sx) * ex + (py - sy) * ey) / length2
            t = min(max(t, 0.0), 1.0)
        nx = sx + t * ex
        ny = sy + t * ey
        dist2 = (px - nx) * (px - nx) + (py - ny) * (py - ny)
        if dist2 < best:
            best = dist2
            edge = k
            best_t = t
            qx = nx
            qy = ny
    d = math.sqrt(best)
    if area2 != 0.0:
        w0 = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
        w1 = (cx - bx) * (py - by) - (cy - by) * (px - bx)
        w2 = (ax - cx) * (py - cy) - (ay - cy) * (px - cx)
        if area2 > 0.0:
            inside = w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0
        else:
            inside = w0 <= 0.0 and w1 <= 0.0 and w2 <= 0.0
        if inside:
            d = -d
    return d, edge, best_t, qx, qy


@njit(inline="always")
def _log_keep(d, inv_sigma):
    """log(1 − sigmoid(−d/σ)) = −softplus(−d/σ), computed stably."""
    x = -d * inv_sigma
    if x > 0.0:
        return -(x + math.log1p(math.exp(-x)))
    return -math.log1p(math.exp(x))


@njit(parallel=True, cache=True)
def soft_log_keep(triangles, boxes, height, width, sigma, radius, out):
    """out[b, v, u] = Σ_f log(1 − sigmoid(−d_f/σ)) over faces within ``radius`` px.

    triangles (B, F, 3, 2) float; boxes (B, F, 4) int32; out (B, H, W) float, zeroed.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    n_threads = numba.get_num_threads()
    n_bands = min(height, n_threads * 8)
    inv_sigma = 1.0 / sigma
    for thread in prange(n_threads):
        for job in range(thread, batch * n_bands, n_threads):
            b = job // n_bands
            band = job % n_bands
            row_lo = band * height // n_bands
            row_hi = (band + 1) * height // n_bands - 1
            for f in range(n_faces):
                y0 = max(boxes[b, f, 2], row_lo)
                y1 = min(boxes[b, f, 3], row_hi)
                x0 = boxes[b, f, 0]
                x1 = boxes[b, f, 1]
                if y0 > y1 or x0 > x1:
                    continue
                ax, ay = triangles[b, f, 0, 0], triangles[b, f, 0, 1]
                bx, by = triangles[b, f, 1, 0], triangles[b, f, 1, 1]
                cx, cy = triangles[b, f, 2, 0], triangles[b, f, 2, 1]
                area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                for v in range(y0, y1 + 1):
                    for u in range(x0, x1 + 1):
                        d, _, _, _, _ = _signed_distance(u, v, ax, ay, bx, by, cx, cy, area2)
                        if d < radius:
                            out[b, v, u] += _log_keep(d, inv_sigma)


@njit(parallel=True, cache=True)
def soft_log_keep_backward(triangles, boxes, sigma, radius, grad_log_keep, grad_triangles):
    """Accumulate d(loss)/d(triangles) given d(loss)/d(log_keep) per pixel.

    grad_log_keep (B, H, W); grad_triangles (B, F, 3, 2), zeroed.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    n_threads = numba.get_num_threads()
    inv_sigma = 1.0 / sigma
    for thread in prange(n_threads):
        for job in range(thread, batch * n_faces, n_threads):
            b = job // n_faces
            f = job % n_faces
            x0, x1, y0, y1 = boxes[b, f, 0], boxes[b, f, 1], boxes[b, f, 2], boxes[b, f, 3]
            if x0 > x1 or y0 > y1:
                continue
            corner_x = triangles[b, f, :, 0]
            corner_y = triangles[b, f, :, 1]
            ax, ay, bx, by, cx, cy = corner_x[0], corner_y[0], corner_x[1], corner_y[1], corner_x[2], corner_y[2]
            area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            gx0 = gy0 = gx1 = gy1 = gx2 = gy2 = 0.0
            for v in range(y0, y1 + 1):
                for u in range(x0, x1 + 1):
                    upstream = grad_log_keep[b, v, u]
                    if upstream == 0.0:
                        continue
                    d, edge, t, qx, qy = _signed_distance(u, v, ax, ay, bx, by, cx, cy, area2)
                    if d >= radius:
                        continue
                    dist = abs(d)
                    if dist <= 0.0:
                        continue
                    # d(log_keep)/d(d) = sigmoid(−d/σ)/σ; d|d|/dq = (q − p)/|d|; sign for inside.
                    x = -d * inv_sigma
                    if x >= 0.0:
                        sig = 1.0 / (1.0 + math.exp(-x))
                    else:
                        e = math.exp(x)
                        sig = e / (1.0 + e)
                    scale = upstream * sig * inv_sigma / dist
                    if d < 0.0:
                        scale = -scale
                    nx = scale * (qx - u)
                    ny = scale * (qy - v)
                    s0 = 1.0 - t
                    if edge == 0:
                        gx0 += s0 * nx
                        gy0 += s0 * ny
                        gx1 += t * nx
                        gy1 += t * ny
                    elif edge == 1:
                        gx1 += s0 * nx
                        gy1 += s0 * ny
                        gx2 += t * nx
                        gy2 += t * ny
                    else:
                        gx2 += s0 * nx
                        gy2 += s0 * ny
                        gx0 += t * nx
                        gy0 += t * ny
            grad_triangles[b, f, 0, 0] = gx0
            grad_triangles[b, f, 0, 1] = gy0
            grad_triangles[b, f, 1, 0] = gx1
            grad_triangles[b, f, 1, 1] = gy1
            grad_triangles[b, f, 2, 0] = gx2
            grad_triangles[b, f, 2, 1] = gy2


@njit(parallel=True, cache=True)
def coverage(triangles, boxes, height, width, out):
    """out[b, v, u] = True where the pixel centre lies in (or on) some face (d ≤ 0)."""
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    n_threads = numba.get_num_threads()
    n_bands = min(height, n_threads * 8)
    for thread in prange(n_threads):
        for job in range(thread, batch * n_bands, n_threads):
            b = job // n_bands
            band = job % n_bands
            row_lo = band * height // n_bands
            row_hi = (band + 1) * height // n_bands - 1
            for f in range(n_faces):
                y0 = max(boxes[b, f, 2], row_lo)
                y1 = min(boxes[b, f, 3], row_hi)
                x0 = boxes[b, f, 0]
                x1 = boxes[b, f, 1]
                if y0 > y1 or x0 > x1:
                    continue
                ax, ay = triangles[b, f, 0, 0], triangles[b, f, 0, 1]
                bx, by = triangles[b, f, 1, 0], triangles[b, f, 1, 1]
                cx, cy = triangles[b, f, 2, 0], triangles[b, f, 2, 1]
                area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                if area2 == 0.0:
                    continue
                for v in range(y0, y1 + 1):
                    for u in range(x0, x1 + 1):
                        if out[b, v, u]:
                            continue
                        w0 = (bx - ax) * (v - ay) - (by - ay) * (u - ax)
                        w1 = (cx - bx) * (v - by) - (cy - by) * (u - bx)
                        w2 = (ax - cx) * (v - cy) - (ay - cy) * (u - cx)
                        if area2 > 0.0:
                            out[b, v, u] = w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0
                        else:
                            out[b, v, u] = w0 <= 0.0 and w1 <= 0.0 and w2 <= 0.0
