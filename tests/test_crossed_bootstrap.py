"""``crossed_bootstrap_interval``: the interval of a mean NEES over runs that share their map's
grid phase and their trial's half (benchmarks/registration_indoor.py ``--map-phases``;
docs/registration_notes.md, "How many draws a cell holds").
"""
from __future__ import annotations

import numpy as np
import pytest

from estimation.covariance import chi2_bounds, crossed_bootstrap_interval
from estimation.errors import EstimationError

DOF = 6


def crossed_nees(rng, maps, trials, shares=(0.3, 0.4, 0.3), scale=1.0):
    """NEES of errors e = a_map + b_trial + c_run, N(0, share I) each, against the covariance
    I (calibrated at scale 1; ``scale`` times the NEES of a covariance ``scale`` too small)."""
    a = rng.normal(size=(maps, 1, DOF)) * np.sqrt(shares[0])
    b = rng.normal(size=(1, trials, DOF)) * np.sqrt(shares[1])
    c = rng.normal(size=(maps, trials, DOF)) * np.sqrt(shares[2])
    return scale * ((a + b + c) ** 2).sum(axis=-1)


def coverage(rng, cells, **kwargs):
    """Share of ``cells`` simulated cells whose crossed interval holds 6, and whose mean lies
    inside the chi-square band of as many independent runs."""
    crossed = independent = 0
    for _ in range(cells):
        values = crossed_nees(rng, **kwargs)
        low, high = crossed_bootstrap_interval(values, draws=1000)
        crossed += low <= DOF <= high
        low, high = chi2_bounds(DOF, values.size)
        independent += low <= values.mean() <= high
    return crossed / cells, independent / cells


def test_the_interval_holds_a_calibrated_crossed_cell_where_the_chi_square_band_does_not():
    """10 maps x 6 trials whose runs share a map's and a trial's draw: the crossed interval
    holds the expected NEES nearly always, the band of 60 independent runs much less often."""
    crossed, independent = coverage(np.random.default_rng(0), 120, maps=10, trials=6)
    assert crossed >= 0.93
    assert independent <= crossed - 0.1


def test_a_covariance_twice_too_small_is_outside():
    """The negative control: the same design, every covariance half the truth (NEES x2)."""
    crossed, _ = coverage(np.random.default_rng(1), 60, maps=3, trials=20, scale=2.0)
    assert crossed <= 0.05
    crossed, _ = coverage(np.random.default_rng(2), 60, maps=10, trials=6, scale=0.5)
    assert crossed <= 0.05  # and a covariance twice too large


def test_independent_runs_are_covered_too():
    crossed, independent = coverage(np.random.default_rng(3), 60, maps=10, trials=6,
                                    shares=(0.0, 0.0, 1.0))
    assert crossed >= 0.93 and independent >= 0.9


def test_a_missing_run_is_left_out_and_the_draws_are_seeded():
    values = crossed_nees(np.random.default_rng(4), 4, 5)
    holed = values.copy()
    holed[1, 2] = np.nan
    low, high = crossed_bootstrap_interval(holed)
    assert np.isfinite([low, high]).all() and low < np.nanmean(holed) < high
    assert crossed_bootstrap_interval(holed) == (low, high)
    assert crossed_bootstrap_interval(holed, seed=1) != (low, high)
    # one map: the trials alone are resampled
    low, high = crossed_bootstrap_interval(values[:1])
    assert low < values[0].mean() < high


@pytest.mark.parametrize("values", [np.ones(6), np.ones((1, 1)), np.full((2, 3), np.nan)])
def test_bad_input_is_refused(values):
    with pytest.raises(EstimationError):
        crossed_bootstrap_interval(values)
    with pytest.raises(EstimationError):
        crossed_bootstrap_interval(np.ones((2, 3)), level=1.0)
