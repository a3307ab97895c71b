"""GICP-SE(3) and Semantic-ICP: Jacobians, whitening, recovery, bad input, PoseGraph use."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial import cKDTree

from estimation.errors import EstimationError
from estimation.registration import (
    UNCONSTRAINED_VARIANCE,
    BatchedGicpFactor,
    Registration,
    RegistrationConfig,
    SemanticIndex,
    gicp_terms,
    point_covariances,
    pose_error,
    register,
    semantic_correspondences,
    semantic_icp,
    whitening,
)
from estimation.registration.factors import (
    cauchy_loss,
    cauchy_weight,
    gauss_newton_step,
    normal_equations,
    solve_weighted,
)


def corner_scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points on a floor, two walls and a box, with a class per surface (4 classes)."""
    k = n // 4
    floor = np.c_[rng.uniform(0, 4, k), rng.uniform(0, 4, k), np.zeros(k)]
    wall_x = np.c_[np.zeros(k), rng.uniform(0, 4, k), rng.uniform(0, 2.5, k)]
    wall_y = np.c_[rng.uniform(0, 4, k), np.zeros(k), rng.uniform(0, 2.5, k)]
    u = rng.uniform(0, 1, (k, 3))
    face = rng.integers(0, 3, k)
    u[np.arange(k), face] = rng.integers(0, 2, k)
    box = u * [1.0, 0.6, 0.8] + [2.0, 2.0, 0.0]
    labels = np.repeat([0, 1, 1, 2], k)
    labels[3 * k:][box[:, 2] < 1e-9] = 0  # the box's bottom face lies on the floor
    return np.vstack([floor, wall_x, wall_y, box]), labels


def random_pose(rng, sigma_rot=0.05, sigma_t=0.1) -> np.ndarray:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, sigma_rot, 3)),
                       rng.normal(0, sigma_t, 3)).matrix()


def make_pair(seed: int, n: int = 2000, sigma: float = 0.005):
    rng = np.random.default_rng(seed)
    target, labels_t = corner_scene(rng, n)
    target = target + rng.normal(0, sigma, target.shape)
    T_gt = random_pose(rng)
    source_world, labels_s = corner_scene(rng, n)
    source_world = source_world + rng.normal(0, sigma, source_world.shape)
    source = (source_world - T_gt[:3, 3]) @ T_gt[:3, :3]
    return source, labels_s, target, labels_t, T_gt


def one_hot(labels, c=4, acc=1.0):
    probs = np.full((len(labels), c), (1 - acc) / (c - 1))
    probs[np.arange(len(labels)), labels] = acc
    return probs


# -- building blocks -------------------------------------------------------------------------
def test_jacobians_match_numerical_derivatives(rng):
    m = 7
    source = rng.normal(size=(m, 3))
    target = rng.normal(size=(m, 3))
    covs = np.array([point_covariances(rng.normal(size=(30, 3)) * [1, 1, 0.01], 10)[0]
                     for _ in range(2 * m)])
    T = random_pose(rng, 0.5, 1.0)
    Ut = whitening(covs[:m], covs[m:], T[:3, :3])
    terms = gicp_terms(T, source, target, Ut)
    h = 1e-6
    numerical = np.zeros((m, 3, 6))
    pose = gtsam.Pose3(T)
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        plus = gicp_terms(pose.retract(d).matrix(), source, target, Ut, jacobians=False)
        minus = gicp_terms(pose.retract(-d).matrix(), source, target, Ut, jacobians=False)
        numerical[:, :, i] = (plus.residuals - minus.residuals) / (2 * h)
    np.testing.assert_allclose(terms.jacobians, numerical, atol=1e-6, rtol=1e-5)


def test_whitening_is_cholesky_of_information(rng):
    A = rng.normal(size=(50, 3, 3))
    cov_t = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    B = rng.normal(size=(50, 3, 3))
    cov_s = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    Ut = whitening(cov_t, cov_s, R)
    info = np.linalg.inv(cov_t + R @ cov_s @ R.T)
    np.testing.assert_allclose(np.swapaxes(Ut, 1, 2) @ Ut, info, rtol=1e-8, atol=1e-10)
    assert np.allclose(np.tril(Ut, -1), 0)  # U^T is upper triangular


def test_point_covariances_are_plane_like(rng):
    plane = np.c_[rng.uniform(0, 1, (400, 2)), np.zeros(400)]
    covs = point_covariances(plane, k=15, epsilon=1e-3)
    eig = np.linalg.eigvalsh(covs)
    np.testing.assert_allclose(eig, np.broadcast_to([1e-3, 1, 1], eig.shape), atol=1e-9)
    normals = np.linalg.eigh(covs)[1][:, :, 0]
    np.testing.assert_allclose(np.abs(normals[:, 2]), 1.0, atol=1e-9)


def test_closed_form_regularisation_matches_eigh(rng):
    from estimation.registration._kernels import regularise_covariances

    A = rng.normal(size=(500, 3, 3)) * rng.uniform(0.01, 3, (500, 1, 3))
    cov = A @ np.swapaxes(A, 1, 2)
    normals = np.linalg.eigh(cov)[1][:, :, 0]
    expected = np.eye(3) - (1 - 1e-3) * normals[:, :, None] * normals[:, None, :]
    np.testing.assert_allclose(regularise_covariances(cov, 1e-3), expected, atol=1e-8)


@pytest.mark.parametrize("d_max", [0.02, 0.05, 0.3])
def test_neighbour_cache_is_exact(rng, d_max):
    from scipy.spatial import cKDTree

    from estimation.registration.correspondences import NeighbourCache

    target = rng.uniform(0, 1, (3000, 3))
    tree = cKDTree(target)
    cache = NeighbourCache(tree, d_max, 8)
    # some points far outside the target: "nothing within d_max" must be cached exactly too
    points = np.vstack([rng.uniform(0, 1, (500, 3)), rng.uniform(1.2, 2, (50, 3))])
    for step in (0.0, 1e-3, 1e-2, 0.05, 0.3, 1e-4):  # small motions use the cache
        points = points + rng.normal(0, step, points.shape)
        dist, idx = cache.query(points)
        ref_dist, ref_idx = tree.query(points, distance_upper_bound=d_max)
        found = np.isfinite(ref_dist)
        np.testing.assert_array_equal(np.isfinite(dist), found)
        np.testing.assert_allclose(dist[found], ref_dist[found], rtol=1e-12)
        np.testing.assert_array_equal(idx[found], ref_idx[found])


