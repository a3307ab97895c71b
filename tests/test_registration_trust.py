"""The consistency flag is down where the estimate itself is not to be trusted.

A run that did not converge, or whose two directions found different solutions (one of them
in another basin), has no covariance worth reporting as trusted, whatever the residual
statistic says. Measured on ICL-NUIM's office against its 3 cm centroid map (the test's room,
every 10th frame; seeds 0-29 from the benchmark's small offsets): seeds 5 and 21 stopped 48 /
25 mm off without converging (at 60 final iterations, with the residual-based kernel while
annealing, before the tenth round; now they converge), seeds 19 and 22 converge 18-26 cm
off in another basin,
where the overlap rule takes the midpoint and the two directions differ by a gap of
337 / 311 (chi-square with 6 dof under the noise alone; `RegistrationConfig.trust_gap`
38.3). Before these two rules all four were flagged trusted.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from test_registration import make_pair

from benchmarks.registration import D_FINAL, OFFSETS, register_ours
from benchmarks.registration_indoor import SOURCE_POINTS, half_room_source
from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig, gicp, pose_error, register
from estimation.registration.metrics import offset_about_centroid


@pytest.fixture(scope="module")
def office(centroid_room):
    return centroid_room("icl", 10)


def benchmark_start(points, labels, seed, n=SOURCE_POINTS, offset="small"):
    """(source, T_gt, initial guess, d0) of the benchmark's trial ``seed``, ``n`` points
    (``offset``: the benchmark's "small" or "wide" start)."""
    rng = np.random.default_rng(seed)
    source, T_gt = half_room_source(points, labels, rng, n)
    metres, degrees, d0 = OFFSETS[offset]
    init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
    return source, T_gt, init, d0


@pytest.mark.parametrize("seed", [19, 22])
def test_two_directions_in_different_basins_are_not_trusted(office, seed):
    points, labels, target = office
    source, T_gt, init, d0 = benchmark_start(points, labels, seed)
    result, _ = register_ours(source, target, init, (d0, D_FINAL))
    # (since the fourteenth round the off-surface share flags both runs too, 0.113 and 0.119:
    # off here)
    off, _ = register_ours(source, target, init, (d0, D_FINAL), trust_gap=math.inf,
                           trust_off_surface=math.inf)
    assert result.converged and pose_error(result.T, T_gt).t_err_m > 0.1  # another basin
    assert result.diagnostic.symmetric and result.diagnostic.direction_gap > 100.0
    # the gap is what flags it: without the rule the same run was trusted
    assert_only_the_rule_flags(result, off)


def assert_only_the_rule_flags(result, without_rule):
    """The run is untrusted, and the same run (same pose) without the rule was trusted."""
    assert not result.diagnostic.trusted
    np.testing.assert_array_equal(without_rule.T, result.T)
    assert without_rule.diagnostic.trusted


@pytest.mark.parametrize("seed", [5, 21])
def test_a_run_that_did_not_converge_is_not_trusted(office, seed):
    # cut after 3 final iterations these starts end unconverged (seed 5 37 mm off); with the
    # default 150 they converge (in 43 / 73 iterations, measured)
    points, labels, target = office
    source, T_gt, init, d0 = benchmark_start(points, labels, seed)
    cut, _ = register_ours(source, target, init, (d0, D_FINAL), max_iterations=3)
    assert not cut.converged
    assert cut.diagnostic is not None and not cut.diagnostic.trusted
    done, _ = register_ours(source, target, init, (d0, D_FINAL))
    assert done.converged and pose_error(done.T, T_gt).t_err_m < 0.005


@pytest.mark.usefixtures("strided_coarse_subset")
@pytest.mark.parametrize("seed", [5, 21])
def test_the_wide_kernel_while_annealing_ends_the_slow_slides(office, seed, monkeypatch):
    # With the residual-based Cauchy alpha from the first annealing stage (before the tenth
    # round) these two starts crawled along the room, the cost falling a little every
    # iteration, and ended 25-48 mm off after 60 final iterations; a dense source (150k
    # points) slid into another basin or ran out of iterations in 3 of 12 starts on the
    # benchmark's room. With cauchy_alpha while annealing they converge within 60. (The
    # final stage's extrapolation also ends these slides, and so does one covariance per
    # centroid for seed 21: both off for the negative control.)
    points, labels, target = office
    source, T_gt, init, d0 = benchmark_start(points, labels, seed)
    done, _ = register_ours(source, target, init, (d0, D_FINAL), max_iterations=60)
    assert done.converged and pose_error(done.T, T_gt).t_err_m < 0.005
    monkeypatch.setattr(gicp, "EXTRAPOLATE", False)
    done, _ = register_ours(source, target, init, (d0, D_FINAL), max_iterations=60)
    assert done.converged and pose_error(done.T, T_gt).t_err_m < 0.005
    update = Registration._update_alpha
    monkeypatch.setattr(Registration, "_update_alpha",
                        lambda self, e, annealing=False: update(self, e, False))
    slid, _ = register_ours(source, target, init, (d0, D_FINAL), max_iterations=60,
                            pooled_source_covariance=False)
    assert not slid.converged and pose_error(slid.T, T_gt).t_err_m > 0.01


def test_an_unconverged_iid_pair_is_not_trusted_and_the_converged_one_is():
    source, _, target, _, _ = make_pair(1000, 2000, 0.01)
    cfg = RegistrationConfig(max_correspondence_distance=0.3)
    done = register(source, target, config=cfg)
    cut = register(source, target, config=RegistrationConfig(
        max_correspondence_distance=0.3, max_iterations=1))
    assert done.converged and done.diagnostic.trusted
    assert not cut.converged and cut.diagnostic is not None and not cut.diagnostic.trusted


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), "38"])
def test_bad_trust_gap_is_refused(value):
    with pytest.raises(EstimationError, match="trust_gap"):
        RegistrationConfig(trust_gap=value)


def test_extrapolation_adds_the_rest_of_a_straight_creep_and_nothing_else():
    """Two steps the same way, the second 0.75 of the first: the rest of the geometric
    series (3 more such steps) is added at once and the next step starts afresh; a turn, a
    longer step or the first step of a stage add nothing; the jump is capped."""
    import gtsam

    from estimation.registration.gicp import EXTRAPOLATE_MAX, _creep_ratio, _extrapolated

    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.1, 0.2, 0.3), [1.0, 2.0, 3.0]).matrix()
    last = np.array([1e-3, 0, 0, 2e-3, 1e-3, 0])

    def stepped(xi):
        return (gtsam.Pose3(T) * gtsam.Pose3.Expmap(xi)).matrix()

    assert _creep_ratio(0.75 * last, last) == pytest.approx(0.75)
    jumped, remembered = _extrapolated(stepped(0.75 * last), 0.75 * last, 0.75)
    np.testing.assert_allclose(jumped, stepped(0.75 * last * 4), atol=1e-12)
    assert remembered is None
    for xi, previous in ((0.75 * last, None), (1.2 * last, last),
                         (np.array([0, 1e-3, 0, -2e-3, 1e-3, 0]), last)):
        assert _creep_ratio(xi, previous) is None
        same, remembered = _extrapolated(stepped(xi), xi, None)
        np.testing.assert_array_equal(same, stepped(xi))
        np.testing.assert_allclose(remembered, xi, atol=1e-15)
    capped, _ = _extrapolated(stepped(0.99 * last), 0.99 * last, _creep_ratio(0.99 * last, last))
    np.testing.assert_allclose(capped, stepped(0.99 * last * (1 + EXTRAPOLATE_MAX)), atol=1e-12)
