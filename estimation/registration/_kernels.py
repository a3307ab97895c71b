"""Vectorised numpy kernels for the per-correspondence 3x3 algebra of GICP (hot path).

Every 3x3 matrix is handled as columns of its entries: one numpy operation per formula term
over all M matrices, no per-matrix LAPACK call and no Python loop. They replaced numba
kernels (issue 14, measured with ``benchmarks/registration.py --start-up``): numba's were
1.5-10x faster per call, but every new process paid ~0.15 s (idle machine; ~0.7-1 s under
load) to load them from numba's cache and ~1.7 s to compile them on a fresh install, so the
first registration of a process took 2.4-3.5x a warm one (these: 1.0-1.2x), and a one-off
``octofactor register`` spent more time there than in the kernels.
"""
from __future__ import annotations

import numpy as np


def smallest_eigenvectors(a00, a01, a02, a11, a12, a22) -> np.ndarray:
    """(M, 3) unit eigenvectors of the smallest eigenvalue of symmetric 3x3 matrices.

    The entries are (M,) arrays. Eigenvalue by the trigonometric method (Smith 1961); the
    eigenvector is the largest cross product of two rows of A - lambda I. An isotropic
    matrix (any direction) gives (0, 0, 1).
    """
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    iso = p2 <= 1e-30 * (q * q + 1e-300)
    p = np.sqrt(np.where(iso, 6.0, p2) / 6.0)
    c00, c11, c22 = b00 / p, b11 / p, b22 / p
    c01, c02, c12 = a01 / p, a02 / p, a12 / p
    r = 0.5 * (c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02)
               + c02 * (c01 * c12 - c11 * c02))
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    u0, u1, u2 = a00 - lam, a11 - lam, a22 - lam
    # rows r0 = (u0, a01, a02), r1 = (a01, u1, a12), r2 = (a02, a12, u2); their cross products
    crosses = (
        (a01 * a12 - a02 * u1, a02 * a01 - u0 * a12, u0 * u1 - a01 * a01),  # r0 x r1
        (a01 * u2 - a02 * a12, a02 * a02 - u0 * u2, u0 * a12 - a01 * a02),  # r0 x r2
        (u1 * u2 - a12 * a12, a12 * a02 - a01 * u2, a01 * a12 - u1 * a02),  # r1 x r2
    )
    n2 = [cx * cx + cy * cy + cz * cz for cx, cy, cz in crosses]
    best = np.where(n2[1] > n2[0], 1, 0)
    best = np.where(n2[2] > np.maximum(n2[0], n2[1]), 2, best)
    v = np.empty((len(q), 3))
    for i in range(3):
        v[:, i] = np.choose(best, [c[i] for c in crosses])
    norm = np.sqrt(np.choose(best, n2))
    bad = iso | ~(norm > 0.0)
    v /= np.where(bad, 1.0, norm)[:, None]
    v[bad] = (0.0, 0.0, 1.0)
    return v


def _planes(normals: np.ndarray, epsilon: float) -> np.ndarray:
    """(M, 3, 3) ``I - (1 - epsilon) n n^T``."""
    out = -(1.0 - epsilon) * normals[:, :, None] * normals[:, None, :]
    out[:, [0, 1, 2], [0, 1, 2]] += 1.0
    return out


def regularise_covariances(cov: np.ndarray, epsilon: float) -> np.ndarray:
    """Replace the eigenvalues of each (N, 3, 3) covariance by (epsilon, 1, 1).

    With orthonormal eigenvectors that is I - (1 - epsilon) n n^T, n the surface normal.
    """
    n = smallest_eigenvectors(cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1],
                              cov[:, 1, 2], cov[:, 2, 2])
    return _planes(n, epsilon)


def neighbour_covariances(points: np.ndarray, idx: np.ndarray, epsilon: float) -> np.ndarray:
    """Plane-regularised covariances from each row of (M, k) neighbour indices into ``points``.

    Coordinates are taken relative to each row's first neighbour (the point itself for a
    k-NN query) before the second moments, so that clouds far from the origin keep their
    precision.
    """
    k = idx.shape[1]
    cols = []
    for i in range(3):
        c = points[:, i][idx]
        c -= c[:, :1]
        cols.append(c)
    x, y, z = cols
    mx, my, mz = x.mean(axis=1), y.mean(axis=1), z.mean(axis=1)

    def moment(u, v, mu, mv):
        return np.einsum("mk,mk->m", u, v) / k - mu * mv

    n = smallest_eigenvectors(moment(x, x, mx, mx), moment(x, y, mx, my),
                              moment(x, z, mx, mz), moment(y, y, my, my),
                              moment(y, z, my, mz), moment(z, z, mz, mz))
    return _planes(n, epsilon)


