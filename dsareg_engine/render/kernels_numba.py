"""Fused CPU kernels (numba) for soft and hard silhouettes, with an analytic backward.

Same mathematics as :mod:`.rasterize_torch` + :mod:`.shade` — the tests hold them equal —
but one pass per face over its pixel box, no per-pair tensors. ``n_threads`` is passed in
(``numba.get_num_threads()``) so the compiled kernels can be cached on disk. Work is split over
threads by interleaved image row bands (forward: each band owns its output rows, so
no write conflicts) and interleaved faces (backward: each face owns its gradient).

The per-pixel work is written branch-free (all three point–segment distances, the inside
test as a select) so LLVM turns the inner loops into SIMD code; profiling showed the
earlier branchy early-outs cost more in mispredictions than they saved. Both passes
visit, per face and row, only the columns whose centres can be within the blur radius
(:func:`_near_columns`); the backward packs those pixels into flat chunks, so its loop
vectorizes even when rows are only a few pixels long.
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


TABLE_STEP = 1.0 / 128.0
TABLE_MAX = 24.0
_TABLE_TOP = TABLE_MAX / TABLE_STEP


def make_tables() -> tuple[np.ndarray, np.ndarray]:
    """Tables of log1p(exp(−a)) and sigmoid(−a) for a ∈ [0, TABLE_MAX] in steps of TABLE_STEP.

    Linear interpolation in them is accurate to ~2e-6, well below float32 image noise,
    and replaces two transcendental calls per face–pixel pair. Arguments past the end
    are clamped to it, where both functions are below 4e-11.
    """
    a = np.arange(0.0, TABLE_MAX + 2 * TABLE_STEP, TABLE_STEP)
    return np.log1p(np.exp(-a)), 1.0 / (1.0 + np.exp(a))


@njit(inline="always")
def _lookup(table, a):
    """Linear interpolation of a table sampled at a = k·TABLE_STEP (a ≥ 0, clamped at the end)."""
    position = min(a * (1.0 / TABLE_STEP), _TABLE_TOP)
    k = int(position)
    w = position - k
    return table[k] + w * (table[k + 1] - table[k])


@njit(inline="always")
def _log_keep(d, inv_sigma, exact, softplus_table):
    """log(1 − sigmoid(−d/σ)) = −softplus(−d/σ) = −(max(x, 0) + log1p(exp(−|x|))), x = −d/σ."""
    x = -d * inv_sigma
    a = abs(x)
    tail = math.log1p(math.exp(-a)) if exact else _lookup(softplus_table, a)
    return -(max(x, 0.0) + tail)


@njit(inline="always")
def _sigmoid(x, exact, sigmoid_table):
    """sigmoid(x)."""
    a = abs(x)
    low = math.exp(-a) / (1.0 + math.exp(-a)) if exact else _lookup(sigmoid_table, a)
    return 1.0 - low if x >= 0.0 else low


@njit(inline="always")
def _edge_terms(px, py, sx, sy, ex, ey, inv_len2, winding):
    """Point p against edge s → s + e: (t, p − q, |p − q|², h).

    q = s + t·e is the nearest point of the segment (t clamped to [0, 1]); h is the
    signed distance to the edge's line times |e|, positive on the inner side.
    """
    wx = px - sx
    wy = py - sy
    t = min(max((wx * ex + wy * ey) * inv_len2, 0.0), 1.0)
    dx = wx - t * ex
    dy = wy - t * ey
    return t, dx, dy, dx * dx + dy * dy, winding * (ex * wy - ey * wx)


@njit(inline="always")
def _pixel_distance(s, px, py):
    """Signed distance (px, negative inside) from p to face ``s`` and its nearest-edge data.

    Returns (d, nearest edge as three 0/1 flags, t0..t2, (p − q) per edge). Inside a
    proper triangle the nearest boundary point is the foot on the nearest edge, so
    ``|d|`` is the smallest point–segment distance either way; degenerate faces
    (winding 0) have no inside.
    """
    (ax, ay, bx, by, cx, cy, e0x, e0y, e1x, e1y, e2x, e2y, il0, il1, il2, i0, i1, i2, winding) = s
    t0, dx0, dy0, q0, h0 = _edge_terms(px, py, ax, ay, e0x, e0y, il0, winding)
    t1, dx1, dy1, q1, h1 = _edge_terms(px, py, bx, by, e1x, e1y, il1, winding)
    t2, dx2, dy2, q2, h2 = _edge_terms(px, py, cx, cy, e2x, e2y, il2, winding)
    near0 = (q0 <= q1) & (q0 <= q2)
    near1 = (~near0) & (q1 <= q2)
    near2 = (~near0) & (~near1)
    distance = math.sqrt(q0 if near0 else (q1 if near1 else q2))
    inside = (h0 >= 0.0) & (h1 >= 0.0) & (h2 >= 0.0) & (winding != 0.0)
    d = -distance if inside else distance
    return d, near0, near1, near2, t0, t1, t2, dx0, dy0, dx1, dy1, dx2, dy2


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
def _near_columns(s, v, radius, x0, x1):
    """Columns of row v whose centres may lie within ``radius`` of face ``s``: (first, last).

    The intersection of two cheap supersets of the face's radius neighbourhood: the
    face's edge lines pushed out by ``radius`` (proper faces only), and its bounding box
    with rounded corners. Empty if first > last.
    """
    lo, hi = x0, x1
    if s[18] != 0.0:
        a0, b0, a1, b1, a2, b2 = _row_lines(s, v)
        lo, hi = _span(a0, b0, a1, b1, a2, b2, -radius, x0, x1)
    ax, ay, bx, by, cx, cy = s[0], s[1], s[2], s[3], s[4], s[5]
    dy = max(min(ay, min(by, cy)) - v, v - max(ay, max(by, cy)), 0.0)
    if dy >= radius:
        return x0, x0 - 1
    half = math.sqrt(radius * radius - dy * dy)
    first = max(min(ax, min(bx, cx)) - half, x0 - 1.0)
    last = min(max(ax, max(bx, cx)) + half, x1 + 1.0)
    return max(lo, int(math.ceil(first))), min(hi, int(math.floor(last)))


@njit(inline="always")
def _band(job, n_bands, height):
    return job // n_bands, (job % n_bands) * height // n_bands, ((job % n_bands) + 1) * height // n_bands - 1


@njit(parallel=True, cache=True)
def gather_faces(pixels, vertex_ok, faces, width, height, radius, triangles, boxes):
    """Face corners and their pixel boxes, in one pass.

    Args:
        pixels: ``(B, V, 2)`` projected vertices ``(u, v)`` px.
        vertex_ok: ``(B, V)`` bool, False for vertices too near/behind the source.
        faces: ``(F, 3)`` int64.
        radius: blur radius px.
        triangles: out ``(B, F, 3, 2)``, same dtype as ``pixels``.
        boxes: out ``(B, F, 4)`` int32 ``[x0, x1, y0, y1]``: the inclusive pixel ranges whose
            centres lie within ``radius`` of the face's bounding box, clamped to the image;
            ``[1, 0, 1, 0]`` (empty) for faces with a bad vertex or entirely off the image.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    for job in prange(batch * n_faces):
        gather_face(pixels, vertex_ok, faces, width, height, radius, triangles, boxes, job // n_faces, job % n_faces)


@njit(inline="always")
def gather_face(pixels, vertex_ok, faces, width, height, radius, triangles, boxes, b, f):
    """Corners and pixel box of face f under pose b (one job of :func:`gather_faces`)."""
    ok = True
    u_min = v_min = np.inf
    u_max = v_max = -np.inf
    for c in range(3):
        vertex = faces[f, c]
        u = pixels[b, vertex, 0]
        v = pixels[b, vertex, 1]
        triangles[b, f, c, 0] = u
        triangles[b, f, c, 1] = v
        ok = ok and vertex_ok[b, vertex] and np.isfinite(u) and np.isfinite(v)
        u_min = min(u_min, u)
        u_max = max(u_max, u)
        v_min = min(v_min, v)
        v_max = max(v_max, v)
    # Clamp in float first so huge coordinates cannot overflow the integer cast.
    x0 = max(min(math.ceil(u_min - radius), width), 0.0)
    x1 = min(max(math.floor(u_max + radius), -1.0), width - 1.0)
    y0 = max(min(math.ceil(v_min - radius), height), 0.0)
    y1 = min(max(math.floor(v_max + radius), -1.0), height - 1.0)
    if not ok or x0 > x1 or y0 > y1:
        boxes[b, f, 0], boxes[b, f, 1], boxes[b, f, 2], boxes[b, f, 3] = 1, 0, 1, 0
    else:
        boxes[b, f, 0], boxes[b, f, 1], boxes[b, f, 2], boxes[b, f, 3] = int(x0), int(x1), int(y0), int(y1)


@njit(parallel=True, cache=True)
def scatter_to_vertices(grad_triangles, faces, grad_pixels):
    """grad_pixels ``(B, V, 2)`` += gradient of each face corner ``(B, F, 3, 2)``."""
    for b in prange(grad_triangles.shape[0]):
        for f in range(faces.shape[0]):
            for c in range(3):
                vertex = faces[f, c]
                grad_pixels[b, vertex, 0] += grad_triangles[b, f, c, 0]
                grad_pixels[b, vertex, 1] += grad_triangles[b, f, c, 1]


@njit(parallel=True, cache=True, fastmath=True)
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
        distance = np.empty(width, dtype=np.float64)
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
                    fv = float(v)
                    lo, hi = _near_columns(s, fv, radius, x0, x1)
                    # Two loops: the distances vectorize; the table lookups do not.
                    for j in range(hi - lo + 1):
                        distance[j] = _pixel_distance(s, float(lo + j), fv)[0]
                    row = out[b, v]
                    for j in range(hi - lo + 1):
                        d = distance[j]
                        if d < radius:
                            row[lo + j] += _log_keep(d, inv_sigma, exact, softplus_table) - floor


FLAT_CHUNK = 512


@njit(inline="always")
def _chunk_gradient(s, pixel_u, pixel_v, upstream, n, radius, inv_sigma, exact, sigmoid_table):
    """Σ over n pixels of d(loss)/d(corners) for face ``s``: (ax, ay, bx, by, cx, cy)."""
    gax = gay = gbx = gby = gcx = gcy = 0.0
    for j in range(n):
        d, near0, near1, near2, t0, t1, t2, dx0, dy0, dx1, dy1, dx2, dy2 = _pixel_distance(s, pixel_u[j], pixel_v[j])
        # d(log_keep)/dd = sigmoid(−d/σ)/σ ; dd/dq = (q − p)/d for either sign of d.
        used = (d < radius) & (d != 0.0)
        safe_d = d if used else 1.0
        scale = upstream[j] * _sigmoid(-d * inv_sigma, exact, sigmoid_table) * inv_sigma / safe_d if used else 0.0
        gx0 = -scale * dx0 if near0 else 0.0
        gy0 = -scale * dy0 if near0 else 0.0
        gx1 = -scale * dx1 if near1 else 0.0
        gy1 = -scale * dy1 if near1 else 0.0
        gx2 = -scale * dx2 if near2 else 0.0
        gy2 = -scale * dy2 if near2 else 0.0
        gax += (1.0 - t0) * gx0 + t2 * gx2
        gay += (1.0 - t0) * gy0 + t2 * gy2
        gbx += t0 * gx0 + (1.0 - t1) * gx1
        gby += t0 * gy0 + (1.0 - t1) * gy1
        gcx += t1 * gx1 + (1.0 - t2) * gx2
        gcy += t1 * gy1 + (1.0 - t2) * gy2
    return gax, gay, gbx, gby, gcx, gcy


@njit(inline="always")
def _add6(a, b):
    return a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5]


