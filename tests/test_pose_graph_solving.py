"""PoseGraph solving tells the truth: gauge anchor, iSAM2 and marginals on direction chains,
GTSAM failures as one-line EstimationErrors, 4x4 arrays as poses, `graph optimize`."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation import EstimationError, PoseGraph
from estimation.io import write_g2o
from estimation.pose_graph import GAUGE_SIGMA
from pipelines.cli import main


def _pose(x=0.0, y=0.0, z=0.0, yaw=0.0, pitch=0.0, roll=0.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), np.array([x, y, z]))


def _direction_chain(n=8, prior=False, seed=0) -> tuple[PoseGraph, list[gtsam.Pose3]]:
    """Nodes + between factors + direction factors (world x axis); no prior unless asked."""
    rng = np.random.default_rng(seed)
    truth = [_pose(k, 0.2 * k, 0, yaw=0.15 * k, pitch=0.05 * k) for k in range(n)]
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    pg = PoseGraph()
    for k, T in enumerate(truth):
        pg.add_node(k, T.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * 0.02)))
    for k in range(n - 1):
        pg.add_between(k, k + 1, truth[k].between(truth[k + 1]), cov)
    for k, T in enumerate(truth):
        d_world = np.array([1.0, 0.0, 0.0])
        d_sensor = T.rotation().unrotate(d_world)
        pg.add_direction(k, d_sensor, d_world, 0.01**2 * np.eye(3))
    if prior:
        pg.add_prior(0, truth[0], np.diag([0.01**2] * 3 + [0.05**2] * 3))
    return pg, truth


# ---------------------------------------------------------------- gauge, iSAM2, marginals
def test_direction_factors_are_not_a_gauge_prior():
    pg, _ = _direction_chain()
    assert not pg.has_pose_prior()  # unary, but they fix only 2 rotation dof
    pg_prior, _ = _direction_chain(prior=True)
    assert pg_prior.has_pose_prior()


def test_isam2_on_a_plain_direction_chain_matches_lm():
    lm, _ = _direction_chain()
    isam, _ = _direction_chain()
    lm_result = lm.optimize("lm")
    isam_result = isam.optimize("isam2", isam2_extra_steps=5)
    assert lm_result.anchored_node == 0 and isam_result.anchored_node == 0
    assert isam_result.final_error < 1e-6 * isam_result.initial_error
    for k in lm.sorted_ids():
        assert isam.nodes[k].pose.equals(lm.nodes[k].pose, 1e-4)
    # the anchor is weak: the marginals include its 1 m translation spread
    cov = isam.marginal_covariance(0)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert cov[3, 3] == pytest.approx(GAUGE_SIGMA**2, rel=0.05)


def test_weak_anchor_lets_directions_correct_the_first_node():
    truth = [_pose(0, 0, 0), _pose(1, 0, 0)]
    pg = PoseGraph()
    pg.add_node(0, _pose(yaw=0.2))  # 0.2 rad off; the direction factors say so
    pg.add_node(1, truth[0].between(truth[1]).compose(_pose(yaw=0.2)))
    pg.add_between(0, 1, truth[0].between(truth[1]), np.eye(6) * 1e-4)
    for k in (0, 1):
        for d_world in np.eye(3)[:2]:
            pg.add_direction(k, truth[k].rotation().unrotate(d_world), d_world,
                             np.eye(3) * 1e-6)
    pg.optimize()
    assert pg.nodes[0].pose.rotation().equals(truth[0].rotation(), 1e-4)


@pytest.mark.parametrize("method", ["lm", "isam2"])
def test_marginals_of_a_direction_chain_with_a_prior(method):
    pg, _ = _direction_chain(prior=True)
    result = pg.optimize(method, isam2_extra_steps=3)  # relinearised at the optimum
    assert result.anchored_node is None
    reference, _ = _direction_chain(prior=True)
    reference.optimize("lm")
    for k in (0, 4, 7):
        cov = pg.marginal_covariance(k)
        assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
        expected = reference.marginal_covariance(k)
        # iSAM2 stops relinearising within its 0.001 threshold of the LM optimum
        np.testing.assert_allclose(cov, expected, rtol=0.01, atol=2e-3 * np.abs(expected).max())
    # the direction factors make the rotation perpendicular to x tighter than the prior alone
    assert pg.marginal_covariance(7)[2, 2] < 0.01**2


def _rotation_free_between(i: int, j: int):
    """A between factor with zero information on the rotation: node j's rotation is held by
    nothing (each part of a graph is anchored, so only such a factor leaves a dof free)."""
    from estimation.pose_graph import FactorRecord, node_key

    noise = gtsam.noiseModel.Diagonal.Precisions(np.array([0.0, 0, 0, 1, 1, 1]))
    return FactorRecord("between", (i, j),
                        gtsam.BetweenFactorPose3(node_key(i), node_key(j), _pose(1), noise))


def test_failed_isam2_leaves_no_stale_bayes_tree():
    # node 2's rotation is held by nothing: iSAM2's elimination meets an indeterminate system
    pg = PoseGraph()
    for k in range(4):
        pg.add_node(k, _pose(k))
    pg.add_between(0, 1, _pose(1), np.eye(6) * 1e-2)
    pg.factors.append(_rotation_free_between(1, 2))
    pg.add_between(2, 3, _pose(1), np.eye(6) * 1e-2)
    with pytest.raises(EstimationError) as info:
        pg.optimize("isam2")
    message = str(info.value)
    assert "iSAM2 failed: indeterminate linear system near node" in message
    assert "\n" not in message
    assert pg.nodes[2].pose.equals(_pose(2), 0)  # poses untouched
    pg.add_between(1, 2, _pose(1.1), np.eye(6) * 1e-2)
    pg.add_prior(0, _pose(), np.eye(6) * 1e-4)
    pg.optimize("isam2", isam2_extra_steps=3)  # rebuilt from scratch, not the broken tree
    reference = PoseGraph()
    for k in range(4):
        reference.add_node(k, _pose(k))
    for record in pg.factors:
        reference.factors.append(record)
    reference.optimize("lm")
    for k in range(4):
        assert pg.nodes[k].pose.equals(reference.nodes[k].pose, 1e-6)
    np.testing.assert_allclose(pg.marginal_covariance(3), reference.marginal_covariance(3),
                               rtol=1e-3)


def test_singular_marginals_are_a_one_line_estimation_error():
    pg = PoseGraph()
    for k in range(3):
        pg.add_node(k, _pose(k))
    pg.add_between(0, 1, _pose(1), np.eye(6))
    pg.factors.append(_rotation_free_between(1, 2))  # node 2's rotation is held by nothing
    with pytest.raises(EstimationError, match=r"indeterminate linear system near node") as info:
        pg.marginal_covariance(1)
    assert "\n" not in str(info.value)


def test_missing_node_is_named():
    pg, _ = _direction_chain(prior=True)
    with pytest.raises(EstimationError, match="^node 7 is not in the graph$"):
        PoseGraph().marginal_covariance(7)
    with pytest.raises(EstimationError, match="^node 70 is not in the graph$"):
        pg.marginal_covariance(70)
    with pytest.raises(EstimationError, match="^node 70 is not in the graph$"):
        pg.relative_covariance(0, 70)


# ---------------------------------------------------------------- 4x4 arrays as poses
def test_4x4_arrays_are_poses():
    T0, T1 = _pose(1, 2, 3, 0.3, -0.2, 0.1), _pose(2, 2, 3, 0.5)
    from_arrays, from_poses = PoseGraph(), PoseGraph()
    from_arrays.add_node(0, T0.matrix())
    from_arrays.add_node(1, T1.matrix().astype(np.float32))  # ~1e-7 off orthonormal
    from_arrays.add_node(2, T1.matrix().tolist())
    from_arrays.add_prior(0, T0.matrix(), np.eye(6))
    from_arrays.add_between(0, 1, T0.between(T1).matrix(), np.eye(6))
    from_poses.add_node(0, T0)
    from_poses.add_node(1, T1)
    from_poses.add_prior(0, T0, np.eye(6))
    from_poses.add_between(0, 1, T0.between(T1), np.eye(6))
    assert isinstance(from_arrays.nodes[0].pose, gtsam.Pose3)
    assert from_arrays.nodes[0].pose.equals(T0, 1e-15)
    assert from_arrays.nodes[1].pose.equals(T1, 1e-6)
    R = from_arrays.nodes[1].pose.rotation().matrix()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)  # projected to a rotation
    assert from_arrays.nodes[2].pose.equals(T1, 1e-15)
    assert from_arrays.factors[1].measured.equals(from_poses.factors[1].measured, 1e-15)
    from_arrays.nodes.pop(2)
    assert from_arrays.error() == pytest.approx(from_poses.error(), abs=1e-9)


def _bad(kind: str) -> np.ndarray:
    T = _pose(1, 2, 3, 0.4).matrix()
    if kind == "scaled":
        T[:3, :3] *= 1.01
    elif kind == "reflection":
        T[:3, :3] = T[:3, :3] @ np.diag([1.0, 1.0, -1.0])
    elif kind == "nan":
        T[0, 3] = np.nan
    elif kind == "last row":
        T[3, 0] = 0.5
    return T


@pytest.mark.parametrize("call, message", [
    (lambda pg: pg.add_node(3, np.eye(3)),
     r"^T_world_sensor of node 3 must be a gtsam.Pose3 or a 4x4 array, got shape \(3, 3\)$"),
    (lambda pg: pg.add_node(3, "identity"),
     "^T_world_sensor of node 3 must be a gtsam.Pose3 or a 4x4 array, got str$"),
    (lambda pg: pg.add_node(3, gtsam.Rot3()),
     "^T_world_sensor of node 3 must be a gtsam.Pose3 or a 4x4 array, got Rot3$"),
    (lambda pg: pg.add_node(3, _bad("scaled")),
     r"^T_world_sensor of node 3: rotation block is not orthonormal"),
    (lambda pg: pg.add_node(3, _bad("reflection")),
     r"^T_world_sensor of node 3: rotation block has det -1"),
    (lambda pg: pg.add_node(3, _bad("nan")), "^T_world_sensor of node 3 has NaN or inf"),
    (lambda pg: pg.add_node(3, _bad("last row")), r"last row is \[0.5, 0.0, 0.0, 1.0\]"),
    (lambda pg: pg.add_prior(0, np.eye(4)[:3], np.eye(6)),
     r"^pose of the prior on node 0 must be a gtsam.Pose3 or a 4x4 array, got shape \(3, 4\)$"),
    (lambda pg: pg.add_between(0, 1, _bad("scaled"), np.eye(6)),
     r"^T_i_j of the between factor 0->1: rotation block is not orthonormal"),
])
def test_bad_pose_arguments_are_named(call, message):
    pg = PoseGraph()
    pg.add_node(0, np.eye(4))
    pg.add_node(1, np.eye(4))
    with pytest.raises(EstimationError, match=message):
        call(pg)
    assert len(pg.nodes) == 2 and not pg.factors


# ---------------------------------------------------------------- graph optimize
def _write_chain(path) -> None:
    pg = PoseGraph()
    for k in range(6):
        pg.add_node(k, _pose(1.05 * k, 0.01 * k, yaw=0.01 * k), timestamp=float(k))
    for k in range(5):
        pg.add_between(k, k + 1, _pose(1.0), np.eye(6) * 1e-3)
    write_g2o(path, pg)


@pytest.mark.parametrize("method", ["lm", "isam2"])
def test_graph_optimize_says_it_anchors_the_first_node(tmp_path, capsys, method):
    _write_chain(tmp_path / "in.g2o")
    code = main(["graph", "optimize", str(tmp_path / "in.g2o"), "-o", str(tmp_path / "out.g2o"),
                 "--method", method])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("octofactor: note: the graph has no prior: node 0 is anchored")
    assert "weak prior" in lines[0]
    initial = float(captured.out.splitlines()[0].split(":")[1])
    final = float(captured.out.splitlines()[1].split(":")[1].split()[0])
    assert final < 1e-2 * initial


def test_graph_optimize_gtsam_failure_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    # a file cannot hold a zero-information factor (the readers refuse it): GTSAM's own
    # exception, as it raises it, stands in for one
    _write_chain(tmp_path / "in.g2o")

    def indeterminate(*args, **kwargs):
        raise RuntimeError("\nIndeterminant linear system detected while working near "
                           "variable 3 (Symbol: x3).\n\nThresholds ...")

    monkeypatch.setattr(gtsam.ISAM2, "update", indeterminate)
    code = main(["graph", "optimize", str(tmp_path / "in.g2o"), "-o", str(tmp_path / "out.g2o"),
                 "--method", "isam2"])
    captured = capsys.readouterr()
    assert code == 2
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("octofactor: error: iSAM2 failed: indeterminate linear system")
    assert "Traceback" not in captured.err
    assert not (tmp_path / "out.g2o").exists()


@pytest.mark.parametrize("method", ["lm", "isam2"])
def test_each_unconnected_part_gets_its_own_anchor(method):
    """Two chains with no factor between them and no prior: both methods anchor the first
    node of each part, optimise both, and give each node a marginal."""
    rng = np.random.default_rng(7)
    pg = PoseGraph()
    truth = {}
    for part, start in ((0, 0), (1, 10)):
        T = gtsam.Pose3(gtsam.Rot3(), np.array([5.0 * part, 0, 0]))
        for k in range(start, start + 4):
            truth[k] = T
            noisy = T.compose(gtsam.Pose3.Expmap(rng.normal(scale=0.05, size=6)))
            pg.add_node(k, noisy)
            if k > start:
                pg.add_between(k - 1, k, truth[k - 1].between(T), np.eye(6) * 1e-4)
            T = T.compose(gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([1.0, 0, 0])))
    assert pg.unanchored_parts() == [0, 10]
    result = pg.optimize(method, isam2_extra_steps=3)
    assert result.anchored_nodes == (0, 10) and result.anchored_node == 0
    assert result.final_error < 1e-6 * result.initial_error
    for k in (3, 13):  # each part's shape is right relative to its own first node
        rel = pg.nodes[k - 3].pose.between(pg.nodes[k].pose)
        assert rel.equals(truth[k - 3].between(truth[k]), 1e-4)
        assert np.all(np.linalg.eigvalsh(pg.marginal_covariance(k)) > 0)
    pg.add_between(3, 10, truth[3].between(truth[10]), np.eye(6) * 1e-4)
    assert pg.unanchored_parts() == [0]  # joined: one gauge
