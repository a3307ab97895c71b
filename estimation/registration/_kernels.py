"""Numba kernels for the per-correspondence 3x3 algebra of GICP (hot path, no Python loop).

Stacks of 3x3 products through numpy cost ~1 ms per 10k matrices each; these loops do the
whole whitening / residual / Jacobian in one pass. Compiled on first use and cached on disk.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def regularise_covariances(cov: np.ndarray, epsilon: float) -> np.ndarray:
    """Replace the eigenvalues of each (N, 3, 3) covariance by (epsilon, 1, 1)."""
    n = cov.shape[0]
    out = np.empty_like(cov)
    for m in range(n):
        _, vecs = np.linalg.eigh(cov[m])
        nx, ny, nz = vecs[0, 0], vecs[1, 0], vecs[2, 0]
        nrm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if nrm == 0.0:
            nrm = 1.0
        nx, ny, nz = nx / nrm, ny / nrm, nz / nrm
        s = 1.0 - epsilon
        out[m, 0, 0] = 1.0 - s * nx * nx
        out[m, 0, 1] = -s * nx * ny
        out[m, 0, 2] = -s * nx * nz
        out[m, 1, 0] = -s * ny * nx
        out[m, 1, 1] = 1.0 - s * ny * ny
        out[m, 1, 2] = -s * ny * nz
        out[m, 2, 0] = -s * nz * nx
        out[m, 2, 1] = -s * nz * ny
        out[m, 2, 2] = 1.0 - s * nz * nz
    return out


@numba.njit(cache=True)
def whitening(cov_target: np.ndarray, cov_source: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Return (M, 3, 3) U^T with U U^T = (Sigma_t + R Sigma_s R^T)^-1 (U lower Cholesky)."""
    n = cov_target.shape[0]
    out = np.zeros((n, 3, 3))
    C = np.empty((3, 3))
    RS = np.empty((3, 3))
    for m in range(n):
        for i in range(3):
            for j in range(3):
                RS[i, j] = R[i, 0] * cov_source[m, 0, j] + R[i, 1] * cov_source[m, 1, j] \
                    + R[i, 2] * cov_source[m, 2, j]
        for i in range(3):
            for j in range(3):
                C[i, j] = cov_target[m, i, j] + RS[i, 0] * R[j, 0] + RS[i, 1] * R[j, 1] \
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
        out[m, 0, 0] = l00
        out[m, 0, 1] = l10
        out[m, 0, 2] = l20
        out[m, 1, 1] = l11
        out[m, 1, 2] = l21
        out[m, 2, 2] = l22
    return out


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
    for m in range(n):
        x0, x1, x2 = source[m, 0], source[m, 1], source[m, 2]
        r = np.empty(3)
        for i in range(3):
            r[i] = target[m, i] - (T[i, 0] * x0 + T[i, 1] * x1 + T[i, 2] * x2 + T[i, 3])
        ee = 0.0
        for i in range(3):
            v = Ut[m, i, 0] * r[0] + Ut[m, i, 1] * r[1] + Ut[m, i, 2] * r[2]
            ee += v * v
            rw[m, i] = v * sqrt_w[m]
        e[m] = ee
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
