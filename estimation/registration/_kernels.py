"""Numba kernels for the per-correspondence 3x3 algebra of GICP (hot path, no Python loop).

Stacks of 3x3 products through numpy cost ~1 ms per 10k matrices each; these loops do the
whole whitening / residual / Jacobian in one pass. Compiled on first use and cached on disk.
"""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (closed form).

    Eigenvalues by the trigonometric method (Smith 1961); the eigenvector is the largest
    cross product of two rows of A - lambda I. Avoids one LAPACK call per point.
    """
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-30 * (q * q + 1e-300):
        return 0.0, 0.0, 1.0  # isotropic: any direction
    p = np.sqrt(p2 / 6.0)
    c00, c11, c22 = b00 / p, b11 / p, b22 / p
    c01, c02, c12 = a01 / p, a02 / p, a12 / p
    r = 0.5 * (c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02)
               + c02 * (c01 * c12 - c11 * c02))
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best = -1.0
    vx, vy, vz = 0.0, 0.0, 1.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        cx = u[1] * v[2] - u[2] * v[1]
        cy = u[2] * v[0] - u[0] * v[2]
        cz = u[0] * v[1] - u[1] * v[0]
        n2 = cx * cx + cy * cy + cz * cz
        if n2 > best:
            best = n2
            vx, vy, vz = cx, cy, cz
    if best <= 0.0:
        return 0.0, 0.0, 1.0
    nrm = np.sqrt(best)
    return vx / nrm, vy / nrm, vz / nrm


@numba.njit(cache=True, inline="always")
def _write_plane(out: np.ndarray, s: float, nx: float, ny: float, nz: float) -> None:
    """Fill the 3x3 ``out`` with I - s n n^T (n = (nx, ny, nz) the unit surface normal)."""
    out[0, 0] = 1.0 - s * nx * nx
    out[0, 1] = -s * nx * ny
    out[0, 2] = -s * nx * nz
    out[1, 0] = -s * ny * nx
    out[1, 1] = 1.0 - s * ny * ny
    out[1, 2] = -s * ny * nz
    out[2, 0] = -s * nz * nx
    out[2, 1] = -s * nz * ny
    out[2, 2] = 1.0 - s * nz * nz


@numba.njit(cache=True)
def regularise_covariances(cov: np.ndarray, epsilon: float) -> np.ndarray:
    """Replace the eigenvalues of each (N, 3, 3) covariance by (epsilon, 1, 1).

    With orthonormal eigenvectors that is I - (1 - epsilon) n n^T, n the surface normal.
    """
    n = cov.shape[0]
    out = np.empty_like(cov)
    s = 1.0 - epsilon
    for m in range(n):
        nx, ny, nz = smallest_eigenvector(cov[m, 0, 0], cov[m, 0, 1], cov[m, 0, 2],
                                          cov[m, 1, 1], cov[m, 1, 2], cov[m, 2, 2])
        _write_plane(out[m], s, nx, ny, nz)
    return out


@numba.njit(cache=True)
def neighbour_covariances(points: np.ndarray, idx: np.ndarray, epsilon: float,
                          thickness: np.ndarray) -> np.ndarray:
    """Plane-regularised covariances from each row of (M, k) neighbour indices into ``points``.

    One pass per point (mean, scatter, smallest eigenvector, ``I - (1 - epsilon) n n^T``)
    instead of numpy stacks of (M, k, 3) temporaries (measured 3-5x cheaper at k = 20).
    Also writes each neighbourhood's thickness into ``thickness`` (M,): its standard
    deviation along the normal n, ``sqrt(n^T S n)``, S the scatter (the map term's scale).
    """
    m_rows = idx.shape[0]
    k = idx.shape[1]
    out = np.empty((m_rows, 3, 3))
    s = 1.0 - epsilon
    for m in range(m_rows):
        mx, my, mz = 0.0, 0.0, 0.0
        for j in range(k):
            q = idx[m, j]
            mx += points[q, 0]
            my += points[q, 1]
            mz += points[q, 2]
        mx /= k
        my /= k
        mz /= k
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        for j in range(k):
            q = idx[m, j]
            dx = points[q, 0] - mx
            dy = points[q, 1] - my
            dz = points[q, 2] - mz
            a00 += dx * dx
            a01 += dx * dy
            a02 += dx * dz
            a11 += dy * dy
            a12 += dy * dz
            a22 += dz * dz
        nx, ny, nz = smallest_eigenvector(a00 / k, a01 / k, a02 / k, a11 / k, a12 / k, a22 / k)
        _write_plane(out[m], s, nx, ny, nz)
        along = (nx * nx * a00 + ny * ny * a11 + nz * nz * a22
                 + 2.0 * (nx * ny * a01 + nx * nz * a02 + ny * nz * a12)) / k
        thickness[m] = np.sqrt(max(along, 0.0))
    return out


@numba.njit(cache=True)
def _whiten_into(out: np.ndarray, cov_target: np.ndarray, cov_source: np.ndarray,
                 R: np.ndarray, C: np.ndarray, RS: np.ndarray) -> None:
    """Write U^T of one pair into the (3, 3) ``out`` (see :func:`whitening`)."""
    for i in range(3):
        for j in range(3):
            RS[i, j] = R[i, 0] * cov_source[0, j] + R[i, 1] * cov_source[1, j] \
                + R[i, 2] * cov_source[2, j]
    for i in range(3):
        for j in range(3):
            C[i, j] = cov_target[i, j] + RS[i, 0] * R[j, 0] + RS[i, 1] * R[j, 1] \
                + RS[i, 2] * R[j, 2]
    # symmetric 3x3 inverse by cofactors
    a, b, c = C[0, 0], 0.5 * (C[0, 1] + C[1, 0]), 0.5 * (C[0, 2] + C[2, 0])
    d, e, f = C[1, 1], 0.5 * (C[1, 2] + C[2, 1]), C[2, 2]
    A00 = d * f - e * e
    A01 = c * e - b * f
    A02 = b * e - c * d
    det = a * A00 + b * A01 + c * A02
    A11 = a * f - c * c
    A12 = b * c - a * e
    A22 = a * d - b * b
    i00, i01, i02 = A00 / det, A01 / det, A02 / det
    i11, i12, i22 = A11 / det, A12 / det, A22 / det
    # Cholesky L of the information matrix; U^T = L^T
    l00 = np.sqrt(i00)
    l10 = i01 / l00
    l20 = i02 / l00
    l11 = np.sqrt(i11 - l10 * l10)
    l21 = (i12 - l20 * l10) / l11
    l22 = np.sqrt(i22 - l20 * l20 - l21 * l21)
    out[0, 0] = l00
    out[0, 1] = l10
    out[0, 2] = l20
    out[1, 1] = l11
    out[1, 2] = l21
    out[2, 2] = l22


@numba.njit(cache=True)
def whitening(cov_target: np.ndarray, cov_source: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Return (M, 3, 3) U^T with U U^T = (Sigma_t + R Sigma_s R^T)^-1 (U lower Cholesky)."""
    n = cov_target.shape[0]
    out = np.zeros((n, 3, 3))
    C = np.empty((3, 3))
    RS = np.empty((3, 3))
    for m in range(n):
        _whiten_into(out[m], cov_target[m], cov_source[m], R, C, RS)
    return out


@numba.njit(cache=True)
def whitening_rows_into(out: np.ndarray, cov_target: np.ndarray, target_rows: np.ndarray,
                        cov_source: np.ndarray, source_rows: np.ndarray, R: np.ndarray) -> None:
    """:func:`whitening_rows` written into the zeroed (M, 3, 3) ``out`` (a part of a larger
    array: two threads fill one array)."""
    C = np.empty((3, 3))
    RS = np.empty((3, 3))
    for m in range(target_rows.shape[0]):
        _whiten_into(out[m], cov_target[target_rows[m]], cov_source[source_rows[m]], R, C, RS)


@numba.njit(cache=True)
def whitening_rows(cov_target: np.ndarray, target_rows: np.ndarray, cov_source: np.ndarray,
                   source_rows: np.ndarray, R: np.ndarray) -> np.ndarray:
    """:func:`whitening` of the pairs (cov_target[target_rows[m]], cov_source[source_rows[m]])
    without gathering them first."""
    out = np.zeros((target_rows.shape[0], 3, 3))
    whitening_rows_into(out, cov_target, target_rows, cov_source, source_rows, R)
    return out


@numba.njit(cache=True)
def _whitened_residual(T: np.ndarray, xs: np.ndarray, xt: np.ndarray, Um: np.ndarray,
                       v: np.ndarray) -> float:
    """Write ``U^T r`` (``r = x_t - R x_s - t``) of one pair into ``v`` (3,); return its
    squared norm, the Mahalanobis e."""
    x0, x1, x2 = xs[0], xs[1], xs[2]
    r0 = xt[0] - (T[0, 0] * x0 + T[0, 1] * x1 + T[0, 2] * x2 + T[0, 3])
    r1 = xt[1] - (T[1, 0] * x0 + T[1, 1] * x1 + T[1, 2] * x2 + T[1, 3])
    r2 = xt[2] - (T[2, 0] * x0 + T[2, 1] * x1 + T[2, 2] * x2 + T[2, 3])
    ee = 0.0
    for i in range(3):
        v[i] = Um[i, 0] * r0 + Um[i, 1] * r1 + Um[i, 2] * r2
        ee += v[i] * v[i]
    return ee


@numba.njit(cache=True)
def gicp_terms(T: np.ndarray, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
               sqrt_w: np.ndarray, want_jacobians: bool):
    """Return (whitened residuals (M,3), Jacobians (M,3,6), Mahalanobis e (M,)).

    r = x_t - R x_s - t; dr/dxi for T Exp(xi) = [R [x_s]_x, -R]; both premultiplied by U^T
    and scaled by sqrt_w.
    """
    n = source.shape[0]
    rw = np.empty((n, 3))
    e = np.empty(n)
    J = np.empty((n if want_jacobians else 0, 3, 6))
    UR = np.empty((3, 3))
    v = np.empty(3)
    for m in range(n):
        x0, x1, x2 = source[m, 0], source[m, 1], source[m, 2]
        e[m] = _whitened_residual(T, source[m], target[m], Ut[m], v)
        for i in range(3):
            rw[m, i] = v[i] * sqrt_w[m]
        if want_jacobians:
            for i in range(3):
                for j in range(3):
                    UR[i, j] = Ut[m, i, 0] * T[0, j] + Ut[m, i, 1] * T[1, j] \
                        + Ut[m, i, 2] * T[2, j]
            s = sqrt_w[m]
            for i in range(3):
                # UR @ [x]_x : columns (UR[:,1]*x2 - UR[:,2]*x1, UR[:,2]*x0 - UR[:,0]*x2, ...)
                J[m, i, 0] = s * (UR[i, 1] * x2 - UR[i, 2] * x1)
                J[m, i, 1] = s * (UR[i, 2] * x0 - UR[i, 0] * x2)
                J[m, i, 2] = s * (UR[i, 0] * x1 - UR[i, 1] * x0)
                J[m, i, 3] = -s * UR[i, 0]
                J[m, i, 4] = -s * UR[i, 1]
                J[m, i, 5] = -s * UR[i, 2]
    return rw, J, e


@numba.njit(cache=True)
def solution_sums(T: np.ndarray, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
                  J: np.ndarray, rw: np.ndarray, w: np.ndarray, c: np.ndarray,
                  cov_target: np.ndarray, target_rows: np.ndarray):
    """Return the solution's sums and per-pair terms in one pass (Registration.solution_terms):
    H = sum w J^T J, the curvature sum sum c g g^T (g = J^T rw), the scores w g (M, 6), the
    target normals (M, 3) (the column of I - C with the largest diagonal, normalised; C the
    target covariance ``I - (1 - eps) n n^T`` of the pair's row), the residuals along them
    n^T (x_t - R x_s - t) (M,) and the sensitivities w J^T (U^T n) (M, 6)."""
    m = J.shape[0]
    H = np.zeros((6, 6))
    curvature = np.zeros((6, 6))
    scores = np.empty((m, 6))
    normals = np.empty((m, 3))
    along = np.empty(m)
    sens = np.empty((m, 6))
    g = np.empty(6)
    n = np.empty(3)
    Un = np.empty(3)
    for k in range(m):
        wk, ck = w[k], c[k]
        for j in range(6):
            g[j] = J[k, 0, j] * rw[k, 0] + J[k, 1, j] * rw[k, 1] + J[k, 2, j] * rw[k, 2]
            scores[k, j] = wk * g[j]
        for i in range(6):
            for j in range(i, 6):
                h = wk * (J[k, 0, i] * J[k, 0, j] + J[k, 1, i] * J[k, 1, j]
                          + J[k, 2, i] * J[k, 2, j])
                H[i, j] += h
                curvature[i, j] += ck * g[i] * g[j]
        C = cov_target[target_rows[k]]
        col, best = 0, 1.0 - C[0, 0]
        for a in range(1, 3):
            if 1.0 - C[a, a] > best:
                col, best = a, 1.0 - C[a, a]
        for a in range(3):
            n[a] = (1.0 if a == col else 0.0) - C[a, col]
        norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        r = 0.0
        for a in range(3):
            n[a] /= norm
            normals[k, a] = n[a]
            r += n[a] * (target[k, a] - (T[a, 0] * source[k, 0] + T[a, 1] * source[k, 1]
                                          + T[a, 2] * source[k, 2] + T[a, 3]))
        along[k] = r
        for a in range(3):
            Un[a] = Ut[k, a, 0] * n[0] + Ut[k, a, 1] * n[1] + Ut[k, a, 2] * n[2]
        for j in range(6):
            sens[k, j] = wk * (J[k, 0, j] * Un[0] + J[k, 1, j] * Un[1] + J[k, 2, j] * Un[2])
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
            curvature[i, j] = curvature[j, i]
    return H, curvature, scores, normals, along, sens


@numba.njit(cache=True)
def shift_sensitivities(J: np.ndarray, Ut: np.ndarray, w: np.ndarray,
                        weight: np.ndarray) -> np.ndarray:
    """Return (M, 6, 3) (w_k J_k^T U_k^T) weight_k (SolutionTerms.shift_sensitivity)."""
    m = J.shape[0]
    out = np.empty((m, 6, 3))
    for k in range(m):
        for i in range(6):
            for j in range(3):
                out[k, i, j] = (w[k] * (J[k, 0, i] * Ut[k, 0, j] + J[k, 1, i] * Ut[k, 1, j]
                                        + J[k, 2, i] * Ut[k, 2, j])) * weight[k]
    return out


@numba.njit(cache=True)
def inplane_sums(J: np.ndarray, Ut: np.ndarray, w: np.ndarray, group: np.ndarray,
                 axis: np.ndarray, n_groups: int) -> np.ndarray:
    """Return (n_groups, 3, 6): per group p and lattice axis b, the sum over its pairs whose
    ``axis`` is not b of ``w_k J_k^T U_k^T e_b`` (``inplane_information``; the (M, 6, 3)
    shift sensitivities, gathered per axis and group, took 150 ms at 460k pairs)."""
    out = np.zeros((n_groups, 3, 6))
    for k in range(J.shape[0]):
        g = group[k]
        for b in range(3):
            if axis[k] == b:
                continue
            for i in range(6):
                out[g, b, i] += w[k] * (J[k, 0, i] * Ut[k, 0, b] + J[k, 1, i] * Ut[k, 1, b]
                                        + J[k, 2, i] * Ut[k, 2, b])
    return out


@numba.njit(cache=True)
def grouped_sums(keys: np.ndarray, lo: np.ndarray, span: np.ndarray,
                 values: np.ndarray) -> np.ndarray:
    """Return ``values`` (M, d) summed over the rows of equal (M, 3) int64 ``keys`` (each
    within ``lo`` + [0, ``span``)), one row per distinct key in the keys' lexicographic
    order (as ``np.unique``'s groups), each group's rows added in their order (as
    ``np.bincount``): a table over the keys' box, no sort."""
    m, d = values.shape
    table = np.full(span[0] * span[1] * span[2], -1, np.int64)
    packed = np.empty(m, np.int64)
    for k in range(m):
        p = ((keys[k, 0] - lo[0]) * span[1] + keys[k, 1] - lo[1]) * span[2] + keys[k, 2] - lo[2]
        packed[k] = p
        table[p] = 0
    groups = 0
    for i in range(table.shape[0]):
        if table[i] == 0:
            table[i] = groups
            groups += 1
    out = np.zeros((groups, d))
    for k in range(m):
        row = table[packed[k]]
        for j in range(d):
            out[row, j] += values[k, j]
    return out


@numba.njit(cache=True)
def gicp_mahalanobis(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                     target: np.ndarray, target_rows: np.ndarray, Ut: np.ndarray) -> np.ndarray:
    """Return (M,) e of :func:`gicp_terms` (the same operations) of the pairs
    (source[source_rows[m]], target[target_rows[m]])."""
    n = source_rows.shape[0]
    e = np.empty(n)
    v = np.empty(3)
    for m in range(n):
        e[m] = _whitened_residual(T, source[source_rows[m]], target[target_rows[m]], Ut[m], v)
    return e


@numba.njit(cache=True)
def gicp_normal_equations(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                          target: np.ndarray, target_rows: np.ndarray, Ut: np.ndarray,
                          w: np.ndarray):
    """Return (H (6,6), g (6,)) = (sum_k w_k J_k^T J_k, sum_k w_k J_k^T U_k^T r_k) of
    :func:`gicp_terms` (unscaled) of the pairs (source[source_rows[m]],
    target[target_rows[m]]), without forming the (M, 3, 6) Jacobians."""
    n = source_rows.shape[0]
    H = np.zeros((6, 6))
    g = np.zeros(6)
    UR = np.empty((3, 3))
    Jr = np.empty(6)
    for m in range(n):
        s, t = source_rows[m], target_rows[m]
        x0, x1, x2 = source[s, 0], source[s, 1], source[s, 2]
        r0 = target[t, 0] - (T[0, 0] * x0 + T[0, 1] * x1 + T[0, 2] * x2 + T[0, 3])
        r1 = target[t, 1] - (T[1, 0] * x0 + T[1, 1] * x1 + T[1, 2] * x2 + T[1, 3])
        r2 = target[t, 2] - (T[2, 0] * x0 + T[2, 1] * x1 + T[2, 2] * x2 + T[2, 3])
        wm = w[m]
        for i in range(3):
            v = Ut[m, i, 0] * r0 + Ut[m, i, 1] * r1 + Ut[m, i, 2] * r2
            for j in range(3):
                UR[i, j] = Ut[m, i, 0] * T[0, j] + Ut[m, i, 1] * T[1, j] \
                    + Ut[m, i, 2] * T[2, j]
            Jr[0] = UR[i, 1] * x2 - UR[i, 2] * x1
            Jr[1] = UR[i, 2] * x0 - UR[i, 0] * x2
            Jr[2] = UR[i, 0] * x1 - UR[i, 1] * x0
            Jr[3] = -UR[i, 0]
            Jr[4] = -UR[i, 1]
            Jr[5] = -UR[i, 2]
            for a in range(6):
                wa = wm * Jr[a]
                g[a] += wa * v
                for b in range(a, 6):
                    H[a, b] += wa * Jr[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g


@numba.njit(cache=True)
def tangential_squares(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                       target: np.ndarray, target_rows: np.ndarray, cov_target: np.ndarray,
                       epsilon: float) -> np.ndarray:
    """Return (M,) the squared component of ``r = T x_s - x_t`` in the target's tangent
    plane: ``max(r.r - r^T (I - C) r / (1 - epsilon), 0)`` (``C = I - (1 - eps) n n^T``),
    of the pairs ``x_s = source[source_rows[m]]``, ``x_t, C`` at ``target_rows[m]``."""
    n = source_rows.shape[0]
    out = np.empty(n)
    for m in range(n):
        s, t = source_rows[m], target_rows[m]
        x0, x1, x2 = source[s, 0], source[s, 1], source[s, 2]
        r0 = T[0, 0] * x0 + T[0, 1] * x1 + T[0, 2] * x2 + T[0, 3] - target[t, 0]
        r1 = T[1, 0] * x0 + T[1, 1] * x1 + T[1, 2] * x2 + T[1, 3] - target[t, 1]
        r2 = T[2, 0] * x0 + T[2, 1] * x1 + T[2, 2] * x2 + T[2, 3] - target[t, 2]
        C = cov_target[t]
        q0 = (1.0 - C[0, 0]) * r0 - C[0, 1] * r1 - C[0, 2] * r2
        q1 = -C[1, 0] * r0 + (1.0 - C[1, 1]) * r1 - C[1, 2] * r2
        q2 = -C[2, 0] * r0 - C[2, 1] * r1 + (1.0 - C[2, 2]) * r2
        normal = (r0 * q0 + r1 * q1 + r2 * q2) / (1.0 - epsilon)
        out[m] = max(r0 * r0 + r1 * r1 + r2 * r2 - normal, 0.0)
    return out


@numba.njit(cache=True, inline="always")
def _answers(n):
    """(distances inf, rows -1, flags False) of n points."""
    return np.full(n, np.inf), np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=np.bool_)


@numba.njit(cache=True, inline="always")
def _scan_candidates(points, m, candidates, r, target, labels, c):
    """(squared distance, row) of the nearest of row ``r``'s cached candidates to point m,
    and of the nearest labelled ``c`` (c < 0: none asked; -1 where none)."""
    px, py, pz = points[m, 0], points[m, 1], points[m, 2]
    best, best_j, best_c, best_cj = np.inf, -1, np.inf, -1
    for j in range(candidates.shape[1]):
        q = candidates[r, j]
        if q >= target.shape[0]:  # no more neighbours within the query radius
            break
        ex, ey, ez = target[q, 0] - px, target[q, 1] - py, target[q, 2] - pz
        d2 = ex * ex + ey * ey + ez * ez
        if d2 < best:
            best, best_j = d2, q
        if c >= 0 and labels[q] == c and d2 < best_c:
            best_c, best_cj = d2, q
    return best, best_j, best_c, best_cj


@numba.njit(cache=True, inline="always")
def _moved_squared(points, m, anchor, r):
    dx, dy, dz = (points[m, 0] - anchor[r, 0], points[m, 1] - anchor[r, 1],
                  points[m, 2] - anchor[r, 2])
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, inline="always")
def _class_decided(best_c, best_cj, lower, d_max):
    """(distance, row, unresolved) of the class's nearest from the candidates' best of the
    class, every other target point at least ``lower`` away (see class_cached_nearest)."""
    if best_cj >= 0 and lower > 0.0 and best_c < lower * lower:
        if best_c <= d_max * d_max:
            return np.sqrt(best_c), best_cj, False
        return np.inf, -1, False
    return np.inf, -1, not lower > d_max


