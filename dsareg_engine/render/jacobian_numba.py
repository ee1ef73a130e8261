"""Fused CPU kernel (numba): the soft silhouette's log-keep image with its per-pixel derivatives.

Forward-mode counterpart of :func:`.kernels_numba.soft_log_keep_backward`: given how every
projected vertex moves with K parameters (a rigid pose has six), one pass over the faces' near
pixels returns ``log_keep`` and ``∂ log_keep / ∂θ_k`` per pixel — the Jacobian a Gauss–Newton
step needs, which the reverse-mode kernel could only give one pixel at a time. Same per-pair
mathematics as the backward kernel (gradient of a face–pixel pair flows to the two corners of
the face's nearest edge, split (1 − t, t)), so the two agree to rounding; work is split over
threads by interleaved row bands, as in the forward kernel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

PARAMETERS = 6
"""K: the kernels are written for the six parameters of a rigid pose increment."""

from .kernels_numba import BANDS_PER_THREAD, _band, _face_setup, _near_columns, _pixel_distance, _sigmoid, gather_face


@njit(inline="always")
def _unit_corner_gradient(d, near0, near1, near2, t0, t1, t2, dx0, dy0, dx1, dy1, dx2, dy2):
    """∂d/∂(corners) of one face–pixel pair: (ax, ay, bx, by, cx, cy); zeros at d = 0.

    ∂d/∂q = (q − p)/d for either sign of d, split (1 − t, t) over the nearest edge's corners.
    """
    inv_d = 1.0 / d if d != 0.0 else 0.0
    gx0 = -inv_d * dx0 if near0 else 0.0
    gy0 = -inv_d * dy0 if near0 else 0.0
    gx1 = -inv_d * dx1 if near1 else 0.0
    gy1 = -inv_d * dy1 if near1 else 0.0
    gx2 = -inv_d * dx2 if near2 else 0.0
    gy2 = -inv_d * dy2 if near2 else 0.0
    return ((1.0 - t0) * gx0 + t2 * gx2, (1.0 - t0) * gy0 + t2 * gy2,
            t0 * gx0 + (1.0 - t1) * gx1, t0 * gy0 + (1.0 - t1) * gy1,
            t1 * gx1 + (1.0 - t2) * gx2, t1 * gy1 + (1.0 - t2) * gy2)


CHUNK = 256


@njit(inline="always")
def _chunk_slopes(s, tangents, pixel_u, pixel_v, n, radius, inv_sigma, exact, sigmoid_table, gradient, slopes):
    """slopes[k, j] = ∂log_keep_f/∂θ_k at the n packed pixels (pixel_u[j], pixel_v[j]) of face ``s``.

    Two vectorizable loops (distances and ∂d/∂corners; their product with the corners' tangents)
    around the one that is not (the sigmoid table lookup).
    """
    for j in range(n):
        d, n0, n1, n2, t0, t1, t2, dx0, dy0, dx1, dy1, dx2, dy2 = _pixel_distance(s, pixel_u[j], pixel_v[j])
        g = _unit_corner_gradient(d, n0, n1, n2, t0, t1, t2, dx0, dy0, dx1, dy1, dx2, dy2)
        gradient[0, j], gradient[1, j], gradient[2, j] = g[0], g[1], g[2]
        gradient[3, j], gradient[4, j], gradient[5, j] = g[3], g[4], g[5]
        gradient[6, j] = d
    for j in range(n):
        d = gradient[6, j]
        # ∂log_keep/∂d = sigmoid(−d/σ)/σ; 0 beyond the radius
        gradient[6, j] = _sigmoid(-d * inv_sigma, exact, sigmoid_table) * inv_sigma if d < radius else 0.0
    for k in range(PARAMETERS):
        t_ax, t_ay, t_bx, t_by, t_cx, t_cy = (tangents[0, k], tangents[1, k], tangents[2, k], tangents[3, k],
                                              tangents[4, k], tangents[5, k])
        for j in range(n):
            slopes[k, j] = gradient[6, j] * (gradient[0, j] * t_ax + gradient[1, j] * t_ay + gradient[2, j] * t_bx
                                             + gradient[3, j] * t_by + gradient[4, j] * t_cx + gradient[5, j] * t_cy)


@njit(parallel=True, cache=True, fastmath=True)
def soft_log_keep_tangents(triangles, corner_tangents, boxes, sigma, radius, exact, sigmoid_table, log_keep, min_log_keep,
                           n_threads, out_tangents):
    """out_tangents (B, H, W, 6) = ∂log_keep/∂θ_k where ``log_keep`` (B, H, W) (from the forward kernel) ≥ ``min_log_keep``.

    Elsewhere the pixel is covered so deeply (``alpha = 1 − exp(log_keep)`` within exp(min_log_keep)
    of 1) that ``∂alpha/∂θ = −exp(log_keep) · ∂log_keep/∂θ`` vanishes: those pixels — most of the
    faces inside the silhouette — are skipped. Threads own interleaved row bands (no write
    conflicts); each face's remaining pixels are packed into flat chunks so the arithmetic vectorizes.

    Args:
        triangles: ``(B, F, 3, 2)`` face corners (px).
        corner_tangents: ``(B, F, 6, 6)``: ∂(ax, ay, bx, by, cx, cy)/∂θ_k per face.
        boxes: ``(B, F, 4)`` int32 pixel boxes from :func:`.kernels_numba.gather_faces`.
        out_tangents: zeroed output.
    """
    batch, n_faces = triangles.shape[0], triangles.shape[1]
    height = log_keep.shape[1]
    n_bands = min(height, n_threads * BANDS_PER_THREAD)
    inv_sigma = 1.0 / sigma
    for thread in prange(n_threads):
        pixel_u = np.empty(CHUNK, dtype=np.float64)
        pixel_v = np.empty(CHUNK, dtype=np.float64)
        gradient = np.empty((7, CHUNK), dtype=np.float64)
        slopes = np.empty((PARAMETERS, CHUNK), dtype=np.float64)
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
                tangents = corner_tangents[b, f]
                n = 0
                for v in range(y0, y1 + 1):
                    lo, hi = _near_columns(s, float(v), radius, x0, x1)
                    row = log_keep[b, v]
                    for u in range(lo, hi + 1):
                        if row[u] >= min_log_keep:
                            pixel_u[n] = u
                            pixel_v[n] = v
                            n += 1
                            if n == CHUNK:
                                _add_chunk(s, tangents, pixel_u, pixel_v, n, radius, inv_sigma, exact, sigmoid_table,
                                           gradient, slopes, out_tangents[b])
                                n = 0
                if n > 0:
                    _add_chunk(s, tangents, pixel_u, pixel_v, n, radius, inv_sigma, exact, sigmoid_table, gradient, slopes,
                               out_tangents[b])


@njit(inline="always")
def _add_chunk(s, tangents, pixel_u, pixel_v, n, radius, inv_sigma, exact, sigmoid_table, gradient, slopes, out_tangents):
    """out_tangents[v, u, :] += the face's slopes at the n packed pixels."""
    _chunk_slopes(s, tangents, pixel_u, pixel_v, n, radius, inv_sigma, exact, sigmoid_table, gradient, slopes)
    for j in range(n):
        pixel = out_tangents[int(pixel_v[j]), int(pixel_u[j])]
        for k in range(PARAMETERS):
            pixel[k] += slopes[k, j]


@njit(cache=True)
def gather_faces_with_tangents(pixels, vertex_ok, vertex_tangents, faces, width, height, radius, triangles, boxes,
                               corner_tangents):
    """:func:`.kernels_numba.gather_faces` plus corner_tangents ``(B, F, 6, 6)`` from vertex_tangents ``(B, V, 2, 6)``.

    Serial: the work is a few microseconds per thousand faces, less than waking a second thread
    (which, on a loaded machine, cost up to 2–3 ms per call in the parallel version).
    """
    for b in range(corner_tangents.shape[0]):
        for f in range(faces.shape[0]):
            gather_face(pixels, vertex_ok, faces, width, height, radius, triangles, boxes, b, f)
            for c in range(3):
                vertex = faces[f, c]
                for k in range(PARAMETERS):
                    corner_tangents[b, f, 2 * c, k] = vertex_tangents[b, vertex, 0, k]
                    corner_tangents[b, f, 2 * c + 1, k] = vertex_tangents[b, vertex, 1, k]


@njit(parallel=True, cache=True)
def normal_equations(log_keep, log_keep_tangents, target, weight, n_threads, hessian, gradient):
    """Gauss–Newton sums of one image, added into ``hessian`` (K, K) and ``gradient`` (K,) (float64).

    With ``alpha = 1 − exp(log_keep)``, ``r = alpha − target`` and ``J = ∂alpha/∂θ = −exp(log_keep) ·
    ∂log_keep/∂θ``: hessian += Σ_p w_p J_p J_pᵀ, gradient += Σ_p w_p J_p r_p; returns Σ_p w_p r_p².
    ``log_keep`` (H, W), ``log_keep_tangents`` (H, W, K), ``target`` (H, W); ``weight`` (H, W), or
    (0, 0) for none.
    """
    height, width, n_params = log_keep_tangents.shape
    weighted = weight.shape[0] > 0
    partial_h = np.zeros((n_threads, n_params, n_params))
    partial_g = np.zeros((n_threads, n_params))
    partial_loss = np.zeros(n_threads)
    for thread in prange(n_threads):
        jac = np.empty(n_params)
        h = np.zeros((n_params, n_params))  # per-thread sums, written back once (no false sharing)
        g = np.zeros(n_params)
        loss = 0.0
        for v in range(thread, height, n_threads):
            for u in range(width):
                w = weight[v, u] if weighted else 1.0
                if log_keep[v, u] == 0.0:  # no face near: alpha = 0, no Jacobian
                    loss += w * target[v, u] * target[v, u]
                    continue
                keep = math.exp(log_keep[v, u])
                r = (1.0 - keep) - target[v, u]
                loss += w * r * r
                for k in range(n_params):
                    jac[k] = -keep * log_keep_tangents[v, u, k]
                for k in range(n_params):
                    g[k] += w * jac[k] * r
                    for m in range(k + 1):
                        h[k, m] += w * jac[k] * jac[m]
        partial_h[thread] = h
        partial_g[thread] = g
        partial_loss[thread] = loss
    for thread in range(n_threads):
        for k in range(n_params):
            gradient[k] += partial_g[thread, k]
            for m in range(k + 1):
                hessian[k, m] += partial_h[thread, k, m]
                if m != k:
                    hessian[m, k] += partial_h[thread, k, m]
    return partial_loss.sum()