@pytest.mark.parametrize("d_max", [0.03, 0.3])
def test_class_neighbour_cache_is_exact(rng, d_max):
    """One cache over every class: each row's nearest target point of its own class, as its
    class's tree says, through small and large motions; a class with one target point (all
    its points are candidates) and a class without any (never a candidate) included."""
    from estimation.registration.correspondences import ClassNeighbourCache

    c = 6
    target = rng.uniform(0, 1, (2000, 3))
    labels = rng.integers(0, 4, 2000)
    labels[7] = 4  # class 4: one point; class 5: none
    index = SemanticIndex(target, np.eye(c)[labels])
    classes = rng.integers(0, c, 600)
    cache = ClassNeighbourCache(index, d_max, classes)
    points = np.vstack([rng.uniform(0, 1, (550, 3)), rng.uniform(1.2, 2, (50, 3))])
    for step in (0.0, 1e-3, 1e-2, 0.05, 0.3, 1e-4):
        points = points + rng.normal(0, step, points.shape)
        dist, idx = cache.query(points)
        for k in range(c):
            rows = np.flatnonzero(classes == k)
            if k not in index.trees:
                assert np.all(np.isinf(dist[rows])) and np.all(idx[rows] == -1)
                continue
            ref_dist, ref_j = index.trees[k].query(points[rows], distance_upper_bound=d_max)
            found = np.isfinite(ref_dist)
            np.testing.assert_array_equal(np.isfinite(dist[rows]), found)
            np.testing.assert_allclose(dist[rows][found], ref_dist[found], rtol=1e-12)
            np.testing.assert_array_equal(idx[rows][found], index.members[k][ref_j[found]])
            assert np.all(idx[rows][~found] == -1)


def test_neighbour_cache_queries_by_rows_are_exact(rng):
    """A cache over the source's rows answers queries of some rows (strided, coarse) and of
    all of them in turn, each row keeping its own anchor, exactly as the tree."""
    from estimation.registration.correspondences import NeighbourCache

    target = rng.uniform(0, 1, (3000, 3))
    tree = cKDTree(target)
    cache = NeighbourCache(tree, 0.05, 8, 800)
    points = rng.uniform(0, 1, (800, 3))
    subsets = (np.arange(0, 800, 7), None, rng.permutation(800)[:300], None,
               np.arange(0, 800, 3))
    for step, rows in zip((0.0, 1e-3, 1e-2, 1e-4, 0.05), subsets):
        points = points + rng.normal(0, step, points.shape)
        query = points if rows is None else points[rows]
        dist, idx = cache.query(query, rows)
        ref_dist, ref_idx = tree.query(query, distance_upper_bound=0.05)
        found = np.isfinite(ref_dist)
        np.testing.assert_array_equal(np.isfinite(dist), found)
        np.testing.assert_allclose(dist[found], ref_dist[found], rtol=1e-12)
        np.testing.assert_array_equal(idx[found], ref_idx[found])
    # rows beyond the size given make room for themselves
    dist, idx = cache.query(rng.uniform(0, 1, (2, 3)), np.array([5, 900]))
    assert cache.size == 901 and len(dist) == 2


@pytest.mark.parametrize("d_max", [0.03, 0.3])
def test_class_neighbours_from_the_geometric_cache_are_exact(rng, d_max):
    """The geometric cache's candidates answer class queries where they decide them (most
    rows: a point's neighbours are mostly of its class), the same as the class's tree;
    Semantic-ICP's E-step gives the same pairs and weights with them as without."""
    from estimation.registration.correspondences import NeighbourCache

    c = 4
    target = rng.uniform(0, 1, (4000, 3))
    labels = (target[:, 0] > 0.5).astype(np.int64) + 2 * (target[:, 1] > 0.5)
    index = SemanticIndex(target, np.eye(c)[labels])
    geometric = NeighbourCache(cKDTree(target), d_max, 8, 900)
    points = rng.uniform(0, 1, (900, 3))
    want = (points[:, 0] > 0.5).astype(np.int64) + 2 * (points[:, 1] > 0.5)
    want[::10] = rng.integers(0, c, 90)  # wrong labels: their class lies further away
    probs = np.eye(c)[want]
    caches_with, caches_without = {}, {}
    resolved = []
    for step in (0.0, 1e-3, 1e-2, 1e-4):
        points = points + rng.normal(0, step, points.shape)
        both = geometric.query_with_class(points, None, index.labels, want)
        nearest = geometric.query(points)
        dist, idx, unresolved = geometric.nearest_of_class(points, np.arange(900),
                                                           index.labels, want)
        for a, b in zip(both, (*nearest, dist, idx, unresolved)):  # one scan, the same
            np.testing.assert_array_equal(a, b)
        resolved.append(1.0 - unresolved.mean())
        for k in range(c):
            rows = np.flatnonzero((want == k) & ~unresolved)
            ref_dist, ref_j = index.trees[k].query(points[rows], distance_upper_bound=d_max)
            found = np.isfinite(ref_dist)
            np.testing.assert_array_equal(np.isfinite(dist[rows]), found)
            np.testing.assert_allclose(dist[rows][found], ref_dist[found], rtol=1e-12)
            np.testing.assert_array_equal(idx[rows][found], index.members[k][ref_j[found]])
        nearest = geometric.query(points)
        kwargs = dict(residual_sigma=0.01, nearest=nearest, posterior=True, label_noise=0.1)
        fast = semantic_correspondences(points, probs, index, d_max, caches=caches_with,
                                        geometric=geometric, **kwargs)
        plain = semantic_correspondences(points, probs, index, d_max, caches=caches_without,
                                         **kwargs)
        for name in ("source_idx", "target_idx"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(plain, name))
        np.testing.assert_allclose(fast.weights, plain.weights, rtol=1e-12)
    assert min(resolved) > 0.6