@numba.njit(cache=True, inline="always")
def _stale(points, m, anchor, reach, r):
    """True where point m has moved beyond its row ``r``'s reach (or the row was never
    queried: a negative reach)."""
    return not _moved_squared(points, m, anchor, r) <= reach[r] * reach[r] or reach[r] < 0.0


@numba.njit(cache=True, inline="always")
def _cached_answer(points, m, candidates, r, target, d_max):
    """(distance, row) of point m's nearest cached candidate of row ``r`` within d_max
    (inf / -1 when none)."""
    best, best_j, _, _ = _scan_candidates(points, m, candidates, r, target, candidates[r], -1)
    if best <= d_max * d_max:
        return np.sqrt(best), best_j
    return np.inf, -1


@numba.njit(cache=True, inline="always")
def _class_from_candidates(points, m, anchor, bound, candidates, r, target, labels, c, d_max):
    """(distance, row, unresolved) of point m's nearest target point labelled ``c`` within
    d_max, from row ``r``'s geometric candidates where they decide it
    (:func:`class_cached_nearest`)."""
    _, _, best_c, best_cj = _scan_candidates(points, m, candidates, r, target, labels, c)
    return _class_decided(best_c, best_cj,
                          bound[r] - np.sqrt(_moved_squared(points, m, anchor, r)), d_max)


