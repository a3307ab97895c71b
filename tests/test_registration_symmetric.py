"""The symmetric registration (``RegistrationConfig.symmetric``): the midpoint of both directions.

Nearest-neighbour matching is not symmetric, and on real scans the estimate moves when source
and target swap roles (docs/registration_notes.md, "Symmetric registration"). Off a voxel lattice
the target is also registered to the source (one Newton step from the forward solution with
the re-matched bread), the midpoint is reported, and its covariance is the sandwich of the two
stacked estimating equations. These tests check the pieces; the calibration itself is checked
in tests/test_registration_covariance.py and test_registration_model_error.py.
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from test_registration import make_pair

from estimation.covariance import nees
from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig

CONFIG = RegistrationConfig(max_correspondence_distance=0.3, symmetric=True)
ONE_WAY = RegistrationConfig(max_correspondence_distance=0.3, symmetric=False)


def _gap(T_a, T_b) -> np.ndarray:
    return gtsam.Pose3.Logmap(gtsam.Pose3(T_a).between(gtsam.Pose3(T_b)))


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_swapping_the_clouds_gives_the_inverse_pose(seed):
    """The midpoint does not depend on which cloud is called the source (to a small share of
    its covariance: the reverse is one Newton step, not iterated to convergence); one
    direction alone does (measured NEES of the swap 0.006-0.04 against 1.9-4.3)."""
    source, _, target, _, _ = make_pair(seed, 2000, 0.005)
    ab = Registration(source, target, CONFIG).run()
    ba = Registration(target, source, CONFIG).run(np.linalg.inv(ab.T))
    assert ab.converged and ba.converged
    assert ab.diagnostic.symmetric and ba.diagnostic.symmetric
    assert nees(_gap(ab.T, np.linalg.inv(ba.T)), ab.covariance) < 0.1
    ab1 = Registration(source, target, ONE_WAY).run()
    ba1 = Registration(target, source, ONE_WAY).run(np.linalg.inv(ab1.T))
    assert nees(_gap(ab1.T, np.linalg.inv(ba1.T)), ab1.covariance) > 1.0


def test_reverse_step_reaches_the_reverse_registration():
    """The reverse's Newton step with the re-matched bread lands where the reverse
    registration, iterated to convergence, does (well inside its covariance)."""
    source, _, target, _, _ = make_pair(22, 2000, 0.005)
    reg = Registration(source, target, ONE_WAY)
    forward = reg.run()
    T_rev, sol, _ = reg.reverse_terms(forward.T, 0.3, reg.cluster_size(forward.T, None))
    full = Registration(target, source, ONE_WAY).run(np.linalg.inv(forward.T))
    start_gap = nees(_gap(np.linalg.inv(forward.T), full.T), full.covariance)
    step_gap = nees(_gap(T_rev, full.T), full.covariance)
    assert start_gap > 1.0  # the directions really differ ...
    assert step_gap < 0.1 * start_gap  # ... and one step covers most of it
    assert len(sol.scores) > 1000


def test_midpoint_and_its_covariance():
    source, _, target, _, _ = make_pair(24, 2000, 0.01)
    sym = Registration(source, target, CONFIG).run()
    one = Registration(source, target, ONE_WAY).run()
    d = sym.diagnostic
    assert d.symmetric and not one.diagnostic.symmetric
    assert np.isnan(one.diagnostic.direction_gap) and d.direction_gap > 0.0
    # the midpoint sits half-way to the reverse estimate: its distance from the forward
    # pose is a fraction of the forward covariance
    assert 0.0 < nees(_gap(one.T, sym.T), one.covariance) < 6.0
    # two correlated estimates of the same data: the midpoint's covariance is no larger than
    # the forward's in any direction by much, and no smaller than a quarter of it
    ratio = np.linalg.eigvals(np.linalg.solve(one.covariance, sym.covariance)).real
    assert ratio.max() < 1.5 and ratio.min() > 0.25
    np.testing.assert_allclose(sym.covariance, sym.covariance.T)
    assert np.linalg.eigvalsh(sym.covariance).min() > 0.0


def test_voxel_lattice_keeps_one_direction():
    """On a voxel lattice the quantisation term models the map's error: no reverse step."""
    from test_registration_model_error import voxel_map_pair

    source, target, _ = voxel_map_pair(3000, n_source=1500, n_dense=20000)
    cfg = RegistrationConfig(max_correspondence_distance=0.3, symmetric=True)
    sym = Registration(source, target, cfg).run()
    one = Registration(source, target, RegistrationConfig(
        max_correspondence_distance=0.3, symmetric=False)).run()
    assert sym.diagnostic.quantisation_pitch == pytest.approx(0.03)
    assert not sym.diagnostic.symmetric
    np.testing.assert_array_equal(sym.T, one.T)
    np.testing.assert_array_equal(sym.covariance, one.covariance)


def test_bad_symmetric_option_is_rejected():
    with pytest.raises(EstimationError, match="symmetric"):
        RegistrationConfig(symmetric="yes")
    with pytest.raises(EstimationError, match="tilted_planes"):
        RegistrationConfig(tilted_planes=1)


