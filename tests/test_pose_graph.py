"""PoseGraph: building, solving, marginals in [rotation, translation] order, consistency."""
from __future__ import annotations

import functools

import gtsam
import numpy as np
import pytest

from estimation import EstimationError, PoseGraph, check_consistency
from estimation.simulation import loop_graph_joint_nees, loop_graph_nees, simulate_loop_graph


def _pose(x=0.0, y=0.0, z=0.0, yaw=0.0, pitch=0.0, roll=0.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), np.array([x, y, z]))


def test_marginal_covariance_is_rotation_then_translation():
    rot_sigma, trans_sigma = 0.01, 0.5
    pg = PoseGraph()
    pg.add_node(0, _pose(1, 2, 3, 0.3))
    cov = np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)
    pg.add_prior(0, _pose(1, 2, 3, 0.3), cov)
    marginal = pg.marginal_covariance(0)
    np.testing.assert_allclose(np.diag(marginal), np.diag(cov), rtol=1e-9)


def test_lm_and_isam2_agree_and_isam2_is_incremental(rng):
    sim = simulate_loop_graph(rng, n_poses=12)
    lm_graph = simulate_loop_graph(np.random.default_rng(7), n_poses=12).graph
    isam_graph = simulate_loop_graph(np.random.default_rng(7), n_poses=12).graph
    lm = lm_graph.optimize("lm")
    assert lm.final_error < lm.initial_error
    # iSAM2 fed in two batches (first half of the nodes, then the rest) must reach the LM optimum.
    partial = PoseGraph()
    for node_id in isam_graph.sorted_ids():
        node = isam_graph.nodes[node_id]
        partial.add_node(node_id, node.pose, node.timestamp)
        for record in isam_graph.factors:
            if max(record.nodes) == node_id:
                partial.factors.append(record)
        if node_id in (5, 11):
            partial.optimize("isam2")
    partial.optimize("isam2", isam2_extra_steps=5)  # relinearise to convergence
    for node_id in lm_graph.sorted_ids():
        assert lm_graph.nodes[node_id].pose.equals(partial.nodes[node_id].pose, 1e-3)
    np.testing.assert_allclose(partial.marginal_covariance(6), lm_graph.marginal_covariance(6),
                               rtol=0.05, atol=1e-9)
    assert sim.graph.factor_counts() == {"prior": 1, "odometry": 11, "loop": 1}


def test_gauge_is_fixed_without_prior():
    pg = PoseGraph()
    pg.add_node(0, _pose())
    pg.add_node(1, _pose(1.2))
    pg.add_between(0, 1, _pose(1.0), np.eye(6) * 0.01)
    pg.optimize()
    assert pg.nodes[0].pose.equals(_pose(), 1e-9)
    np.testing.assert_allclose(pg.nodes[1].pose.translation(), [1, 0, 0], atol=1e-9)


def test_relative_covariance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    cov_i = np.diag([0.02, 0.01, 0.03, 0.1, 0.2, 0.05]) ** 2
    cov_j = np.diag([0.01, 0.02, 0.01, 0.05, 0.1, 0.2]) ** 2
    T_i, T_j = _pose(1, 2, 0, 0.4, 0.1), _pose(3, 1, 1, -0.3, 0.2, 0.1)
    pg = PoseGraph()
    pg.add_node(0, T_i)
    pg.add_node(1, T_j)
    pg.add_prior(0, T_i, cov_i)
    pg.add_prior(1, T_j, cov_j)
    analytic = pg.relative_covariance(0, 1)
    T_ij = T_i.between(T_j)
    samples = []
    for _ in range(4000):
        a = T_i.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov_i)))
        b = T_j.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov_j)))
        samples.append(T_ij.localCoordinates(a.between(b)))
    empirical = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(analytic)), np.sqrt(np.diag(empirical)), rtol=0.08)


def test_rejects_bad_input():
    pg = PoseGraph()
    pg.add_node(0, _pose())
    with pytest.raises(EstimationError, match="already exists"):
        pg.add_node(0, _pose())
    with pytest.raises(EstimationError, match="NaN"):
        pg.add_node(1, gtsam.Pose3(gtsam.Rot3(), np.array([np.nan, 0, 0])))
    with pytest.raises(EstimationError, match="unknown node 5"):
        pg.add_between(0, 5, _pose(), np.eye(6))
    with pytest.raises(EstimationError, match="positive definite"):
        pg.add_prior(0, _pose(), -np.eye(6))
    with pytest.raises(EstimationError, match="6x6"):
        pg.add_prior(0, _pose(), np.eye(3))
    with pytest.raises(EstimationError, match="kind"):
        pg.add_node(1, _pose())
        pg.add_between(0, 1, _pose(), np.eye(6), kind="bogus")


def test_robust_between_factor_downweights_an_outlier():
    pg = PoseGraph()
    for k in range(4):
        pg.add_node(k, _pose(float(k)))
    pg.add_prior(0, _pose(), np.eye(6) * 1e-8)
    for k in range(3):
        pg.add_between(k, k + 1, _pose(1.0), np.eye(6) * 1e-4)
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(1.0)
    pg.add_between(0, 3, _pose(10.0), np.eye(6) * 1e-4, kind="loop", robust=cauchy)
    pg.optimize()
    assert abs(pg.nodes[3].pose.translation()[0] - 3.0) < 0.05
    assert pg.factors[-1].robust == "Cauchy"


N_POSES = 10


@functools.cache
def _loop_nees(n_runs: int, model_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per run after LM: (n_runs, N_POSES) per-node NEES and (n_runs,) joint NEES."""
    runs = [loop_graph_nees(1000 + seed, N_POSES, model_scale) for seed in range(n_runs)]
    return np.array([r.per_node for r in runs]), np.array([r.joint for r in runs])


def test_pose_graph_nees_is_consistent():
    per_node, joint = _loop_nees(200, 1.0)
    check = check_consistency(joint, dof=6 * N_POSES)
    assert check.passed, check
    # each node's marginal alone (dof 6), every node inside its band on >= 90 % of the nodes
    check_nodes = check_consistency(per_node, dof=6)
    assert check_nodes.passed, check_nodes


def test_loop_graph_joint_nees_is_the_joint_value():
    assert loop_graph_joint_nees(1000, N_POSES) == _loop_nees(200, 1.0)[1][0]


def test_pose_graph_nees_negative_control_fails():
    # Noise models four times too confident (variance x 0.25): NEES ~ 4x too large.
    per_node, joint = _loop_nees(200, 0.25)
    check = check_consistency(joint, dof=6 * N_POSES)
    assert not check.passed
    assert not check_consistency(per_node, dof=6).passed
    assert check.mean > 2 * 6 * N_POSES