@numba.njit(cache=True)
def cached_nearest(points, rows, anchor, reach, candidates, target, d_max):
    """Nearest cached candidate of each point within d_max (inf / -1 when none), and the
    points whose displacement from their row's anchor exceeds its ``reach`` (stale: query
    again; a negative reach: never queried). ``rows``: each point's row of the cache."""
    n = points.shape[0]
    dist, idx, stale = _answers(n)
    for m in range(n):
        r = rows[m]
        if _stale(points, m, anchor, reach, r):
            stale[m] = True
            continue
        dist[m], idx[m] = _cached_answer(points, m, candidates, r, target, d_max)
    return dist, idx, stale


@numba.njit(cache=True)
def cached_nearest_and_class(points, rows, anchor, bound, reach, candidates, target, labels,
                             want, d_max):
    """:func:`cached_nearest` and :func:`class_cached_nearest` in one scan of the candidates.
    Returns (distance, index, stale, class
    distance, class index, unresolved); a stale point is also unresolved (query it again,
    then ask both)."""
    n = points.shape[0]
    dist, idx, stale = _answers(n)
    class_dist, class_idx, unresolved = _answers(n)
    for m in range(n):
        r = rows[m]
        moved2 = _moved_squared(points, m, anchor, r)
        if not moved2 <= reach[r] * reach[r] or reach[r] < 0.0:
            stale[m] = unresolved[m] = True
            continue
        best, best_j, best_c, best_cj = _scan_candidates(points, m, candidates, r, target,
                                                         labels, want[m])
        if best <= d_max * d_max:
            dist[m], idx[m] = np.sqrt(best), best_j
        class_dist[m], class_idx[m], unresolved[m] = _class_decided(
            best_c, best_cj, bound[r] - np.sqrt(moved2), d_max)
    return dist, idx, stale, class_dist, class_idx, unresolved