@pytest.mark.parametrize("posterior", [True, False])
def test_cached_class_candidates_equal_the_class_trees(rng, posterior):
    """Semantic-ICP's class candidates from the class caches (one kernel pass per rank,
    stale rows queried again) are the class trees' answers: two ranks of soft labels, some
    rows asked, the first rank's answer from the geometric scan (posterior E-step) or none
    (the annealing's scores), rows whose most probable class changes, small and large
    motions. The same pairs and weights as without caches, call after call."""
    from estimation.registration.correspondences import NeighbourCache, top_class_order

    c, d_max = 5, 0.08
    target = rng.uniform(0, 1, (4000, 3))
    labels = (target[:, 0] > 0.5).astype(np.int64) + 2 * (target[:, 1] > 0.5)
    labels[:40] = 4  # a rare class
    index = SemanticIndex(target, np.eye(c)[labels])
    n = 1000
    points = rng.uniform(0, 1, (n, 3))
    probs = rng.dirichlet(np.full(c, 0.3), n)  # soft: a second class above 0.1 for many
    geometric = NeighbourCache(cKDTree(target), d_max, 8, n)
    caches: dict = {}
    second = []
    for step, rows in ((0.0, None), (1e-3, None), (1e-2, np.arange(0, n, 3)), (0.05, None),
                       (1e-4, rng.permutation(n)[:400]), (1e-4, None)):
        points = points + rng.normal(0, step, points.shape)
        if step == 0.05:  # labels change: rows asked for another class than cached
            probs = probs[rng.permutation(n)]
        moved, p = (points, probs) if rows is None else (points[rows], probs[rows])
        order = top_class_order(p, 2)
        second.append(np.mean(p[np.arange(len(p)), order[:, 1]] >= 0.1))
        kwargs = dict(residual_sigma=0.02, posterior=posterior, order=order, rows=rows)
        first = nearest = None
        if posterior:
            dist, j, *first = geometric.query_with_class(moved, rows, index.labels,
                                                         np.ascontiguousarray(order[:, 0]))
            nearest = dist, j
        cached = semantic_correspondences(
            moved, p, index, d_max, nearest=nearest, caches=caches,
            geometric=geometric if posterior else None,
            first_class=None if first is None else tuple(first), **kwargs)
        plain = semantic_correspondences(moved, p, index, d_max, nearest=nearest, **kwargs)
        for name in ("source_idx", "target_idx", "weights", "distances"):
            np.testing.assert_array_equal(getattr(cached, name), getattr(plain, name))
    assert min(second) > 0.3  # the second rank was searched


def test_lazy_covariances_equal_the_full_computation(rng):
    from scipy.spatial import cKDTree

    from estimation.registration.correspondences import LazyCovariances

    points = rng.normal(size=(800, 3)) * [1.0, 1.0, 0.05]
    full = point_covariances(points, 12, 1e-3)
    lazy = LazyCovariances(points, cKDTree(points), 12, 1e-3)
    rows = rng.integers(0, 800, 300)  # repeated rows, any order
    np.testing.assert_allclose(lazy[rows], full[rows], atol=1e-12)
    assert lazy.done.sum() == len(np.unique(rows))
    np.testing.assert_allclose(lazy.all(), full, atol=1e-12)


def test_kd_tree_answers_as_the_median_split_tree(rng, shared_data):
    """kd_tree (sliding-midpoint splits, built faster) gives every k-NN query the answer of
    scipy's default median-split tree: on a real laser scan, a plane, and repeated points."""
    from benchmarks.registration_indoor import scan_room
    from estimation.registration.correspondences import kd_tree

    scan = scan_room(shared_data / "octomap" / "scan.dat.bz2")[0][::4]
    plane = np.c_[rng.uniform(0, 2, (3000, 2)), np.zeros(3000)]
    repeated = np.repeat(rng.normal(size=(300, 3)), 7, axis=0)
    for points in (scan, plane, repeated):
        query = points[::3] + rng.normal(scale=0.02, size=points[::3].shape)
        for k, bound in ((1, 0.05), (8, 0.4), (20, np.inf)):
            d_new, i_new = kd_tree(points).query(query, k=k, distance_upper_bound=bound)
            d_ref, i_ref = cKDTree(points).query(query, k=k, distance_upper_bound=bound)
            np.testing.assert_array_equal(d_new, d_ref)
            # (equidistant neighbours may come in either order: repeated points)
            same = (i_new == i_ref) | np.isclose(
                np.linalg.norm(points[np.minimum(i_new, len(points) - 1)] - points[
                    np.minimum(i_ref, len(points) - 1)], axis=-1), 0.0)
            assert same.all()


def test_candidate_cache_and_coarse_subset_keep_the_answer():
    source, _, target, _, T_gt = make_pair(8, 6000)
    init = T_gt @ random_pose(np.random.default_rng(3), 0.1, 0.3)
    plain = RegistrationConfig(max_correspondence_distance=0.2, initial_correspondence_distance=0.8,
                               cached_neighbours=0, coarse_points=None)
    results = {}
    for name, changes in (("plain", {}), ("cache", {"cached_neighbours": 8}),
                          ("coarse", {"coarse_points": 1000})):
        cfg = RegistrationConfig(**{**plain.__dict__, **changes})
        results[name] = register(source, target, init, cfg)
        assert results[name].converged, results[name].reason
    # the cache is exact (its distances are the KD-tree's to the bit): the same
    # correspondences, hence the same iterates, in the annealing iterations that use it
    # (CACHE_STEP) as in the final ones
    np.testing.assert_array_equal(results["cache"].T, results["plain"].T)
    np.testing.assert_array_equal(results["cache"].covariance, results["plain"].covariance)
    assert results["cache"].iterations == results["plain"].iterations
    # the coarse subset only changes the path to the same fixed point
    gap = pose_error(results["coarse"].T, results["plain"].T)
    assert gap.t_err_m < 1e-3 and gap.r_err_rad < 1e-3


