"""Direction (vanishing-point) factors: GTSAM's attitude factor on a PoseGraph node."""
from __future__ import annotations

import pickle

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11

from estimation import EstimationError, PoseGraph, check_consistency
from estimation.pose_graph import node_key


def _random_pose(rng) -> gtsam.Pose3:
    return gtsam.Pose3.Expmap(rng.normal(size=6) * [1, 1, 1, 3, 3, 3])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _perpendicular(d: np.ndarray) -> np.ndarray:
    return _unit(np.cross(d, [0.3, -0.5, 0.8]))


def _rotated_body(T: gtsam.Pose3, axis_sensor: np.ndarray, angle: float) -> gtsam.Pose3:
    """``T`` rotated by ``angle`` about ``axis_sensor`` (an axis in the sensor frame)."""
    return T.compose(gtsam.Pose3(gtsam.Rot3.Expmap(axis_sensor * angle), np.zeros(3)))


def _one_direction(rng, sigma=0.01):
    T = _random_pose(rng)
    d_sensor = _unit(rng.normal(size=3))
    d_world = T.rotation().matrix() @ d_sensor
    pg = PoseGraph()
    pg.add_node(0, T)
    cov = sigma**2 * (np.eye(3) - np.outer(d_sensor, d_sensor))
    record = pg.add_direction(0, d_sensor, d_world, cov)
    return pg, record, T, d_sensor, d_world


def _unwhitened(record, T: gtsam.Pose3) -> np.ndarray:
    values = gtsam.Values()
    values.insert(node_key(record.nodes[0]), T)
    return np.asarray(record.factor.unwhitenedError(values))


@pytest.mark.parametrize("seed", range(5))
def test_direction_error_is_zero_at_truth_and_grows_off_axis(seed):
    rng = np.random.default_rng(seed)
    pg, record, T, d_sensor, d_world = _one_direction(rng)
    assert record.kind == "direction" and record.nodes == (0,)
    assert np.linalg.norm(_unwhitened(record, T)) < 1e-12
    perpendicular = _perpendicular(d_sensor)
    norms = []
    for angle in (0.01, 0.05, 0.2):
        error = _unwhitened(record, _rotated_body(T, perpendicular, angle))
        # the 2-D error is the rotated direction's offset in the tangent of d_world: sin(angle)
        assert np.linalg.norm(error) == pytest.approx(np.sin(angle), rel=1e-6)
        norms.append(np.linalg.norm(error))
    assert norms == sorted(norms)
    # rotations about the direction itself (in the sensor or the world frame), and any
    # translation, leave it unobserved
    about_axis = _rotated_body(T, d_sensor, 0.7)
    assert np.linalg.norm(_unwhitened(record, about_axis)) < 1e-12
    world_turn = gtsam.Pose3(gtsam.Rot3.Expmap(d_world * -1.1), np.zeros(3)).compose(T)
    assert np.linalg.norm(_unwhitened(record, world_turn)) < 1e-12
    moved = gtsam.Pose3(T.rotation(), T.translation() + rng.normal(size=3) * 10)
    assert np.linalg.norm(_unwhitened(record, moved)) < 1e-12


def test_direction_arguments_are_sensor_then_world():
    """R_world_sensor @ direction_sensor must equal direction_world: swapping them is an error."""
    T = gtsam.Pose3(gtsam.Rot3.Ypr(1.0, 0.3, -0.2), np.array([1.0, 2.0, 3.0]))
    d_sensor = _unit([0.2, -0.1, 1.0])
    d_world = T.rotation().matrix() @ d_sensor
    pg = PoseGraph()
    pg.add_node(0, T)
    right = pg.add_direction(0, d_sensor, d_world, np.eye(3) * 1e-4)
    swapped = pg.add_direction(0, d_world, d_sensor, np.eye(3) * 1e-4)
    assert right.factor.error(pg.values()) < 1e-20
    assert np.linalg.norm(_unwhitened(swapped, T)) > 0.3
    np.testing.assert_allclose(right.metadata["direction_sensor"], d_sensor)
    np.testing.assert_allclose(right.metadata["direction_world"], d_world)


