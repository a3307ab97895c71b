"""Consistency statistics: NEES, NIS and their chi-square acceptance bounds.

Errors are tangent vectors in GTSAM's order [rotation, translation] when poses are
involved (``T_est.localCoordinates(T_true)`` or ``Logmap``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from .errors import EstimationError


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared e^T P^-1 e for each row of ``errors``.

    ``errors`` is (..., n) and ``covariances`` (..., n, n); NIS is the same formula
    with the innovation and its covariance S.
    """
    errors = np.asarray(errors, dtype=float)
    covariances = np.asarray(covariances, dtype=float)
    n = errors.shape[-1] if errors.ndim else 0
    if errors.ndim == 0 or covariances.shape[-2:] != (n, n) or \
            covariances.shape[:-2] != errors.shape[:-1]:
        raise EstimationError(f"errors (..., n) and covariances (..., n, n) do not match: "
                              f"shapes {errors.shape} and {covariances.shape}")
    try:
        solved = np.linalg.solve(covariances, errors[..., None])[..., 0]
    except np.linalg.LinAlgError:
        raise EstimationError("a covariance is singular (NEES undefined)") from None
    return np.einsum("...i,...i->...", errors, solved)


nis = nees


def chi2_bounds(dof: int, n_runs: int = 1, alpha: float = 0.05) -> tuple[float, float]:
    """Two-sided (1 - alpha) bounds for the mean of ``n_runs`` NEES values of ``dof`` each.

    n_runs * mean(NEES) ~ chi2(n_runs * dof) for a consistent estimator
    (Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking", 5.4.2).
    """
    total = dof * n_runs
    lower = stats.chi2.ppf(alpha / 2, total) / n_runs
    upper = stats.chi2.ppf(1 - alpha / 2, total) / n_runs
    return float(lower), float(upper)


@dataclass(frozen=True)
class ConsistencyCheck:
    """The outcome of a NEES/NIS check over Monte Carlo runs."""

    mean: float            # mean NEES over every run (and step)
    lower: float           # two-sided chi-square bounds for that mean
    upper: float
    fraction_inside: float  # share of steps whose across-run mean lies inside its bounds
    passed: bool


def check_consistency(values: np.ndarray, dof: int, alpha: float = 0.05,
                      min_fraction: float = 0.9) -> ConsistencyCheck:
    """Check NEES (or NIS) values of shape (n_runs,) or (n_runs, n_steps) against chi-square.

    For (n_runs, n_steps), each step's mean over runs is tested against its bounds and the
    check passes when at least ``min_fraction`` of the steps are inside; for a single step
    the mean itself must be inside.
    """
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    n_runs = values.shape[0]
    lower, upper = chi2_bounds(dof, n_runs, alpha)
    step_means = values.mean(axis=0)
    inside = (step_means >= lower) & (step_means <= upper)
    fraction = float(inside.mean())
    passed = fraction >= min_fraction if values.shape[1] > 1 else bool(inside[0])
    return ConsistencyCheck(float(values.mean()), lower, upper, fraction, passed)


@dataclass(frozen=True)
class CommonErrorSplit:
    """The NEES of runs that share an error source, split into the error common to every run
    and the runs' variation about it (:func:`nees_about_common`).

    Attributes
    ----------
    common : (n,) the runs' mean error
    standard_error : (n,) its standard error (the runs' spread over sqrt(N))
    mean : mean NEES of the errors
    common_part : mean over the runs of common^T P_i^-1 common
    about_common : N / (N - 1) times the mean of (e_i - common)^T P_i^-1 (e_i - common), the
        variation's NEES (unbiased for its expectation; without the factor the two parts add
        up to ``mean`` where the covariances are alike)
    """

    common: np.ndarray
    standard_error: np.ndarray
    mean: float
    common_part: float
    about_common: float


def nees_about_common(errors: np.ndarray, covariances: np.ndarray) -> CommonErrorSplit:
    """Split the mean NEES of ``errors`` (N, n) against ``covariances`` (N, n, n) into the
    runs' common error and their variation about it.

    Runs that share a fixed error source, such as one map that every registration of a
    benchmark cell uses or one scan that every split re-samples, share its error: their mean
    NEES is then in large part ONE draw of that error, not N, and the chi-square bounds of N
    independent runs (:func:`chi2_bounds`) do not apply to it. The variation about the common
    error is what N runs do measure. The errors must be expressed in one frame (for a
    registration, the map's: ``T_gt.AdjointMap() @ tangent``), and N >= 2.
    """
    errors = np.asarray(errors, dtype=float)
    covariances = np.asarray(covariances, dtype=float)
    if errors.ndim != 2 or len(errors) < 2:
        raise EstimationError(f"errors must be (N, n) with N >= 2, got shape {errors.shape}")
    n_runs = len(errors)
    common = errors.mean(axis=0)
    centred = errors - common
    return CommonErrorSplit(
        common=common,
        standard_error=errors.std(axis=0, ddof=1) / np.sqrt(n_runs),
        mean=float(nees(errors, covariances).mean()),
        common_part=float(nees(np.broadcast_to(common, errors.shape), covariances).mean()),
        about_common=float(nees(centred, covariances).mean() * n_runs / (n_runs - 1)))


def crossed_bootstrap_interval(values: np.ndarray, level: float = 0.95, draws: int = 4000,
                               seed: int = 0) -> tuple[float, float]:
    """Percentile interval of the mean of ``values`` (R, C), a crossed design whose rows and
    columns each share an error source, with rows and columns resampled independently
    (Owen's pigeonhole bootstrap, "The pigeonhole bootstrap", Ann. Appl. Stat. 1(2), 2007;
    slightly conservative: it counts the row-column interaction twice).

    A registration benchmark run against several maps is such a design: the runs against
    one map share its grid phase's draw of the map's error, the runs of one trial its half,
    noise, labels and start. Their mean NEES is then a mean over few independent draws, and
    the chi-square bounds of R * C independent runs (:func:`chi2_bounds`) are far too narrow
    for it. NaN marks a run left out (not converged, another basin); means over the cells
    present. The draws are seeded: the same values give the same interval.
    """
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or values.size < 2:
        raise EstimationError(f"values must be (rows, columns) with at least two runs, got "
                              f"shape {values.shape}")
    if not 0.0 < level < 1.0:
        raise EstimationError(f"level must be in (0, 1), got {level!r}")
    present = np.isfinite(values)
    if not present.any():
        raise EstimationError("values hold no finite run")
    rng = np.random.default_rng(seed)
    n_rows, n_cols = values.shape
    # how often each row and column is drawn, per bootstrap draw
    row_counts = _draw_counts(rng.integers(0, n_rows, (draws, n_rows)), n_rows)
    col_counts = _draw_counts(rng.integers(0, n_cols, (draws, n_cols)), n_cols)
    sums = np.einsum("dr,rc,dc->d", row_counts, np.where(present, values, 0.0), col_counts)
    counts = np.einsum("dr,rc,dc->d", row_counts, present.astype(float), col_counts)
    means = sums[counts > 0] / counts[counts > 0]
    tail = 50.0 * (1.0 - level)
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return float(low), float(high)


def _draw_counts(picks: np.ndarray, n: int) -> np.ndarray:
    """Return (draws, n) how often each of n items occurs in each row of ``picks`` (one
    bincount over every draw at once, each draw's items offset by n)."""
    offsets = n * np.arange(len(picks))[:, None]
    return np.bincount((picks + offsets).ravel(), minlength=n * len(picks)).reshape(-1, n)