@pytest.mark.parametrize("anneal", ["iteration", "convergence"])
def test_both_anneal_schedules_recover_the_transform(anneal):
    source, _, target, _, T_gt = make_pair(9, 3000)
    init = T_gt @ random_pose(np.random.default_rng(4), 0.1, 0.3)
    result = register(source, target, init, RegistrationConfig(
        max_correspondence_distance=0.2, initial_correspondence_distance=1.0, anneal=anneal))
    assert result.converged, result.reason
    err = pose_error(result.T, T_gt)
    assert err.t_err_m < 5e-3 and err.r_err_rad < 2e-3



def test_annealing_stages_do_not_starve_the_final_stage():
    # five stages (1.0 m -> 0.2 m, decay 0.7): max_iterations bounds the final stage only, so
    # the stage whose convergence is tested always gets its budget
    source, _, target, _, T_gt = make_pair(11, 3000)
    init = T_gt @ random_pose(np.random.default_rng(5), 0.2, 0.2)
    cfg = RegistrationConfig(max_correspondence_distance=0.2, initial_correspondence_distance=1.0,
                             decay=0.7, anneal="convergence", max_iterations=4, tolerance=1e-3)
    result = register(source, target, init, cfg)
    assert result.converged, result.reason
    assert result.iterations > cfg.max_iterations  # the annealing stages came on top
    assert result.iterations == len(result.cost_log)
    # an unreachable final distance (decay 1) still stops: max_iterations plus nothing
    stuck = register(source, target, init, RegistrationConfig(
        max_correspondence_distance=0.2, initial_correspondence_distance=1.0, decay=1.0,
        max_iterations=5))
    assert not stuck.converged and stuck.iterations == 5 and stuck.reason == "max iterations"

def test_bad_anneal_settings_are_rejected():
    with pytest.raises(EstimationError, match="anneal"):
        RegistrationConfig(anneal="sometimes")
    with pytest.raises(EstimationError, match="decay"):
        RegistrationConfig(decay=0.0)


def test_batched_factor_is_freed(rng):
    # the CustomFactor callback must not reference its Python owner: such a cycle runs
    # through C++, the garbage collector cannot break it, and every factor leaked
    import gc
    import weakref

    n = 50
    Ut = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    factor = BatchedGicpFactor(gtsam.symbol("t", 0), rng.normal(size=(n, 3)),
                               rng.normal(size=(n, 3)), Ut, np.ones(n))
    alive = weakref.ref(factor.Ut)
    del factor, Ut
    gc.collect()
    assert alive() is None


def test_cauchy_weight_is_derivative_of_loss():
    e = np.linspace(0, 50, 11)
    h = 1e-6
    numeric = (cauchy_loss(e + h, 2.0) - cauchy_loss(e - np.minimum(h, e), 2.0)) / \
        (h + np.minimum(h, e))
    np.testing.assert_allclose(cauchy_weight(e, 2.0), numeric, rtol=1e-5)


def test_batched_factor_linearises_to_stacked_terms(rng):
    source, _, target, _, T_gt = make_pair(3, 400)
    reg = Registration(source, target, RegistrationConfig())
    corr = reg.correspondences(T_gt, 0.3)
    src, tgt = source[corr.source_idx], target[corr.target_idx]
    Ut = whitening(reg.target_cov[corr.target_idx], reg.source_cov[corr.source_idx],
                   T_gt[:3, :3])
    weights = rng.uniform(0.2, 1.0, len(src))
    factor = BatchedGicpFactor(gtsam.symbol("t", 0), src, tgt, Ut, weights)
    values = gtsam.Values()
    values.insert(factor.key, gtsam.Pose3(T_gt))
    terms = gicp_terms(T_gt, src, tgt, Ut)
    expected = 0.5 * np.sum(weights * terms.mahalanobis)
    assert factor.factor.error(values) == pytest.approx(expected, rel=1e-9)
    jac = factor.factor.linearize(values)
    A, b = jac.jacobian()
    # GTSAM stores -residual as b; compare A^T A with the weighted Gauss-Newton information
    H = np.einsum("m,mji,mjk->ik", weights, terms.jacobians, terms.jacobians)
    np.testing.assert_allclose(A.T @ A, H, rtol=1e-8, atol=1e-8)
    # one GTSAM Gauss-Newton step from a perturbed pose lowers the weighted cost
    start = T_gt @ random_pose(rng, 0.01, 0.02)
    values.update(factor.key, gtsam.Pose3(start))
    before = factor.factor.error(values)
    values.update(factor.key, gtsam.Pose3(solve_weighted(start, factor, "gn", 1)))
    assert factor.factor.error(values) < before


def test_one_step_from_the_normal_equations_is_gtsams_gauss_newton_step(rng):
    # the registration's inner step (fused normal equations solved by GTSAM) against
    # GaussNewtonOptimizer on the batched factor, and the stacked Jacobians' J^T W J, J^T W r
    source, _, target, _, T_gt = make_pair(4, 400)
    reg = Registration(source, target, RegistrationConfig())
    corr = reg.correspondences(T_gt, 0.3)
    start = T_gt @ random_pose(rng, 0.01, 0.02)
    Ut = whitening(reg.target_cov[corr.target_idx], reg.source_cov[corr.source_idx],
                   start[:3, :3])
    weights = rng.uniform(0.2, 1.0, len(corr))
    H, g = normal_equations(start, source, corr.source_idx, target, corr.target_idx, Ut,
                            weights)
    terms = gicp_terms(start, source[corr.source_idx], target[corr.target_idx], Ut)
    np.testing.assert_allclose(H, np.einsum("m,mji,mjk->ik", weights, terms.jacobians,
                                            terms.jacobians), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g, np.einsum("m,mji,mj->i", weights, terms.jacobians,
                                            terms.residuals), rtol=1e-10, atol=1e-12)
    key = gtsam.symbol("t", 0)
    factor = BatchedGicpFactor(key, source[corr.source_idx], target[corr.target_idx], Ut,
                               weights)
    np.testing.assert_allclose(gauss_newton_step(start, H, g, key),
                               solve_weighted(start, factor, "gn", 1), atol=1e-12)