@numba.njit(cache=True)
def class_cached_nearest(points, rows, anchor, bound, reach, candidates, target, labels, want,
                         d_max):
    """The nearest target point labelled ``want[m]`` within d_max (inf / -1 when none) of each
    point, from a geometric cache's candidates where they decide it, and the points where they
    do not (unresolved: ask the class's own tree).

    A row's candidates are its k nearest target points at its anchor, every other one at
    least ``bound`` from there; after moving by delta, every other one is at least
    ``bound - delta`` away. So the nearest candidate of the class is the class's nearest
    where it is closer than that, and none of the class lies within d_max where no candidate
    does and ``bound - delta > d_max``.
    """
    n = points.shape[0]
    dist, idx, unresolved = _answers(n)
    for m in range(n):
        r = rows[m]
        if reach[r] < 0.0:  # never queried
            unresolved[m] = True
            continue
        dist[m], idx[m], unresolved[m] = _class_from_candidates(
            points, m, anchor, bound, candidates, r, target, labels, want[m], d_max)
    return dist, idx, unresolved


@numba.njit(cache=True)
def class_rank_cached(points, rows, which, order, rank, probs, min_class_prob, first_dist,
                      first_idx, first_unresolved, g_anchor, g_bound, g_reach, g_candidates,
                      target, labels, c_anchor, c_reach, c_candidates, c_classes, d_max,
                      rank_target, rank_dist):
    """Semantic-ICP's class candidates of one ``rank`` from cached candidates, for the points
    ``which``: the nearest target point labelled ``order[m, rank]`` within d_max, written to
    ``rank_target[rank, m]`` and ``rank_dist[rank, m]`` (left as they are where none).

    Rank 0 asks every point, the others those whose class has ``probs`` at least
    ``min_class_prob``. The answer comes, in turn, from ``first_*`` (rank 0, where given:
    :func:`cached_nearest_and_class`'s class answer; an empty ``first_dist`` where not), from
    the geometric cache's candidates where they decide it (as :func:`class_cached_nearest`;
    an empty ``g_reach``: no geometric cache), or from the class cache (``c_*``: its rows
    ``rows[m]``, ``c_classes`` the class each row was queried for), as
    :func:`cached_nearest`; both caches' candidates are rows of ``target`` (its points,
    ``labels`` their classes). Returns the points whose class-cache row is stale (moved beyond
    its reach, never queried, or queried for another class): query them again, then again
    here."""
    use_first = first_dist.shape[0] > 0
    use_geometric = g_reach.shape[0] > 0
    stale = np.empty(which.shape[0], dtype=np.int64)
    n_stale = 0
    for p in range(which.shape[0]):
        m = which[p]
        c = order[m, rank]
        if rank > 0 and not probs[m, c] >= min_class_prob:
            continue
        r = rows[m]
        if rank == 0 and use_first:
            dist, idx, unresolved = first_dist[m], first_idx[m], first_unresolved[m]
        elif use_geometric and g_reach[r] >= 0.0:
            dist, idx, unresolved = _class_from_candidates(
                points, m, g_anchor, g_bound, g_candidates, r, target, labels, c, d_max)
        else:
            dist, idx, unresolved = np.inf, -1, True
        if unresolved:
            if c_classes[r] != c or _stale(points, m, c_anchor, c_reach, r):
                stale[n_stale] = m
                n_stale += 1
                continue
            dist, idx = _cached_answer(points, m, c_candidates, r, target, d_max)
        if idx >= 0:
            rank_target[rank, m], rank_dist[rank, m] = idx, dist
    return stale[:n_stale]