@njit(parallel=True, cache=True, fastmath=True)
def soft_log_keep_backward(triangles, boxes, sigma, radius, exact, sigmoid_table, n_threads, grad_log_keep, grad_triangles):
    """grad_triangles (B, F, 3, 2) = d(loss)/d(corners) given d(loss)/d(log_keep) (B, H, W).

    The gradient of a pair flows to the two corners of the face's nearest edge, split
    (1 − t, t) by where the nearest boundary point q lies on it (q minimizes the
    distance, so t's own derivative does not enter). The face's near pixels are packed
    into flat chunks so the per-pixel loop vectorizes however short the rows are.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    inv_sigma = 1.0 / sigma
    for thread in prange(n_threads):
        pixel_u = np.empty(FLAT_CHUNK, dtype=np.float64)
        pixel_v = np.empty(FLAT_CHUNK, dtype=np.float64)
        upstream = np.empty(FLAT_CHUNK, dtype=np.float64)
        for job in range(thread, batch * n_faces, n_threads):
            b = job // n_faces
            f = job % n_faces
            x0, x1, y0, y1 = boxes[b, f, 0], boxes[b, f, 1], boxes[b, f, 2], boxes[b, f, 3]
            if x0 > x1 or y0 > y1:
                continue
            s = _face_setup(triangles[b, f, :, 0], triangles[b, f, :, 1])
            total = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            n = 0
            for v in range(y0, y1 + 2):
                lo, hi = _near_columns(s, float(v), radius, x0, x1) if v <= y1 else (0, -1)
                u = lo
                while u <= hi:
                    take = min(hi - u + 1, FLAT_CHUNK - n)
                    for k in range(take):
                        pixel_u[n + k] = u + k
                        pixel_v[n + k] = v
                        upstream[n + k] = grad_log_keep[b, v, u + k]
                    n += take
                    u += take
                    if n == FLAT_CHUNK:
                        total = _add6(total, _chunk_gradient(s, pixel_u, pixel_v, upstream, n, radius, inv_sigma, exact, sigmoid_table))
                        n = 0
                if v > y1 and n > 0:  # the extra, empty row flushes the last partial chunk
                    total = _add6(total, _chunk_gradient(s, pixel_u, pixel_v, upstream, n, radius, inv_sigma, exact, sigmoid_table))
            gax, gay, gbx, gby, gcx, gcy = total
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