def test_solution_sums_equal_the_numpy_products(rng):
    """The solution's one-pass sums (Registration.solution_terms) against the numpy
    products they replace: H = sum w J^T J, sum c g g^T, the scores w J^T r, the target
    normals from the covariances' largest diagonal of I - C, the residuals along them and
    w J^T U^T n."""
    from estimation.registration.correspondences import transform_points
    from estimation.registration.factors import solution_sums

    source, _, target, _, T_gt = make_pair(5, 600)
    reg = Registration(source, target, RegistrationConfig())
    corr = reg.correspondences(T_gt, 0.3)
    T = T_gt @ random_pose(rng, 0.01, 0.02)
    src, tgt = source[corr.source_idx], target[corr.target_idx]
    cov_t = reg.target_cov.all()
    Ut = whitening(cov_t[corr.target_idx], reg.source_cov[corr.source_idx], T[:3, :3])
    terms = gicp_terms(T, src, tgt, Ut)
    w, c = rng.uniform(0.2, 1.0, len(corr)), rng.uniform(-0.5, 0.0, len(corr))
    H, curvature, scores, normals, along, sens = solution_sums(T, src, tgt, Ut, terms, w, c,
                                                               cov_t, corr.target_idx)
    J, r = terms.jacobians, terms.residuals
    g = np.einsum("mji,mj->mi", J, r)
    close = {"rtol": 1e-10, "atol": 1e-12}
    np.testing.assert_allclose(H, np.einsum("m,mji,mjk->ik", w, J, J), **close)
    np.testing.assert_allclose(curvature, np.einsum("m,mi,mk->ik", c, g, g), **close)
    np.testing.assert_allclose(scores, w[:, None] * g, **close)
    D = np.eye(3) - cov_t[corr.target_idx]
    n = D[np.arange(len(D)), :, np.argmax(np.einsum("mii->mi", D), axis=1)]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(normals, n, **close)
    # the normal of each target neighbourhood (up to sign): the covariance's flat direction
    flat = np.einsum("mi,mij,mj->m", normals, cov_t[corr.target_idx], normals)
    assert np.all(flat < 0.01)
    np.testing.assert_allclose(along, np.einsum("mi,mi->m", n, tgt - transform_points(T, src)),
                               **close)
    np.testing.assert_allclose(sens, w[:, None] * np.einsum("mij,mi->mj", J,
                                                            np.einsum("mij,mj->mi", Ut, n)),
                               **close)


@pytest.mark.parametrize("size", [0.05, 0.4, 1e-4])
def test_cluster_sums_equal_a_grouping_by_block(rng, size):
    """Values summed per cubic block: the table over the blocks' box (0.4 m blocks over a
    2 m cloud) and the sort where the box has more blocks than four per point (0.05 and
    1e-4 m), against a plain grouping of the blocks' keys."""
    from estimation.registration.covariance_terms import cluster_sums

    points = rng.uniform(-1, 1, (5000, 3))
    values = rng.normal(size=(5000, 6))
    summed = cluster_sums(points, values, size)
    keys = np.floor(points / size).astype(np.int64)
    unique, group = np.unique(keys, axis=0, return_inverse=True)
    ref = np.zeros((len(unique), 6))
    np.add.at(ref, group.reshape(-1), values)
    assert summed.shape == ref.shape
    np.testing.assert_allclose(summed, ref, rtol=1e-12, atol=1e-12)


def test_shift_sensitivity_is_w_jt_ut(rng):
    from estimation.registration.result import SolutionTerms

    m = 50
    J, Ut = rng.normal(size=(m, 3, 6)), rng.normal(size=(m, 3, 3))
    w, weight = rng.uniform(0, 1, m), rng.uniform(0, 2, m)
    sol = SolutionTerms(None, None, None, w, None, None, None, None, None, None, J, Ut)
    ref = w[:, None, None] * (np.swapaxes(J, 1, 2) @ Ut)
    np.testing.assert_allclose(sol.shift_sensitivity(), ref, rtol=1e-13)
    np.testing.assert_allclose(sol.shift_sensitivity(weight), ref * weight[:, None, None],
                               rtol=1e-13)


def test_a_step_in_degenerate_geometry_leaves_the_free_direction_alone():
    # collinear pairs: rotation about the line is free; GTSAM finds the system indeterminate,
    # the damped step must not move along it (and must not raise)
    H = np.diag([0.0, 4.0, 4.0, 1.0, 1.0, 1.0])
    g = np.array([0.0, 0.4, -0.2, 0.1, 0.3, -0.1])
    T = gauss_newton_step(np.eye(4), H, g, gtsam.symbol("t", 0))
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(T))
    assert abs(xi[0]) < 1e-12
    np.testing.assert_allclose(xi[1:], -g[1:] / np.diag(H)[1:], rtol=1e-5)  # -H^-1 g


# -- recovery ---------------------------------------------------------------------------------
@pytest.mark.parametrize("optimizer", ["gn", "lm"])
def test_gicp_recovers_transform(optimizer):
    source, _, target, _, T_gt = make_pair(1)
    result = register(source, target, config=RegistrationConfig(optimizer=optimizer))
    err = pose_error(result.T, T_gt)
    assert result.converged, result.reason
    assert err.t_err_m < 5e-3 and err.r_err_rad < 2e-3
    assert result.inliers > 0.8 * len(source) and 0 < result.fitness <= 1
    assert result.cost_log[-1] < result.cost_log[0]
    assert result.method == "gicp" and result.iterations == len(result.cost_log)


@pytest.mark.reference
def test_gicp_agrees_with_open3d():
    import open3d as o3d

    source, _, target, _, T_gt = make_pair(2)
    ours = register(source, target, config=RegistrationConfig(max_correspondence_distance=0.3))
    reg = o3d.pipelines.registration
    theirs = reg.registration_generalized_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)), 0.3, np.eye(4),
        reg.TransformationEstimationForGeneralizedICP(reg.CauchyLoss(1.0)),
        reg.ICPConvergenceCriteria(1e-8, 1e-8, 60))
    assert pose_error(ours.T, theirs.transformation).d_se3 < 2e-3
    assert pose_error(ours.T, T_gt).d_se3 <= pose_error(theirs.transformation, T_gt).d_se3 + 1e-3