@numba.njit(cache=True)
def top_classes(probs, top):
    """Each row's ``top`` most probable classes, best first (ties: the lower class, as
    repeated ``argmax`` with the chosen entries masked)."""
    n, c = probs.shape
    order = np.empty((n, top), dtype=np.int64)
    for i in range(n):
        for rank in range(top):
            best = -1
            value = 0.0
            for j in range(c):
                taken = False
                for r in range(rank):
                    if order[i, r] == j:
                        taken = True
                if taken:
                    continue
                if best < 0 or probs[i, j] > value:
                    best = j
                    value = probs[i, j]
            order[i, rank] = best
    return order


@numba.njit(cache=True)
def group_rows(keys, searched, n_groups):
    """Rows with ``searched`` grouped by ``keys`` (0 <= key < n_groups), each group in row
    order: (starts (n_groups + 1), rows) so that group g is rows[starts[g]:starts[g + 1]]."""
    starts = np.zeros(n_groups + 1, dtype=np.int64)
    for i in range(keys.shape[0]):
        if searched[i]:
            starts[keys[i] + 1] += 1
    for g in range(n_groups):
        starts[g + 1] += starts[g]
    fill = starts[:-1].copy()
    rows = np.empty(starts[n_groups], dtype=np.int64)
    for i in range(keys.shape[0]):
        if searched[i]:
            rows[fill[keys[i]]] = i
            fill[keys[i]] += 1
    return starts, rows


