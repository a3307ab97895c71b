"""The batched GICP factor: every correspondence of a cloud pair in ONE GTSAM factor.

A per-correspondence :class:`gtsam.CustomFactor` costs a Python call (~16 us) per
correspondence per linearisation and measured 5-8x slower than Open3D's GICP; one factor
whose error function evaluates all M correspondences with vectorised numpy costs one Python
call per linearisation (see benchmarks/registration.py, ``--factor-ablation``).

Conventions: the unknown is ``T_target_source`` (:class:`gtsam.Pose3`), perturbed on the
right, ``T * Expmap(xi)`` with ``xi = [omega, v]`` (GTSAM's tangent order [rotation,
translation]). The residual of correspondence k is ``r_k = x_t - T x_s`` (eq. (3)), whitened
with ``U_k^T`` where ``U_k U_k^T = C_k^-1`` and ``C_k = Sigma_t + R Sigma_s R^T``.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..aot import kernels

# compiled ahead of time by `make setup` (estimation/aot.py), numba's JIT otherwise
_kernels = kernels("estimation.registration._kernels")


def skew(v: np.ndarray) -> np.ndarray:
    """Return the (..., 3, 3) cross-product matrices of the (..., 3) vectors ``v``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def cauchy_loss(e: np.ndarray, alpha: float) -> np.ndarray:
    """rho_alpha(e) = alpha^2 log(1 + e / alpha^2) of the squared Mahalanobis distance e."""
    return alpha ** 2 * np.log1p(e / alpha ** 2)


def cauchy_weight(e: np.ndarray, alpha: float) -> np.ndarray:
    """rho'_alpha(e) = 1 / (1 + e / alpha^2): the IRLS weight (GTSAM's mEstimator.Cauchy)."""
    return 1.0 / (1.0 + e / alpha ** 2)


@dataclass(frozen=True)
class GicpTerms:
    """The whitened correspondences of one linearisation.

    Attributes
    ----------
    residuals : (M, 3) whitened residuals U_k^T r_k (times sqrt(w_k) when weights are given)
    jacobians : (M, 3, 6) whitened Jacobians U_k^T dr_k/dxi (same scaling), or None
    mahalanobis : (M,) e_k = ||r_k||^2_{C_k}
    """

    residuals: np.ndarray
    jacobians: np.ndarray | None
    mahalanobis: np.ndarray