@pytest.mark.parametrize("semantic_weight", ["inside", "outside"])
def test_semantic_icp_recovers_transform(semantic_weight):
    source, labels_s, target, labels_t, T_gt = make_pair(4)
    result = semantic_icp(source, one_hot(labels_s, acc=0.9), target, one_hot(labels_t, acc=0.9),
                          semantic_weight=semantic_weight)
    assert result.converged, result.reason
    assert result.method == "semantic"
    err = pose_error(result.T, T_gt)
    assert err.t_err_m < 5e-3 and err.r_err_rad < 2e-3


@pytest.mark.parametrize("yaw_deg,shift", [(20, (2.0, 1.5, 0.0)), (45, (-1.0, 1.0, 0.3)),
                                           (-40, (1.5, -1.0, 0.2))])
def test_semantic_labels_widen_the_basin(yaw_deg, shift):
    # the box is the only structure that fixes the in-plane position; from these offsets
    # plain GICP locks the box onto the walls, while the box label pulls it home
    source, labels_s, target, labels_t, T_gt = make_pair(5, 4000)
    centre = np.eye(4)
    centre[:3, 3] = source.mean(axis=0)
    offset = gtsam.Pose3(gtsam.Rot3.Yaw(np.deg2rad(yaw_deg)), np.array(shift)).matrix()
    init = T_gt @ centre @ offset @ np.linalg.inv(centre)
    cfg = RegistrationConfig(max_correspondence_distance=0.2, initial_correspondence_distance=1.5)
    geometric = register(source, target, init, cfg)
    assert pose_error(geometric.T, T_gt).t_err_m > 0.2
    sem = semantic_icp(source, one_hot(labels_s, acc=0.9), target, one_hot(labels_t, acc=0.9),
                       init=init, config=cfg)
    err = pose_error(sem.T, T_gt)
    assert sem.converged, sem.reason
    assert err.t_err_m < 0.01 and err.r_err_rad < 0.005


# -- bad input: never a silent identity -------------------------------------------------------
def test_empty_and_tiny_clouds_fail_with_reason():
    target = np.random.default_rng(0).normal(size=(100, 3))
    for source in (np.zeros((0, 3)), np.ones((3, 3))):
        result = register(source, target)
        assert not result.converged and "too few points" in result.reason
        assert np.all(np.diag(result.covariance) >= UNCONSTRAINED_VARIANCE)


def test_no_correspondence_within_dmax():
    source, _, target, _, _ = make_pair(6, 400)
    far = np.eye(4)
    far[:3, 3] = [50.0, 0, 0]
    result = register(source, target, init=far)
    assert not result.converged and "correspondences" in result.reason
    np.testing.assert_array_equal(result.T, far)  # returned as given, flagged as failed


def test_single_plane_is_degenerate(rng):
    plane = np.c_[rng.uniform(0, 3, (1500, 2)), np.zeros(1500)]
    target = plane + rng.normal(0, 0.002, plane.shape)
    source = plane[::-1] + rng.normal(0, 0.002, plane.shape) + [0.02, 0.01, 0.01]
    result = register(source, target)
    assert not result.converged and "degenerate" in result.reason
    assert "3 unconstrained" in result.reason
    # the unconstrained directions are yaw, x and y: huge variance there, small for z
    variances = np.diag(result.covariance)
    assert variances[2] > 1e3 and variances[3] > 1e3 and variances[4] > 1e3
    # (normal noise tilts the null space a little, so some of the huge variance leaks in)
    assert variances[5] < 0.05 and variances[0] < 0.05 and variances[1] < 0.05


def test_single_label_everywhere_still_registers():
    source, labels_s, target, labels_t, T_gt = make_pair(7)
    probs_s = np.ones((len(source), 1))
    probs_t = np.ones((len(target), 1))
    result = semantic_icp(source, probs_s, target, probs_t)
    assert result.converged, result.reason
    assert pose_error(result.T, T_gt).t_err_m < 5e-3


def test_invalid_input_raises():
    pts = np.zeros((20, 3))
    with pytest.raises(EstimationError, match="NaN"):
        register(np.full((20, 3), np.nan), pts)
    with pytest.raises(EstimationError, match=r"\(N, 3\)"):
        register(np.zeros((20, 2)), pts)
    with pytest.raises(EstimationError, match="classes"):
        Registration(pts, pts, None, np.ones((20, 2)), np.ones((20, 3)))
    with pytest.raises(EstimationError, match="both clouds"):
        Registration(pts, pts, None, np.ones((20, 2)), None)
    with pytest.raises(EstimationError, match="semantic_weight"):
        RegistrationConfig(semantic_weight="middle")
    with pytest.raises(EstimationError, match="4x4"):
        register(pts, pts, init=np.eye(3))


# -- the PoseGraph ----------------------------------------------------------------------------
def test_result_adds_a_between_factor():
    from estimation.pose_graph import PoseGraph

    source, _, target, _, T_gt = make_pair(8)
    result = register(source, target)
    pg = PoseGraph()
    pg.add_node(0, gtsam.Pose3())
    pg.add_node(1, gtsam.Pose3())
    pg.add_prior(0, gtsam.Pose3(), np.eye(6) * 1e-8)
    result.add_to_pose_graph(pg, 0, 1, kind="calibration")
    pg.optimize()
    assert pose_error(pg.nodes[1].pose, T_gt).d_se3 < 1e-2
    failed = register(source[:3], target)
    with pytest.raises(EstimationError, match="did not converge"):
        failed.add_to_pose_graph(pg, 0, 1)


# -- Semantic-ICP's E-step ---------------------------------------------------------------------
def _index(points, labels, c=3, acc=0.9):
    return SemanticIndex(np.asarray(points, float), one_hot(np.asarray(labels), c, acc))