@pytest.mark.parametrize("seed", range(4))
def test_direction_jacobian_matches_numerical_derivative(seed):
    rng = np.random.default_rng(10 + seed)
    pg, record, T, d_sensor, _ = _one_direction(rng, sigma=0.03)
    # away from the optimum, where the Jacobian is not trivially zero in any direction
    T_eval = _rotated_body(T, _perpendicular(d_sensor), 0.3).compose(
        gtsam.Pose3.Expmap(rng.normal(size=6) * 0.1))
    values = gtsam.Values()
    values.insert(node_key(0), T_eval)
    A, b = record.factor.linearize(values).jacobian()  # whitened: A = W H, b = -W e

    def whitened(pose: gtsam.Pose3) -> np.ndarray:
        v = gtsam.Values()
        v.insert(node_key(0), pose)
        return np.asarray(record.factor.whitenedError(v))

    numerical = numericalDerivative11(whitened, T_eval, 1e-6)
    np.testing.assert_allclose(A, numerical, atol=1e-5 * np.abs(A).max())
    np.testing.assert_allclose(-b, whitened(T_eval), rtol=1e-9)
    assert np.allclose(A[:, 3:], 0.0)  # translation is not observed


def test_sensor_covariance_whitens_to_unit_chi_square():
    """Measured directions drawn from ``cov`` give whitened errors ~ chi2(2); a covariance
    taken in the wrong frame (world instead of sensor) must fail the same check."""
    rng = np.random.default_rng(21)
    T = gtsam.Pose3(gtsam.Rot3.Ypr(0.9, -0.4, 0.6), np.zeros(3))
    R = T.rotation().matrix()
    d_sensor = _unit([0.1, 0.2, 1.0])
    d_world = R @ d_sensor
    e1 = _perpendicular(d_sensor)
    e2 = np.cross(d_sensor, e1)
    cov = 0.03**2 * np.outer(e1, e1) + 0.002**2 * np.outer(e2, e2)  # strongly anisotropic
    nees, nees_wrong_frame = [], []
    for _ in range(300):
        measured = _unit(d_sensor + rng.multivariate_normal(np.zeros(3), cov))
        pg = PoseGraph()
        pg.add_node(0, T)
        good = pg.add_direction(0, measured, d_world, cov)
        # the same covariance read as a world-frame one: what a frame mix-up would give
        wrong = pg.add_direction(0, measured, d_world, R.T @ cov @ R)
        nees.append(2 * good.factor.error(pg.values()))
        nees_wrong_frame.append(2 * wrong.factor.error(pg.values()))
    assert check_consistency(np.array(nees), dof=2).passed
    assert not check_consistency(np.array(nees_wrong_frame), dof=2).passed


def test_isotropic_covariance_does_not_depend_on_the_initial_rotation():
    d_sensor = _unit([0.3, 0.1, 1.0])
    d_world = np.array([1.0, 0.0, 0.0])
    cov = 0.02**2 * (np.eye(3) - np.outer(d_sensor, d_sensor))
    for yaw in (0.0, 0.5, 2.5, np.pi):
        pg = PoseGraph()
        pg.add_node(0, gtsam.Pose3(gtsam.Rot3.Ypr(yaw, 0.2, 0.1), np.zeros(3)))
        record = pg.add_direction(0, d_sensor * 3.0, d_world, cov)
        np.testing.assert_allclose(record.metadata["cov_tangent"], 0.02**2 * np.eye(2),
                                   atol=1e-15)
        assert np.linalg.norm(record.metadata["direction_sensor"]) == pytest.approx(1.0)


