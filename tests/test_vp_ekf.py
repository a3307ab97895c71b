"""VP-EKF: analytic Jacobians vs numerical, NEES/NIS Monte Carlo with a negative control."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.covariance import check_consistency
from estimation.errors import EstimationError
from estimation.geometry import R_BODY_CAMERA, euler_to_matrix, matrix_to_euler, wrap_angle
from estimation.vp_ekf import (
    VanishingPointEKF,
    VpEkfConfig,
    camera_rotation,
    direction_jacobian,
    direction_observation,
    manhattan_jacobian,
    manhattan_observation,
    motion_jacobians,
    motion_model,
    state_from_tangent_jacobian,
    tangent_from_state_jacobian,
    vp_point_from_pixel,
    vp_point_jacobian,
    vp_point_observation,
)

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
SIGMA_PX = 1.5
COV_VO = np.diag([0.002 ** 2] * 3 + [0.01 ** 2] * 3)   # [rot, trans] per step
COV_POSE0 = np.diag([0.002 ** 2] * 3 + [0.01 ** 2] * 3)


def numerical_jacobian(f, x, h=1e-6):
    f0 = np.asarray(f(x))
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros(x.size)
        dx[i] = h
        J[:, i] = (np.asarray(f(x + dx)) - np.asarray(f(x - dx))).reshape(-1) / (2 * h)
    return J


def random_state(rng):
    # a forward-looking camera (body x towards the VP point), moderate attitude
    return np.r_[rng.normal(size=3), rng.uniform(-0.6, 0.6, 3),
                 30.0 + rng.normal(), rng.normal(size=2)]


def random_increment(rng):
    return gtsam.Rot3.Expmap(rng.normal(scale=0.1, size=3)).matrix(), rng.normal(scale=0.3, size=3)


# ----------------------------------------------------------------------- Jacobians

def test_motion_jacobian_G_matches_numerical(rng):
    for _ in range(20):
        x = random_state(rng)
        dR, dt = random_increment(rng)
        G, _ = motion_jacobians(x, dR, dt)
        num = numerical_jacobian(lambda s, dR=dR, dt=dt: motion_model(s, dR, dt), x)
        np.testing.assert_allclose(G, num, atol=1e-7)


def test_motion_noise_jacobian_V_matches_numerical(rng):
    for _ in range(20):
        x = random_state(rng)
        dR, dt = random_increment(rng)
        _, V = motion_jacobians(x, dR, dt)
        u = gtsam.Pose3(gtsam.Rot3(dR), dt)

        def g_of_xi(xi, u=u, x=x):
            v = u.compose(gtsam.Pose3.Expmap(xi))
            return motion_model(x, v.rotation().matrix(), v.translation())

        np.testing.assert_allclose(V, numerical_jacobian(g_of_xi, np.zeros(6)), atol=1e-7)


def test_observation_jacobian_H_matches_numerical(rng):
    for _ in range(20):
        x = random_state(rng)
        H = vp_point_jacobian(x, K)
        num = numerical_jacobian(lambda s: vp_point_observation(s, K), x)
        np.testing.assert_allclose(H, num, rtol=1e-6, atol=1e-5)


def test_direction_jacobian_matches_numerical(rng):
    for _ in range(20):
        x = random_state(rng)
        w = rng.normal(size=3)
        w /= np.linalg.norm(w)
        num = numerical_jacobian(lambda s, w=w: direction_observation(s, w), x)
        np.testing.assert_allclose(direction_jacobian(x, w), num, atol=1e-8)


def test_manhattan_jacobian_matches_numerical(rng):
    for _ in range(20):
        x = random_state(rng)
        x[6:9] = rng.normal(scale=0.3, size=3)  # the Manhattan frame's correction delta
        R0 = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
        for axis in range(3):
            num = numerical_jacobian(lambda s, a=axis, R0=R0: manhattan_observation(s, R0, a), x)
            np.testing.assert_allclose(manhattan_jacobian(x, R0, axis), num, atol=1e-8)


def test_vp_init_jacobians_match_numerical(rng):
    for _ in range(10):
        x = random_state(rng)
        uv = rng.uniform([100, 100], [500, 400])
        init = vp_point_from_pixel(x, uv, K, 40.0)
        assert np.linalg.norm(init.point - x[:3]) == pytest.approx(40.0)
        num_pose = numerical_jacobian(
            lambda s, x=x, uv=uv: vp_point_from_pixel(np.r_[s, x[6:]], uv, K, 40.0).point, x[:6])
        num_uv = numerical_jacobian(lambda z, x=x: vp_point_from_pixel(x, z, K, 40.0).point, uv,
                                    h=1e-4)
        np.testing.assert_allclose(init.J_pose, num_pose, atol=1e-6)
        np.testing.assert_allclose(init.J_uv, num_uv, atol=1e-6)
        # back-projection then projection returns the pixel
        np.testing.assert_allclose(vp_point_observation(np.r_[x[:6], init.point], K), uv,
                                   atol=1e-8)


def test_tangent_jacobian_matches_local_coordinates(rng):
    for _ in range(10):
        x = random_state(rng)

        def camera_pose(s):
            return gtsam.Pose3(gtsam.Rot3(camera_rotation(s)), s[:3])

        T0 = camera_pose(x)
        num = numerical_jacobian(
            lambda s, T0=T0, x=x: T0.localCoordinates(camera_pose(np.r_[s, x[6:]])), x[:6])
        J = tangent_from_state_jacobian(x)
        np.testing.assert_allclose(J, num, atol=1e-7)
        np.testing.assert_allclose(J @ state_from_tangent_jacobian(x), np.eye(6), atol=1e-12)


def test_initial_pose_and_covariance_round_trip(rng):
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.3), rng.normal(size=3))
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-3 + np.eye(6) * 1e-4
    ekf = VanishingPointEKF(K, T, cov)
    assert ekf.T_world_camera.equals(T, 1e-12)
    np.testing.assert_allclose(ekf.pose_covariance(), cov, atol=1e-12)


# ----------------------------------------------------------------------- filter behaviour

def corridor_poses(n_steps):
    """True camera poses: 0.24 m steps along world x, zigzag in y and yaw, small z/pitch/roll."""
    k = np.arange(n_steps + 1)
    pos = np.column_stack([0.24 * k, 0.3 * np.sin(2 * np.pi * k / 12),
                           1.2 + 0.03 * np.sin(2 * np.pi * k / 17)])
    euler = np.column_stack([0.02 * np.sin(2 * np.pi * k / 9), 0.03 * np.sin(2 * np.pi * k / 15),
                             0.2 * np.cos(2 * np.pi * k / 12)])
    return [gtsam.Pose3(gtsam.Rot3(euler_to_matrix(e) @ R_BODY_CAMERA), p)
            for p, e in zip(pos, euler)]


def pose_error(T_world_camera_true, ekf):
    x_true = np.r_[T_world_camera_true.translation(),
                   matrix_to_euler(T_world_camera_true.rotation().matrix() @ R_BODY_CAMERA.T)]
    err = x_true - ekf.x[:6, 0]
    err[3:] = wrap_angle(err[3:])
    return err


def monte_carlo_run(rng, n_steps, process_scale=1.0, distance=60.0, range_sigma=3.0):
    """One run on simulated VO increments and VP pixels; returns (NEES (n,), NIS (n,))."""
    poses = corridor_poses(n_steps)
    T0 = poses[0].compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), COV_POSE0)))
    config = VpEkfConfig(vp_distance=distance, vp_range_sigma=range_sigma, gate_chi2=np.inf)
    ekf = VanishingPointEKF(K, T0, COV_POSE0, config)
    direction = np.array([1.0, 0.02, 0.01]) / np.linalg.norm([1.0, 0.02, 0.01])
    vp_world = poses[0].translation() + rng.normal(distance, range_sigma) * direction
    cov_px = np.eye(2) * SIGMA_PX ** 2

    def measure(T):
        q = K @ (T.rotation().matrix().T @ (vp_world - T.translation()))
        return q[:2] / q[2] + rng.normal(0.0, SIGMA_PX, 2)

    assert ekf.update_vp(measure(poses[0]), cov_px).status == "initialised"
    nees_steps, nis_steps = [], []
    for k in range(1, n_steps + 1):
        xi = rng.multivariate_normal(np.zeros(6), COV_VO)
        increment = poses[k - 1].between(poses[k]).compose(gtsam.Pose3.Expmap(xi))
        ekf.predict_vo(increment, COV_VO * process_scale)
        outcome = ekf.update_vp(measure(poses[k]), cov_px)
        assert outcome.status == "updated"
        assert ekf.x.shape == (9, 1)
        nis_steps.append(outcome.nis)
        err = pose_error(poses[k], ekf)
        nees_steps.append(err @ np.linalg.solve(ekf.P[:6, :6], err))
    return np.array(nees_steps), np.array(nis_steps)


def monte_carlo(seed, n_runs, n_steps=60, process_scale=1.0):
    rng = np.random.default_rng(seed)
    runs = [monte_carlo_run(rng, n_steps, process_scale) for _ in range(n_runs)]
    return np.array([r[0] for r in runs]), np.array([r[1] for r in runs])


def test_nees_and_nis_consistent_over_100_runs():
    nees_values, nis_values = monte_carlo(seed=3, n_runs=100)
    nees_check = check_consistency(nees_values, dof=6)
    nis_check = check_consistency(nis_values, dof=2)
    assert nees_check.passed, nees_check
    assert nis_check.passed, nis_check
    assert nees_check.fraction_inside >= 0.9 and nis_check.fraction_inside >= 0.9


def test_negative_control_underestimated_process_noise_fails():
    nees_values, nis_values = monte_carlo(seed=3, n_runs=50, n_steps=30, process_scale=0.05)
    assert not check_consistency(nees_values, dof=6).passed
    assert not check_consistency(nis_values, dof=2).passed


def test_outlier_is_gated_and_state_unchanged(rng):
    poses = corridor_poses(2)
    ekf = VanishingPointEKF(K, poses[0], COV_POSE0, VpEkfConfig(vp_distance=60.0))
    ekf.update_vp(np.array([330.0, 240.0]), np.eye(2))
    ekf.predict_vo(poses[0].between(poses[1]), COV_VO)
    x_before, P_before = ekf.x.copy(), ekf.P.copy()
    predicted = vp_point_observation(ekf.x, K)
    outcome = ekf.update_vp(predicted + [200.0, -150.0], np.eye(2) * 4.0)
    assert outcome.status == "gated" and outcome.nis > ekf.config.gate_chi2
    np.testing.assert_array_equal(ekf.x, x_before)
    np.testing.assert_array_equal(ekf.P, P_before)
    inlier = ekf.update_vp(predicted + [1.0, -1.0], np.eye(2) * 4.0)
    assert inlier.status == "updated"
    assert np.trace(ekf.P[:6, :6]) < np.trace(P_before[:6, :6])


def test_lost_frames_grow_covariance_and_never_crash():
    ekf = VanishingPointEKF(K, corridor_poses(0)[0], COV_POSE0)
    traces = []
    for _ in range(50):  # VO failed and no VP for 50 frames
        ekf.predict_lost()
        traces.append(np.trace(ekf.P[:6, :6]))
        np.linalg.cholesky(ekf.P)
    assert np.all(np.diff(traces) > 0)
    assert ekf.update_vp(None, np.eye(2)).status == "skipped"


def test_default_start_is_body_identity():
    ekf = VanishingPointEKF(K)
    np.testing.assert_allclose(ekf.x[:, 0], np.zeros(9), atol=1e-12)
    np.testing.assert_allclose(ekf.T_world_camera.rotation().matrix(), R_BODY_CAMERA)


def test_bad_inputs_raise_estimation_error():
    ekf = VanishingPointEKF(K)
    with pytest.raises(EstimationError):
        ekf.predict_vo(np.eye(4), np.full((6, 6), np.nan))
    with pytest.raises(EstimationError):
        ekf.update_vp(np.array([300.0, 200.0]), -np.eye(2))
    with pytest.raises(EstimationError):
        VpEkfConfig(vp_model="lines")


def test_yaw_wraps_across_pi():
    T = gtsam.Pose3(gtsam.Rot3(euler_to_matrix([0.0, 0.0, np.pi - 0.01]) @ R_BODY_CAMERA),
                    np.zeros(3))
    ekf = VanishingPointEKF(K, T, COV_POSE0)
    turn = gtsam.Pose3(gtsam.Rot3(R_BODY_CAMERA.T @ euler_to_matrix([0, 0, 0.05]) @ R_BODY_CAMERA),
                       np.zeros(3))
    ekf.predict_vo(turn, COV_VO)
    assert ekf.x[5, 0] == pytest.approx(-np.pi + 0.04, abs=1e-9)
    expected = T.compose(turn)
    assert ekf.T_world_camera.equals(expected, 1e-9)


def test_manhattan_directions_correct_roll_that_one_point_cannot():
    """Three orthogonal VPs observe the full rotation; one VP point leaves roll drifting."""
    rng = np.random.default_rng(7)
    n_steps = 60
    poses = corridor_poses(n_steps)
    sigma_dir = 0.003
    roll_errors = {}
    statuses = []
    for model in ("point", "manhattan"):
        errors = []
        for _ in range(8):
            config = VpEkfConfig(vp_model=model, vp_distance=1000.0, direction_sigma=sigma_dir)
            ekf = VanishingPointEKF(K, poses[0], COV_POSE0, config)
            for k in range(n_steps + 1):
                if k > 0:
                    xi = rng.multivariate_normal(np.zeros(6), COV_VO)
                    ekf.predict_vo(poses[k - 1].between(poses[k]).compose(gtsam.Pose3.Expmap(xi)),
                                   COV_VO)
                R_cw = poses[k].rotation().matrix().T
                dirs = (R_cw @ np.eye(3)).T  # the world x, y, z axes seen from the camera
                dirs = dirs + rng.normal(0.0, sigma_dir, dirs.shape)
                dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
                if model == "manhattan":
                    outcomes = ekf.update_directions(dirs)
                    statuses.extend(o.status for o in outcomes)
                else:
                    q = K @ dirs[0]
                    ekf.update_vp(q[:2] / q[2] + rng.normal(0, SIGMA_PX, 2),
                                  np.eye(2) * SIGMA_PX ** 2)
            errors.append(pose_error(poses[-1], ekf)[3])
        roll_errors[model] = np.sqrt(np.mean(np.square(errors)))
    assert statuses.count("initialised") == 3 * 8
    assert statuses.count("updated") >= 0.95 * 3 * 8 * n_steps
    # Manhattan: bounded by the first frame's error (~3.6 mrad); point: a random walk
    # (2 mrad per step * sqrt(60) ~ 15 mrad).
    assert roll_errors["manhattan"] < 0.006
    assert roll_errors["manhattan"] < 0.5 * roll_errors["point"]


def manhattan_run(rng, n_steps, process_scale=1.0, sigma_dir=0.003):
    """One Manhattan run; returns (pose NEES (n,), summed NIS of the three axes (n,))."""
    poses = corridor_poses(n_steps)
    T0 = poses[0].compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), COV_POSE0)))
    config = VpEkfConfig(vp_model="manhattan", direction_sigma=sigma_dir, gate_chi2=np.inf)
    ekf = VanishingPointEKF(K, T0, COV_POSE0, config)

    def measure(T):
        dirs = (T.rotation().matrix().T @ np.eye(3)).T  # world axes in the camera
        dirs = dirs + rng.normal(0.0, sigma_dir, dirs.shape)
        return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)

    assert {o.status for o in ekf.update_directions(measure(poses[0]))} == {"initialised"}
    nees_steps, nis_steps = [], []
    for k in range(1, n_steps + 1):
        xi = rng.multivariate_normal(np.zeros(6), COV_VO)
        ekf.predict_vo(poses[k - 1].between(poses[k]).compose(gtsam.Pose3.Expmap(xi)),
                       COV_VO * process_scale)
        outcomes = ekf.update_directions(measure(poses[k]))
        assert [o.status for o in outcomes] == ["updated"] * 3
        nis_steps.append(sum(o.nis for o in outcomes))
        err = pose_error(poses[k], ekf)
        nees_steps.append(err @ np.linalg.solve(ekf.P[:6, :6], err))
    return np.array(nees_steps), np.array(nis_steps)


@pytest.mark.parametrize("process_scale, consistent", [(1.0, True), (0.05, False)])
def test_manhattan_nees_nis_with_negative_control(process_scale, consistent):
    rng = np.random.default_rng(11)
    runs = [manhattan_run(rng, 25, process_scale) for _ in range(50)]
    nees_check = check_consistency(np.array([r[0] for r in runs]), dof=6)
    nis_check = check_consistency(np.array([r[1] for r in runs]), dof=6)  # 3 axes x 2 dof
    if consistent:
        assert nees_check.passed, nees_check
        assert nis_check.passed, nis_check
    else:
        assert not nees_check.passed and not nis_check.passed