def test_posterior_estep_normalises_per_source_point():
    # target: a class-0 point at the origin, a class-1 point 10 cm away, a class-0 point far off
    index = _index([[0, 0, 0], [0.1, 0, 0], [5, 0, 0]], [0, 1, 0])
    # source 0 sits on target 0 with the right label; source 1 sits on target 0 but is labelled 1
    moved = np.array([[0.005, 0, 0], [0.0, 0.005, 0]])
    probs = one_hot(np.array([0, 1]), 3, 0.9)
    post = semantic_correspondences(moved, probs, index, 0.3, residual_sigma=0.02,
                                    nearest=cKDTree(index.points).query(moved), posterior=True)
    sums = np.bincount(post.source_idx, post.weights, minlength=2)
    np.testing.assert_allclose(sums, 1.0, atol=1e-3)  # less the dropped (< min_weight) ones
    # the nearest neighbour of source 0 is also its class candidate: counted once
    assert np.sum(post.source_idx == 0) == 1
    # source 1's vote goes to its geometric neighbour (1 cm off) over the class-1 point (10 cm)
    w1 = dict(zip(post.target_idx[post.source_idx == 1], post.weights[post.source_idx == 1]))
    assert w1[0] > 0.9
    # the unnormalised paper weights keep class candidates only: source 1 matches the class-1 point
    weight = semantic_correspondences(moved, probs, index, 0.3, residual_sigma=0.3)
    assert set(weight.target_idx[weight.source_idx == 1]) == {1}
    assert np.all(weight.weights <= 0.9 * 0.9 + 1e-12)


def _brute_force_estep(moved, probs, index, d_max, sigma, top, nearest, posterior,
                       label_noise, min_weight=1e-3, min_class_prob=0.1):
    """{(source row, target row): weight} of the E-step from its definition, by brute force."""
    d = np.linalg.norm(moved[:, None, :] - index.points[None, :, :], axis=2)
    n, c = probs.shape
    cands = {}
    for i in range(n):
        nn = int(np.argmin(d[i])) if nearest and d[i].min() <= d_max else -1
        if nn >= 0:
            cands[i, nn] = (probs[i] @ index.probs[nn], d[i, nn])
        for rank, cls in enumerate(np.argsort(-probs[i], kind="stable")[:top]):
            if rank and probs[i, cls] < min_class_prob:
                continue
            rows = np.flatnonzero(index.labels == cls)
            if not len(rows) or d[i, rows].min() > d_max:
                continue
            j = int(rows[np.argmin(d[i, rows])])
            if j != nn:
                cands[i, j] = (probs[i, cls] * index.probs[j, cls], d[i, j])
    w = {k: ((1 - label_noise) * p + label_noise / c) * np.exp(-0.5 * (r / sigma) ** 2)
         for k, (p, r) in cands.items()}
    if posterior:
        total = np.zeros(n)
        for (i, _), v in w.items():
            total[i] += v
        w = {k: v / total[k[0]] for k, v in w.items()}
    return {k: v for k, v in w.items() if v >= min_weight}


@pytest.mark.parametrize("posterior, label_noise, top", [(True, 0.2, 2), (True, 0.0, 3),
                                                         (False, 0.0, 2), (False, 0.1, 1)])
def test_estep_candidates_equal_their_definition(rng, posterior, label_noise, top):
    """The compiled candidate assembly (top classes, class search, nearest neighbour counted
    once, label noise, posterior normalisation, the weight floor) against brute force, with
    soft labels so that the second and third classes are searched too."""
    c = 4
    target = rng.uniform(0, 1, (300, 3))
    probs_t = rng.dirichlet(np.ones(c) * 0.3, 300)
    index = SemanticIndex(target, probs_t)
    moved = rng.uniform(-0.1, 1.1, (200, 3))
    probs = rng.dirichlet(np.ones(c) * 0.5, 200)
    d_max, sigma = 0.15, 0.05
    nearest = cKDTree(target).query(moved, distance_upper_bound=d_max) if posterior else None
    corr = semantic_correspondences(moved, probs, index, d_max, residual_sigma=sigma,
                                    top_classes=top, nearest=nearest, posterior=posterior,
                                    label_noise=label_noise)
    expected = _brute_force_estep(moved, probs, index, d_max, sigma, top, posterior,
                                  posterior, label_noise)
    got = {(int(i), int(j)): w for i, j, w in zip(corr.source_idx, corr.target_idx,
                                                 corr.weights)}
    assert len(got) == len(corr.weights) and set(got) == set(expected)
    np.testing.assert_allclose([got[k] for k in expected], list(expected.values()), rtol=1e-12)
    np.testing.assert_allclose(corr.distances, np.linalg.norm(
        moved[corr.source_idx] - target[corr.target_idx], axis=1), rtol=1e-12)


def test_bad_semantic_estep_is_rejected():
    with pytest.raises(EstimationError, match="semantic_estep"):
        RegistrationConfig(semantic_estep="bayes")
    with pytest.raises(EstimationError, match="factors"):
        RegistrationConfig(factors="per-point")


@pytest.mark.parametrize("estep", ["posterior", "weight"])
def test_semantic_icp_with_half_the_labels_wrong_still_registers(estep):
    from perception.simulation.room import noisy_labels

    source, labels_s, target, labels_t, T_gt = make_pair(21)
    rng = np.random.default_rng(3)
    noisy_s, noisy_t = noisy_labels(labels_s, 0.5, 4, rng), noisy_labels(labels_t, 0.5, 4, rng)
    result = semantic_icp(source, one_hot(noisy_s, acc=0.5), target, one_hot(noisy_t, acc=0.5),
                          config=RegistrationConfig(semantic_estep=estep))
    assert result.converged, result.reason
    err = pose_error(result.T, T_gt)
    assert err.t_err_m < 5e-3 and err.r_err_rad < 2e-3