@numba.njit(cache=True, inline="always")
def _pair_arrays(count):
    """Empty (source rows, target rows, distances, weights) of ``count`` pairs."""
    return (np.empty(count, dtype=np.int64), np.empty(count, dtype=np.int64),
            np.empty(count), np.empty(count))


@numba.njit(cache=True)
def semantic_candidates(nearest, nearest_dist, order, rank_target, rank_dist,
                        classes, source_probs, target_probs, label_noise, sigma):
    """Semantic-ICP's candidate list: the geometric nearest neighbours (``nearest`` >= 0),
    then for each rank and each class of ``classes`` in turn the class candidates
    (``rank_target`` >= 0) that are not that nearest neighbour, each block in row order;
    their scores: the label agreement (with ``label_noise``; the nearest neighbour's summed
    over the classes) times the Gaussian residual likelihood exp(-d^2 / (2 sigma^2)).
    Returns (source rows, target rows, distances, scores)."""
    n, top = order.shape
    n_classes = source_probs.shape[1]
    count = 0
    for i in range(n):
        if nearest[i] >= 0:
            count += 1
    for rank in range(top):
        for i in range(n):
            t = rank_target[rank, i]
            if t >= 0 and t != nearest[i]:
                count += 1
    src, tgt, dist, prior = _pair_arrays(count)
    m = 0
    for i in range(n):
        t = nearest[i]
        if t >= 0:
            agreement = 0.0
            for c in range(n_classes):
                agreement += source_probs[i, c] * target_probs[t, c]
            src[m], tgt[m], dist[m], prior[m] = i, t, nearest_dist[i], agreement
            m += 1
    # each rank's candidates grouped by class (each class in row order), then written class
    # by class in the order of ``classes``
    wanted = np.empty(n, dtype=np.bool_)
    for rank in range(top):
        for i in range(n):
            wanted[i] = rank_target[rank, i] >= 0 and rank_target[rank, i] != nearest[i]
        starts, grouped = group_rows(order[:, rank], wanted, source_probs.shape[1])
        for k in range(classes.shape[0]):
            c = classes[k]
            for p in range(starts[c], starts[c + 1]):
                i = grouped[p]
                t = rank_target[rank, i]
                src[m], tgt[m], dist[m] = i, t, rank_dist[rank, i]
                prior[m] = source_probs[i, c] * target_probs[t, c]
                m += 1
    keep = 1.0 - label_noise
    floor = label_noise / n_classes
    for m in range(count):
        if label_noise > 0.0:
            prior[m] = keep * prior[m] + floor
        z = dist[m] / sigma
        prior[m] *= np.exp(-0.5 * z * z)
    return src, tgt, dist, prior


