"""``nees_about_common``: the mean NEES of runs that share an error, split into the common
error and the runs' variation about it (benchmarks/registration_indoor.py and
registration_real.py print it; docs/registration_notes.md, "One map, one draw of its error").
"""
from __future__ import annotations

import numpy as np
import pytest

from estimation.covariance import chi2_bounds, nees, nees_about_common
from estimation.errors import EstimationError

DOF = 6


def shared_runs(rng, n_runs, common_scale, noise_scale=1.0):
    """Runs whose errors share one draw c ~ N(0, common_scale^2 I) and vary by
    d_i ~ N(0, noise_scale^2 I); every run reports the population's covariance."""
    common = rng.normal(scale=common_scale, size=DOF)
    errors = common + rng.normal(scale=noise_scale, size=(n_runs, DOF))
    covariance = (common_scale ** 2 + noise_scale ** 2) * np.eye(DOF)
    return errors, np.broadcast_to(covariance, (n_runs, DOF, DOF))


def test_the_parts_add_up_to_the_mean_where_the_covariances_are_alike():
    rng = np.random.default_rng(0)
    errors, covs = shared_runs(rng, 12, 1.0)
    split = nees_about_common(errors, covs)
    n = len(errors)
    assert split.mean == pytest.approx(nees(errors, covs).mean())
    assert split.common_part + split.about_common * (n - 1) / n == pytest.approx(split.mean)
    np.testing.assert_allclose(split.common, errors.mean(axis=0))
    np.testing.assert_allclose(split.standard_error, errors.std(axis=0, ddof=1) / np.sqrt(n))


def test_the_variation_about_the_common_error_is_unbiased():
    """Over many cells, the variation's NEES averages tr(P^-1 D) (here 6 / 2: half of each
    run's variance is the common draw), whatever the common draw was."""
    rng = np.random.default_rng(1)
    about = [nees_about_common(*shared_runs(rng, 8, 1.0)).about_common for _ in range(400)]
    assert np.mean(about) == pytest.approx(DOF / 2, rel=0.05)
    # without the N / (N - 1) correction it would read 7/8 of that
    assert abs(np.mean(about) * 7 / 8 - DOF / 2) > 0.25


def test_a_cells_mean_nees_is_one_draw_of_the_common_error():
    """Runs that share half their error variance: a cell's mean NEES, calibrated over the
    population (it averages 6), falls outside the bounds of N independent runs far more
    often than 5 %, because its common part is one draw; runs with no common error stay
    inside them about 95 % of the time."""
    rng = np.random.default_rng(2)
    n_runs = 20
    lower, upper = chi2_bounds(DOF, n_runs)
    cells = [nees_about_common(*shared_runs(rng, n_runs, 1.0)) for _ in range(300)]
    means = np.array([c.mean for c in cells])
    assert np.mean(means) == pytest.approx(DOF, rel=0.1)
    outside = np.mean((means < lower) | (means > upper))
    assert outside > 0.4
    # with no common error the same bounds hold (the negative control of the above)
    independent = [nees_about_common(*shared_runs(rng, n_runs, 0.0)).mean for _ in range(300)]
    assert np.mean((np.array(independent) < lower) | (np.array(independent) > upper)) < 0.1


@pytest.mark.parametrize("shape", [(1, 6), (6,), (2, 3, 6)])
def test_too_few_runs_or_a_bad_shape_is_refused(shape):
    with pytest.raises(EstimationError, match="N >= 2"):
        nees_about_common(np.zeros(shape), np.broadcast_to(np.eye(6), shape[:-1] + (6, 6)))