@pytest.mark.parametrize("semantic", [False, True], ids=["gicp", "semantic-icp"])
def test_reverse_on_its_thread_gives_the_same_bits_as_inline(semantic, monkeypatch):
    """The reverse direction runs on a second thread beside this direction's covariance; it
    takes its state (alpha, Semantic-ICP's sigma) before it starts and shares only read-only
    or locked data, so pose, covariance and direction gap are bit-identical to running it on
    the calling thread."""
    from concurrent.futures import Future

    from test_registration import one_hot

    import estimation.registration.gicp as gicp

    source, labels_s, target, labels_t, _ = make_pair(24, 2000, 0.005)
    probs = (one_hot(labels_s, acc=0.9), one_hot(labels_t, acc=0.9)) if semantic else (None,
                                                                                      None)
    threaded = Registration(source, target, CONFIG, *probs).run()

    class Inline:
        def submit(self, fn, *args):
            future = Future()
            future.set_result(fn(*args))
            return future

    monkeypatch.setattr(gicp, "_reverse_executor", lambda: Inline())
    inline = Registration(source, target, CONFIG, *probs).run()
    assert threaded.diagnostic.symmetric and inline.diagnostic.symmetric
    assert np.array_equal(threaded.T, inline.T)
    assert np.array_equal(threaded.covariance, inline.covariance)
    assert threaded.diagnostic.direction_gap == inline.diagnostic.direction_gap


@pytest.mark.parametrize("reach", [0.0, 1e9], ids=["cache-prepared", "covariances-only"])
@pytest.mark.parametrize("semantic", [False, True], ids=["gicp", "semantic-icp"])
def test_prepared_stages_give_the_same_bits(semantic, reach, monkeypatch):
    """The final stage's and the reverse direction's neighbour caches and covariances are
    prepared on the second thread while the iterations before them run, from poses before
    the solution (``PREPARE_STEP``), and so are the source's KD-tree, lattice test and
    radius, and the matched source rows' covariances: the caches are exact from any anchor
    and each row's covariance does not depend on when or where it is computed, so pose,
    covariance and direction gap are bit-identical to a run that prepares nothing. (An
    annealing start off the solution, so that the preparations start from poses that still
    move.) Both where the final stage's cache is prepared and where only its covariances are
    (``PREPARED_REACH``: the cache's reach too short for the motion still to come)."""
    from test_registration import one_hot, random_pose

    import estimation.registration.gicp as gicp

    monkeypatch.setattr(gicp, "PREPARED_REACH", reach)

    source, labels_s, target, labels_t, T_gt = make_pair(25, 3000, 0.005)
    probs = (one_hot(labels_s, acc=0.9), one_hot(labels_t, acc=0.9)) if semantic else (None,
                                                                                      None)
    cfg = RegistrationConfig(max_correspondence_distance=0.3, initial_correspondence_distance=0.8,
                             decay=0.3 / 0.8, coarse_points=1000)
    init = T_gt @ random_pose(np.random.default_rng(5), 0.1, 0.2)
    names = ("_prepare_forward", "_prepare_reverse", "_prepare_source", "_prefetch_source")
    calls = []
    for name in names:
        method = getattr(gicp.Registration, name)
        monkeypatch.setattr(gicp.Registration, name,
                            lambda self, *a, _m=method, _n=name: (calls.append(_n), _m(self, *a)))
    prepared = Registration(source, target, cfg, *probs).run(init)
    assert set(calls) == set(names)
    for name in names:
        monkeypatch.setattr(gicp.Registration, name, lambda self, *a: None)
    plain = Registration(source, target, cfg, *probs).run(init)
    assert prepared.diagnostic.symmetric and plain.diagnostic.symmetric
    assert prepared.iterations == plain.iterations
    assert np.array_equal(prepared.T, plain.T)
    assert np.array_equal(prepared.covariance, plain.covariance)
    assert prepared.diagnostic.direction_gap == plain.diagnostic.direction_gap


def test_reverse_started_before_the_overlap_test_is_stopped_inside_the_target():
    """The reverse direction starts before the overlap test at the solution (its own thread);
    where the source then lies inside the target (a part of the cloud registered to it, no
    voxel grid to tell it earlier) it is stopped and the forward estimate is reported, as
    without the symmetric option."""
    from test_registration import corner_scene, random_pose

    from estimation.registration.gicp import source_inside_target

    rng = np.random.default_rng(26)
    target, _ = corner_scene(rng, 4000)
    target = target + rng.normal(0, 0.005, target.shape)
    part = target[target[:, 0] > np.median(target[:, 0])] + rng.normal(0, 0.005, (2000, 3))
    T_gt = random_pose(rng)
    source = (part - T_gt[:3, 3]) @ T_gt[:3, :3]
    cfg = RegistrationConfig(max_correspondence_distance=0.3, voxel_matching=None)
    sym = Registration(source, target, cfg).run(T_gt)
    one = Registration(source, target, replace(cfg, symmetric=False)).run(T_gt)
    assert sym.converged and not sym.diagnostic.symmetric
    assert source_inside_target(*sym.diagnostic.overlap)
    assert np.array_equal(sym.T, one.T)
    assert np.array_equal(sym.covariance, one.covariance)