# -- GTSAM's own robust Cauchy model gives the same estimate as the batched IRLS factor ----------
@pytest.mark.parametrize("semantic_weight", ["outside", "inside"])
def test_robust_noise_model_step_equals_batched_step(rng, semantic_weight):
    from estimation.registration.factors import robust_factors

    m, alpha = 300, 2.0
    src = rng.normal(size=(m, 3))
    T = random_pose(rng, 0.1, 0.2)
    tgt = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.05, (m, 3))
    tgt[:30] += rng.normal(0, 1.0, (30, 3))  # outliers: the kernel matters
    covs = point_covariances(rng.normal(size=(m, 3)), 10)
    Ut = whitening(covs, covs[::-1], np.eye(3))
    omega = rng.uniform(0.05, 1.0, m)
    e = gicp_terms(np.eye(4), src, tgt, Ut, jacobians=False).mahalanobis
    reg = Registration(src, tgt, RegistrationConfig(cauchy_alpha=alpha,
                                                    semantic_weight=semantic_weight),
                       np.ones((m, 2)) * 0.5, np.ones((m, 2)) * 0.5)
    key = gtsam.symbol("t", 0)
    batched = solve_weighted(np.eye(4), BatchedGicpFactor(key, src, tgt, Ut,
                                                          reg._weights(e, omega)))
    robust = solve_weighted(np.eye(4), robust_factors(key, src, tgt, Ut, omega, alpha,
                                                      semantic_weight), key=key)
    np.testing.assert_allclose(robust, batched, atol=1e-9)
    assert pose_error(batched, np.eye(4)).d_se3 > 0.05  # the step did move


@pytest.mark.parametrize("semantic", [False, True])
def test_registration_with_gtsam_robust_factors_matches_batched(semantic):
    source, labels_s, target, labels_t, T_gt = make_pair(8, 600, 0.005)
    probs = (one_hot(labels_s, acc=0.9), one_hot(labels_t, acc=0.9)) if semantic else (None,) * 2
    results = [Registration(source, target, RegistrationConfig(factors=f), *probs).run()
               for f in ("batched", "robust")]
    assert results[0].converged and results[1].converged
    assert results[0].iterations == results[1].iterations
    np.testing.assert_allclose(results[1].T, results[0].T, atol=1e-8)
    assert pose_error(results[1].T, T_gt).t_err_m < 0.01


def test_semantic_candidate_caches_keep_the_answer():
    # the class candidates' cache (and the geometric one) are exact: same path, same pose
    source, labels_s, target, labels_t, T_gt = make_pair(9, 3000, 0.005)
    probs = one_hot(labels_s, acc=0.8), one_hot(labels_t, acc=0.8)
    runs = [Registration(source, target, RegistrationConfig(
        cached_neighbours=k, initial_correspondence_distance=0.6), *probs).run()
        for k in (8, 0)]
    assert runs[0].iterations == runs[1].iterations
    np.testing.assert_array_equal(runs[0].cost_log, runs[1].cost_log)
    np.testing.assert_allclose(runs[0].T, runs[1].T, atol=1e-12)
    assert pose_error(runs[0].T, T_gt).t_err_m < 5e-3


def test_lazy_covariances_filled_from_two_threads_equal_the_full_computation(rng):
    """Rows filled by a prefetching thread and by this one at once (no lock while computing,
    overlapping rows computed twice) hold the one-pass values."""
    import threading

    from scipy.spatial import cKDTree

    from estimation.registration.correspondences import LazyCovariances

    points = rng.normal(size=(3000, 3)) * [1.0, 1.0, 0.05]
    full = point_covariances(points, 12, 1e-3)
    lazy = LazyCovariances(points, cKDTree(points), 12, 1e-3)
    worker = threading.Thread(target=lazy.prefetch, args=(np.arange(0, 3000, 2),),
                              kwargs={"chunk": 100})
    worker.start()
    for part in np.array_split(rng.permutation(3000)[:2000], 20):
        lazy[part]
    worker.join()
    assert lazy.done[::2].all()
    np.testing.assert_array_equal(lazy.values[lazy.done], full[lazy.done])
    stop = threading.Event()
    stop.set()
    fresh = LazyCovariances(points, cKDTree(points), 12, 1e-3)
    fresh.prefetch(np.arange(3000), stop=stop)  # stopped before its first chunk
    assert not fresh.done.any()


def test_a_start_at_the_final_distance_aligns_a_coarse_subset_first(monkeypatch):
    """RegistrationConfig()'s start at the final d_max: the coarse subset is aligned there
    first (COARSE_FIRST), so fewer iterations match every point, and the final stage, on
    every point, converges to the fixed point it reaches without that stage."""
    import estimation.registration.gicp as gicp

    source, _, target, _, T_gt = make_pair(5, 9000)
    init = T_gt @ gtsam.Pose3(gtsam.Rot3.Rodrigues(0.04, -0.02, 0.03),
                              np.array([0.06, -0.04, 0.03])).matrix()
    calls = []
    query = gicp.Registration.correspondences

    def counted(self, T, d, rows=None, step=None, **cells):
        if step is not None:  # the iterations' (not the covariance's, nor on other threads)
            calls.append((self, len(self.source) if rows is None else len(rows)))
        return query(self, T, d, rows, step, **cells)

    monkeypatch.setattr(gicp.Registration, "correspondences", counted)
    results, full = {}, {}
    for coarse_first in (True, False):
        monkeypatch.setattr(gicp, "COARSE_FIRST", coarse_first)
        calls.clear()
        registration = Registration(source, target, RegistrationConfig())
        results[coarse_first] = registration.run(init)
        assert results[coarse_first].converged
        own = [n for who, n in calls if who is registration]  # not the reverse direction's
        full[coarse_first] = own.count(len(source))
        coarse = [n for n in own if n < len(source)]
        # the coarse stage ran first, on about coarse_points rows
        assert (len(coarse) >= 2 and own[:len(coarse)] == coarse) == coarse_first
        # (half evenly strided, half over the normals' directions: rows in both count once)
        assert all(2400 <= n <= 3000 for n in coarse), coarse
    assert full[True] < full[False]
    step = gtsam.Pose3.Logmap(gtsam.Pose3(results[False].T).between(gtsam.Pose3(results[True].T)))
    assert np.linalg.norm(step) < 3e-4  # within a few convergence tolerances (1e-4)
    # a start at the fixed point: one coarse step (below COARSE_FIRST_STEP), then every point
    monkeypatch.setattr(gicp, "COARSE_FIRST", True)
    calls.clear()
    registration = Registration(source, target, RegistrationConfig())
    registration.run(results[False].T)
    own = [n for who, n in calls if who is registration]
    assert own[0] < len(source) and own[1:] == [len(source)] * (len(own) - 1)