def whitening(cov_target: np.ndarray, cov_source: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Return (M, 3, 3) ``U_k^T`` with ``U_k U_k^T = (Sigma_t + R Sigma_s R^T)^-1``."""
    return _kernels.whitening(np.ascontiguousarray(cov_target, dtype=float),
                              np.ascontiguousarray(cov_source, dtype=float),
                              np.ascontiguousarray(R, dtype=float))


def _rows(rows: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rows, dtype=np.int64)


def _f8(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


def whitening_rows(cov_target: np.ndarray, target_rows: np.ndarray, cov_source: np.ndarray,
                   source_rows: np.ndarray, R: np.ndarray) -> np.ndarray:
    """:func:`whitening` of ``cov_target[target_rows]`` and ``cov_source[source_rows]``,
    without gathering the (M, 3, 3) stacks first (the same numbers)."""
    return _kernels.whitening_rows(_f8(cov_target), _rows(target_rows), _f8(cov_source),
                                   _rows(source_rows), _f8(R))


def whitening_rows_into(out: np.ndarray, cov_target: np.ndarray, target_rows: np.ndarray,
                        cov_source: np.ndarray, source_rows: np.ndarray, R: np.ndarray) -> None:
    """:func:`whitening_rows` written into ``out``, a zeroed C-contiguous (M, 3, 3) array
    (or a range of rows of one)."""
    _kernels.whitening_rows_into(out, _f8(cov_target), _rows(target_rows), _f8(cov_source),
                                 _rows(source_rows), _f8(R))


def pooled_covariances(cov_source: np.ndarray, source_rows: np.ndarray,
                       target_rows: np.ndarray, n_target: int) -> tuple[np.ndarray, np.ndarray]:
    """Return (covariances, rows): the mean of ``cov_source[source_rows]`` over the pairs that
    share a target row, and each pair's row of it, for :func:`whitening_rows` in place of
    ``(cov_source, source_rows)``. ``n_target``: the target's row count."""
    return _kernels.pooled_rows(_f8(cov_source), _rows(source_rows), _rows(target_rows),
                                int(n_target))


def gicp_terms(T: np.ndarray, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
               jacobians: bool = True, sqrt_weights: np.ndarray | None = None) -> GicpTerms:
    """Return whitened residuals (and Jacobians) of eq. (3) at the 4x4 ``T``.

    ``source`` and ``target`` are the matched (M, 3) points, ``Ut`` the (M, 3, 3) whitening
    ``U_k^T``. Jacobian of ``r = x_t - R x_s - t`` for ``T Exp(xi)``: ``[R [x_s]_x, -R]``.
    With ``sqrt_weights`` residuals and Jacobians are scaled by them (``mahalanobis`` is not).
    """
    sw = np.ones(len(source)) if sqrt_weights is None else np.ascontiguousarray(sqrt_weights,
                                                                              dtype=float)
    rw, J, e = _kernels.gicp_terms(np.ascontiguousarray(T, dtype=float),
                                   np.ascontiguousarray(source, dtype=float),
                                   np.ascontiguousarray(target, dtype=float),
                                   np.ascontiguousarray(Ut, dtype=float), sw, bool(jacobians))
    return GicpTerms(rw, J if jacobians else None, e)


def shift_sensitivities(jacobians: np.ndarray, Ut: np.ndarray, w: np.ndarray,
                        weight: np.ndarray) -> np.ndarray:
    """Return (M, 6, 3) ``(w_k J_k^T U_k^T) weight_k`` in one pass (numpy's batched matmul
    took 47 ms for a raw half-room's 435k pairs)."""
    return _kernels.shift_sensitivities(_f8(jacobians), _f8(Ut), _f8(w), _f8(weight))


def inplane_sums(jacobians: np.ndarray, Ut: np.ndarray, w: np.ndarray, group: np.ndarray,
                 axis: np.ndarray) -> np.ndarray:
    """Return (G, 3, 6): per group (``group``, G = its largest index + 1) and lattice axis b,
    ``w_k J_k^T U_k^T e_b`` summed over its pairs whose dominant ``axis`` is not b, in one
    pass."""
    return _kernels.inplane_sums(_f8(jacobians), _f8(Ut), _f8(w), _rows(group), _rows(axis),
                                 int(group.max()) + 1)


def grouped_sums(keys: np.ndarray, lo: np.ndarray, span: np.ndarray,
                 values: np.ndarray) -> np.ndarray:
    """Return ``values`` (M, d) summed over the rows of equal (M, 3) int64 ``keys`` within
    ``lo + [0, span)``, one row per distinct key in ``np.unique``'s order, in one pass over a
    table of the keys' box."""
    return _kernels.grouped_sums(_rows(keys), _rows(lo), _rows(span), _f8(values))


def solution_sums(T: np.ndarray, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
                  terms: GicpTerms, w: np.ndarray, c: np.ndarray, cov_target: np.ndarray,
                  target_rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return (H, curvature sum, scores, target normals, residuals along them,
    sensitivities) of the matched pairs at ``T`` in one pass (``terms``: their
    :func:`gicp_terms`; ``w`` the IRLS weights, ``c`` the robust cost's curvature terms;
    ``cov_target[target_rows]`` the pairs' target covariances ``I - (1 - eps) n n^T``):
    ``sum w J^T J``, ``sum c g g^T`` with ``g = J^T r``, ``w g`` (M, 6), ``n`` (M, 3),
    ``n^T (x_t - T x_s)`` (M,) and ``w J^T U^T n`` (M, 6) (Registration.solution_terms)."""
    return _kernels.solution_sums(_f8(T), _f8(source), _f8(target), _f8(Ut), _f8(terms.jacobians),
                                  _f8(terms.residuals), _f8(w), _f8(c), _f8(cov_target),
                                  _rows(target_rows))


def tangential_squares(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                       target: np.ndarray, target_rows: np.ndarray, cov_target: np.ndarray,
                       epsilon: float) -> np.ndarray:
    """Return (M,) the squared component of ``T x_s - x_t`` in the target's tangent plane,
    for the pairs ``(source[source_rows], target[target_rows])`` whose target covariances
    ``cov_target[target_rows]`` are ``I - (1 - epsilon) n n^T`` (one pass, no gathered
    copies or (M, 3, 3) temporaries)."""
    return _kernels.tangential_squares(_f8(T), _f8(source), _rows(source_rows), _f8(target),
                                       _rows(target_rows), _f8(cov_target), float(epsilon))


def mahalanobis(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                target: np.ndarray, target_rows: np.ndarray, Ut: np.ndarray) -> np.ndarray:
    """Return :func:`gicp_terms`' ``mahalanobis`` of the pairs
    ``(source[source_rows], target[target_rows])`` (the same numbers, no gathered copies)."""
    return _kernels.gicp_mahalanobis(_f8(T), _f8(source), _rows(source_rows), _f8(target),
                                     _rows(target_rows), _f8(Ut))


def normal_equations(T: np.ndarray, source: np.ndarray, source_rows: np.ndarray,
                     target: np.ndarray, target_rows: np.ndarray, Ut: np.ndarray,
                     weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(sum_k w_k J_k^T J_k, sum_k w_k J_k^T r_k)`` (whitened, as :func:`gicp_terms`)
    of the pairs ``(source[source_rows], target[target_rows])`` in one pass, without the
    (M, 3, 6) Jacobians."""
    return _kernels.gicp_normal_equations(_f8(T), _f8(source), _rows(source_rows), _f8(target),
                                          _rows(target_rows), _f8(Ut), _f8(weights))


# relative damping of a step whose system GTSAM finds indeterminate (gauss_newton_step): GTSAM's
# Cholesky gives up on pivots below about 1e-9 of the largest, so the damping must clear that
DEGENERATE_DAMPING = 1e-6


def gauss_newton_step(T: np.ndarray, H: np.ndarray, g: np.ndarray, key: int) -> np.ndarray:
    """Return the 4x4 pose after one Gauss-Newton step of the weighted least-squares problem
    with information ``H`` and gradient ``g = sum w J^T r`` (:func:`normal_equations`), solved
    by GTSAM: a :class:`gtsam.HessianFactor` eliminated by ``GaussianFactorGraph.optimize``
    and retracted by ``Values.retract``, as ``GaussNewtonOptimizer`` does with the batched
    factor's linearisation (its Cholesky elimination forms the same ``J^T J``; the optimiser
    also evaluates the cost twice more, which one step does not use).
    """
    values = gtsam.Values()
    values.insert(key, gtsam.Pose3(T))
    try:
        return values.retract(_hessian_graph(key, H, g).optimize()).atPose3(key).matrix()
    except RuntimeError:
        # GTSAM's IndeterminateLinearSystemException: a direction the pairs do not constrain
        # (degenerate geometry, e.g. collinear clouds). Damped as Levenberg-Marquardt does,
        # the step leaves that direction alone; the covariance's degeneracy test then reports
        # it (converged=False).
        damping = DEGENERATE_DAMPING * max(float(np.trace(H)) / 6.0, 1e-300)
        return values.retract(_hessian_graph(key, H + damping * np.eye(6), g).optimize()
                              ).atPose3(key).matrix()


def _hessian_graph(key: int, H: np.ndarray, g: np.ndarray) -> gtsam.GaussianFactorGraph:
    graph = gtsam.GaussianFactorGraph()
    # the linearised factor is ||J dx + r||^2: G = J^T J, the linear term J^T (-r)
    graph.add(gtsam.HessianFactor(key, H, -g, 0.0))
    return graph


class BatchedGicpFactor:
    """One :class:`gtsam.CustomFactor` holding every correspondence of a cloud pair.

    The robust Cauchy kernel enters as fixed IRLS weights ``w_k`` (computed by the outer
    loop at ``T_old``): inside one outer iteration the factor is a plain weighted least-squares
    problem, which GTSAM's optimisers handle exactly, and the outer loop re-weights.

    Parameters
    ----------
    key : GTSAM key of the ``T_target_source`` pose
    source, target : (M, 3) matched points
    Ut : (M, 3, 3) whitening (from :func:`whitening`)
    weights : (M,) IRLS weights (Cauchy weight times the semantic weight where applicable)
    """

    def __init__(self, key: int, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
                 weights: np.ndarray):
        self.key = key
        self.source = source
        self.target = target
        self.Ut = Ut
        self.sqrt_w = np.sqrt(weights)
        m = len(source)
        self.factor = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(3 * m), [key],
                                         _error_function(key, source, target, Ut, self.sqrt_w))


def _error_function(key, source, target, Ut, sqrt_w):
    """The CustomFactor callback, a closure over the arrays only.

    A bound method would close a reference cycle through the C++ factor (Python object ->
    gtsam.CustomFactor -> callback -> Python object) that Python's garbage collector cannot
    see: every factor, with its (M, 3, 3) whitening, leaked (24 GB over the 50k benchmark).
    """
    def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
        T = values.atPose3(key).matrix()
        terms = gicp_terms(T, source, target, Ut, jacobians=H is not None, sqrt_weights=sqrt_w)
        if H is not None:
            H[0] = terms.jacobians.reshape(-1, 6)
        return terms.residuals.reshape(-1)

    return error


def robust_factors(key: int, source: np.ndarray, target: np.ndarray, Ut: np.ndarray,
                   omega: np.ndarray, alpha: float, semantic_weight: str = "outside"
                   ) -> list[gtsam.CustomFactor]:
    """Return one :class:`gtsam.CustomFactor` per correspondence with a GTSAM robust Cauchy model.

    Each factor's error is the whitened residual ``U_k^T r_k`` under
    ``noiseModel.Robust(mEstimator.Cauchy(k), Isotropic.Sigma(3, 1 / sqrt(omega_k)))``, so
    GTSAM itself applies the kernel (eq. (3) and (7)): with k = alpha the loss is
    ``rho_alpha(omega_k e_k)`` (``semantic_weight="inside"``); with k = alpha sqrt(omega_k) it
    is ``omega_k rho_alpha(e_k)`` ("outside", and GICP with omega = 1), since
    ``k^2 log(1 + omega e / k^2) = omega alpha^2 log(1 + e / alpha^2)``. GTSAM's Cauchy weight
    ``1 / (1 + x^2 / k^2)`` of the whitened error x is then exactly the IRLS weight the batched
    factor gets from :meth:`Registration._weights`: one Gauss-Newton step of these factors and
    of :class:`BatchedGicpFactor` is the same step (tested). This is the reference path;
    it costs a Python call per correspondence per linearisation (``--factor-ablation``).
    """
    factors = []
    for k in range(len(source)):
        w = float(omega[k])
        scale = alpha if semantic_weight == "inside" else alpha * np.sqrt(w)
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(scale),
            gtsam.noiseModel.Isotropic.Sigma(3, 1.0 / np.sqrt(w)))
        factors.append(gtsam.CustomFactor(noise, [key], _error_function(
            key, source[k:k + 1], target[k:k + 1], Ut[k:k + 1], np.ones(1))))
    return factors


def solve_weighted(T: np.ndarray, factor: BatchedGicpFactor | list[gtsam.CustomFactor],
                   optimizer: str = "gn", max_iterations: int = 1,
                   key: int | None = None) -> np.ndarray:
    """Return the 4x4 pose minimising the factor(s)' cost, by GTSAM's optimiser.

    ``factor`` is a :class:`BatchedGicpFactor` or a list of factors on ``key``
    (:func:`robust_factors`).
    """
    graph = gtsam.NonlinearFactorGraph()
    if isinstance(factor, BatchedGicpFactor):
        graph.add(factor.factor)
        key = factor.key
    else:
        for f in factor:
            graph.add(f)
    values = gtsam.Values()
    values.insert(key, gtsam.Pose3(T))
    if optimizer == "lm":
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    else:
        params = gtsam.GaussNewtonParams()
        params.setMaxIterations(max_iterations)
        result = gtsam.GaussNewtonOptimizer(graph, values, params).optimize()
    return result.atPose3(key).matrix()