def whitening(cov_target: np.ndarray, cov_source: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Return (M, 3, 3) U^T with U U^T = (Sigma_t + R Sigma_s R^T)^-1 (U lower Cholesky)."""
    C = cov_target + np.matmul(np.matmul(R, cov_source), R.T)
    a, d, f = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    b = 0.5 * (C[:, 0, 1] + C[:, 1, 0])
    c = 0.5 * (C[:, 0, 2] + C[:, 2, 0])
    e = 0.5 * (C[:, 1, 2] + C[:, 2, 1])
    # symmetric 3x3 inverse by cofactors
    A00 = d * f - e * e
    A01 = c * e - b * f
    A02 = b * e - c * d
    det = a * A00 + b * A01 + c * A02
    i00, i01, i02 = A00 / det, A01 / det, A02 / det
    i11, i12, i22 = (a * f - c * c) / det, (b * c - a * e) / det, (a * d - b * b) / det
    # Cholesky L of the information matrix; U^T = L^T
    out = np.zeros((len(C), 3, 3))
    l00 = np.sqrt(i00)
    l10 = i01 / l00
    l20 = i02 / l00
    l11 = np.sqrt(i11 - l10 * l10)
    l21 = (i12 - l20 * l10) / l11
    out[:, 0, 0] = l00
    out[:, 0, 1] = l10
    out[:, 0, 2] = l20
    out[:, 1, 1] = l11
    out[:, 1, 2] = l21
    out[:, 2, 2] = np.sqrt(i22 - l20 * l20 - l21 * l21)
    return out


def gicp_terms(T: np.ndarray, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
               sqrt_w: np.ndarray, want_jacobians: bool):
    """Return (whitened residuals (M,3), Jacobians (M,3,6), Mahalanobis e (M,)).

    r = x_t - R x_s - t; dr/dxi for T Exp(xi) = [R [x_s]_x, -R]; both premultiplied by U^T
    and scaled by sqrt_w.
    """
    R = T[:3, :3]
    r = target - source @ R.T - T[:3, 3]
    v = np.einsum("mij,mj->mi", Ut, r)
    e = np.einsum("mi,mi->m", v, v)
    rw = v * sqrt_w[:, None]
    if not want_jacobians:
        return rw, np.empty((0, 3, 6)), e
    UR = np.matmul(Ut, R) * sqrt_w[:, None, None]
    x0, x1, x2 = (source[:, i, None] for i in range(3))
    J = np.empty((len(source), 3, 6))
    # UR @ [x]_x
    J[:, :, 0] = UR[:, :, 1] * x2 - UR[:, :, 2] * x1
    J[:, :, 1] = UR[:, :, 2] * x0 - UR[:, :, 0] * x2
    J[:, :, 2] = UR[:, :, 0] * x1 - UR[:, :, 1] * x0
    J[:, :, 3:] = -UR
    return rw, J, e


def cached_nearest(points, anchor, reach, candidates, target, d_max):
    """Nearest cached candidate of each point within d_max (inf / -1 when none), and the
    rows whose displacement from their anchor exceeds ``reach`` (stale: query again)."""
    n = len(points)
    moved = points - anchor
    stale = ~(np.einsum("mi,mi->m", moved, moved) <= reach * reach) | (reach < 0.0)
    dist = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int64)
    rows = np.nonzero(~stale)[0]
    if len(rows):
        cand = candidates[rows]
        valid = cand < len(target)  # the KD-tree's "no neighbour" sentinel is n
        diff = target[np.where(valid, cand, 0)] - points[rows, None, :]
        d2 = np.where(valid, np.einsum("mki,mki->mk", diff, diff), np.inf)
        best = np.argmin(d2, axis=1)
        d2best = d2[np.arange(len(rows)), best]
        ok = d2best <= d_max * d_max
        dist[rows[ok]] = np.sqrt(d2best[ok])
        idx[rows[ok]] = cand[np.arange(len(rows)), best][ok]
    return dist, idx, stale