@numba.njit(cache=True)
def normalise_keep(src, tgt, omega, dist, n, posterior, min_weight):
    """The candidates with weight >= ``min_weight``, the weights first normalised over each
    source row's candidates where ``posterior`` (sums in list order, as ``np.bincount``)."""
    count = src.shape[0]
    if posterior:
        total = np.zeros(n)
        for m in range(count):
            total[src[m]] += omega[m]
        for m in range(count):
            omega[m] = omega[m] / max(total[src[m]], 1e-300)
    kept = 0
    for m in range(count):
        if omega[m] >= min_weight:
            kept += 1
    out_src, out_tgt, out_w, out_d = _pair_arrays(kept)
    k = 0
    for m in range(count):
        if omega[m] >= min_weight:
            out_src[k], out_tgt[k], out_w[k], out_d[k] = src[m], tgt[m], omega[m], dist[m]
            k += 1
    return out_src, out_tgt, out_w, out_d


@numba.njit(cache=True)
def same_voxel_pairs(T, source, source_idx, target_idx, distances, aligned, target, origin,
                     pitch, lo, dims, table, columns, cells, cell_rows, labels, check_labels):
    """Same-voxel matching of the pairs flagged ``aligned``: the source point (moved by T)
    is matched to its own cell's map point where the cell holds one (the dense ``table`` of
    the map's box when it has rows, else a binary search of the sorted ``cells``: of the
    cell's (i, j) column, which begins at ``columns[i dims_1 + j]``, when that has rows), of
    the pair's target's label where ``check_labels``. Returns the new (target rows,
    distances)."""
    m = source_idx.shape[0]
    new_target = target_idx.copy()
    new_dist = distances.copy()
    n_cells = cells.shape[0]
    dense = table.shape[0] > 0
    by_column = columns.shape[0] > 0
    for p in range(m):
        if not aligned[p]:
            continue
        s = source_idx[p]
        x = T[0, 0] * source[s, 0] + T[0, 1] * source[s, 1] + T[0, 2] * source[s, 2] + T[0, 3]
        y = T[1, 0] * source[s, 0] + T[1, 1] * source[s, 1] + T[1, 2] * source[s, 2] + T[1, 3]
        z = T[2, 0] * source[s, 0] + T[2, 1] * source[s, 1] + T[2, 2] * source[s, 2] + T[2, 3]
        k0 = np.int64(np.floor((x - origin[0]) / pitch)) - lo[0]
        k1 = np.int64(np.floor((y - origin[1]) / pitch)) - lo[1]
        k2 = np.int64(np.floor((z - origin[2]) / pitch)) - lo[2]
        if k0 < 0 or k1 < 0 or k2 < 0 or k0 >= dims[0] or k1 >= dims[1] or k2 >= dims[2]:
            continue
        key = (k0 * dims[1] + k1) * dims[2] + k2
        if dense:
            row = np.int64(table[key])
        elif by_column:
            first, end = columns[k0 * dims[1] + k1], columns[k0 * dims[1] + k1 + 1]
            pos = first + np.searchsorted(cells[first:end], key)
            row = cell_rows[pos] if pos < end and cells[pos] == key else -1
        else:
            pos = min(np.searchsorted(cells, key), n_cells - 1)
            row = cell_rows[pos] if cells[pos] == key else -1
        if row < 0 or (check_labels and labels[row] != labels[target_idx[p]]):
            continue
        ex, ey, ez = target[row, 0] - x, target[row, 1] - y, target[row, 2] - z
        new_target[p] = row
        new_dist[p] = np.sqrt(ex * ex + ey * ey + ez * ez)
    return new_target, new_dist