def _drifting_chain(n=25, yaw_bias=0.02, seed=3):
    """Truth turning in yaw; odometry with a yaw bias; dead-reckoned initial poses.

    The factors' rotation sigma (0.02 rad) admits the bias; the drawn noise is smaller.
    """
    rng = np.random.default_rng(seed)
    truth = [gtsam.Pose3(gtsam.Rot3.Ypr(0.25 * k, 0.05 * np.sin(k), 0.0),
                         np.array([np.cos(0.2 * k) * k, np.sin(0.2 * k) * k, 0.1 * k]))
             for k in range(n)]
    cov = np.diag([0.02**2] * 3 + [0.01**2] * 3)
    noise_cov = np.diag([1e-3**2] * 3 + [0.01**2] * 3)
    odometry = []
    for k in range(n - 1):
        noise = gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), noise_cov))
        bias = gtsam.Pose3(gtsam.Rot3.Yaw(yaw_bias), np.zeros(3))
        odometry.append(truth[k].between(truth[k + 1]).compose(noise).compose(bias))
    initial = [truth[0]]
    for T in odometry:
        initial.append(initial[-1].compose(T))
    return truth, initial, odometry, cov, rng


def _rotation_errors(pg: PoseGraph, truth) -> np.ndarray:
    return np.array([np.linalg.norm(truth[k].rotation().localCoordinates(
        pg.nodes[k].pose.rotation())) for k in range(len(truth))])


@pytest.mark.parametrize("mode", ["directions", "ignored", "inverted"])
def test_direction_factors_remove_rotation_drift(mode):
    truth, initial, odometry, cov, rng = _drifting_chain()
    pg = PoseGraph()
    for k, pose in enumerate(initial):
        pg.add_node(k, pose)
    for k, T in enumerate(odometry):
        pg.add_between(k, k + 1, T, cov)
    sigma = 0.005
    worlds = [np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])]  # corridor axis, vertical
    if mode != "ignored":
        for k, T in enumerate(truth):
            for d_world in worlds:
                measured = _unit(T.rotation().unrotate(d_world) + rng.normal(size=3) * sigma)
                cov_d = sigma**2 * (np.eye(3) - np.outer(measured, measured))
                if mode == "directions":
                    pg.add_direction(k, measured, d_world, cov_d)
                else:  # what a factor with its arguments swapped would do
                    pg.add_direction(k, d_world, measured, cov_d)
    drift_before = _rotation_errors(pg, truth)
    assert drift_before[-1] > 0.3  # 24 steps of 0.02 rad
    result = pg.optimize("lm")
    assert result.anchored_node == 0
    errors = _rotation_errors(pg, truth)
    if mode == "directions":
        assert errors.max() < 0.02, errors  # direction sigma 0.005, two per node
    else:
        assert errors.max() > 0.1, errors


def test_direction_factor_pickles():
    rng = np.random.default_rng(1)
    pg, record, T, _, _ = _one_direction(rng)
    factor = pickle.loads(pickle.dumps(record.factor))
    moved = _rotated_body(T, np.array([1.0, 0, 0]), 0.1)
    assert np.allclose(_unwhitened(record, moved), factor.unwhitenedError(
        _values(moved)), atol=1e-15)


def _values(T: gtsam.Pose3) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(node_key(0), T)
    return values


@pytest.mark.parametrize("args, message", [
    (([0, 0, 0], [1, 0, 0], np.eye(3)), "direction_sensor of the direction factor on node 0 "
                                         "is the zero vector"),
    (([1, 0], [1, 0, 0], np.eye(3)), r"direction_sensor .* shape \(3,\)"),
    (([1, 0, 0], [np.nan, 0, 0], np.eye(3)), "direction_world .* NaN"),
    (([1, 0, 0], [1, 0, 0], np.eye(2)), r"must be 3x3 \(sensor frame\)"),
    (([1, 0, 0], [1, 0, 0], -np.eye(3)), "not positive semi-definite"),
    (([1, 0, 0], [1, 0, 0], np.diag([1.0, 0.0, 0.0])), "no spread perpendicular"),
    (([1, 0, 0], [1, 0, 0], np.diag([0.0, 1.0, 0.0])), "no spread perpendicular"),
])
def test_add_direction_rejects_bad_input(args, message):
    pg = PoseGraph()
    pg.add_node(0, gtsam.Pose3())
    with pytest.raises(EstimationError, match=message):
        pg.add_direction(0, *args)
    with pytest.raises(EstimationError, match="unknown node 4"):
        pg.add_direction(4, [1, 0, 0], [1, 0, 0], np.eye(3))
    assert pg.factors == []