@numba.njit(cache=True)
def pooled_rows(cov: np.ndarray, source_rows: np.ndarray, target_rows: np.ndarray,
                n_target: int) -> tuple[np.ndarray, np.ndarray]:
    """Return (G, 3, 3) means of ``cov[source_rows[m]]`` over the pairs m that share a target
    row, and the (M,) group of each pair (groups numbered in order of first appearance)."""
    slot = np.full(n_target, -1, np.int64)
    m_pairs = target_rows.shape[0]
    group = np.empty(m_pairs, np.int64)
    g = 0
    for m in range(m_pairs):
        t = target_rows[m]
        if slot[t] < 0:
            slot[t] = g
            g += 1
        group[m] = slot[t]
    sums = np.zeros((g, 3, 3))
    counts = np.zeros(g)
    for m in range(m_pairs):
        j = group[m]
        c = cov[source_rows[m]]
        for a in range(3):
            for b in range(3):
                sums[j, a, b] += c[a, b]
        counts[j] += 1.0
    for j in range(g):
        for a in range(3):
            for b in range(3):
                sums[j, a, b] /= counts[j]
    return sums, group


@numba.njit(cache=True)
def resultant_lengths(re, im, turn_re, turn_im, count):
    """The (count, d) lengths ``|sum_m terms[m, a]|`` of the complex (M, d) terms ``re + i im``
    and of the terms multiplied by ``turn`` once, twice, ... (``count`` in all): numpy's
    ``abs(terms.sum(axis=0))`` then ``terms *= turn`` (to the last bit or two: numpy's
    vectorised product and abs round differently), without a numpy call per step (8000 of
    them took 14 ms of a registration's second thread on the scan's 15k-point halves)."""
    m, d = re.shape
    re = re.copy()
    im = im.copy()
    out = np.empty((count, d))
    for k in range(count):
        for a in range(d):
            sr = 0.0
            si = 0.0
            for j in range(m):
                sr += re[j, a]
                si += im[j, a]
            out[k, a] = math.hypot(sr, si)
        for j in range(m):
            for a in range(d):
                r, i = re[j, a], im[j, a]
                tr, ti = turn_re[j, a], turn_im[j, a]
                re[j, a] = r * tr - i * ti
                im[j, a] = r * ti + i * tr
    return out
