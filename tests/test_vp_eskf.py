"""The error-state VP filter (estimation.vp_eskf): Jacobians, any world frame, consistency."""
from __future__ import annotations

import itertools

import gtsam
import numpy as np
import pytest

from estimation.covariance import chi2_bounds
from estimation.vp_ekf import VpEkfConfig
from estimation.vp_eskf import VanishingPointESKF, axis_jacobians, so3_exp

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def test_direction_jacobian_matches_numerical_derivative():
    rng = np.random.default_rng(0)
    R_wc = so3_exp(rng.normal(size=3))
    R_wm = so3_exp(rng.normal(size=3))
    for axis in range(3):
        d0, H = axis_jacobians(R_wc, R_wm, axis)
        numeric = np.zeros((3, 9))
        eps = 1e-7
        for k in range(9):
            dx = np.zeros(9)
            dx[k] = eps
            Rc = R_wc @ gtsam.Pose3.Expmap(dx[:6]).rotation().matrix()
            Rm = R_wm @ so3_exp(dx[6:])
            numeric[:, k] = ((Rc.T @ Rm)[:, axis] - d0) / eps
        np.testing.assert_allclose(H[:, :9], numeric, atol=1e-6)
        assert not H[:, 9:].any()  # the keyframe clone is not observed


def _rotations_every_90_deg():
    out = []
    for axis in range(3):
        for quarter in range(4):
            w = np.zeros(3)
            w[axis] = quarter * np.pi / 2
            out.append(so3_exp(w))
    return out


@pytest.mark.parametrize("R0", _rotations_every_90_deg())
def test_any_first_pose_filters_without_error(R0):
    """First poses at every 90 deg rotation about each axis (the paper's Euler state is
    singular at pitch +-90 deg; the default error state has no singular pose)."""
    T0 = gtsam.Pose3(gtsam.Rot3(R0), np.array([1.0, -2.0, 0.5]))
    R_wm = np.eye(3)
    f = VanishingPointESKF(K, T0, np.diag([1e-6] * 6), VpEkfConfig(vp_model="manhattan"))
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.01), np.array([0.0, 0.0, 0.05]))
    T = T0
    for _ in range(5):
        T = T.compose(step)
        f.predict_vo(step, np.diag([1e-6] * 3 + [1e-4] * 3))
        dirs = (T.rotation().matrix().T @ R_wm).T
        outcomes = f.update_directions(dirs)
        assert all(o.status in ("initialised", "updated") for o in outcomes)
    assert f.T_world_camera.equals(T, 1e-6)
    assert np.all(np.isfinite(f.P))


def test_reanchor_moves_the_estimate_and_keeps_the_covariance():
    rng = np.random.default_rng(1)
    f = VanishingPointESKF(K, gtsam.Pose3(), np.diag([1e-4] * 6),
                           VpEkfConfig(vp_model="manhattan"))
    f.update_directions(np.eye(3))
    f.predict_vo(gtsam.Pose3.Expmap(rng.normal(scale=0.1, size=6)), np.eye(6) * 1e-4)
    P, T, R_wm = f.P.copy(), f.T_world_camera, f.R_world_manhattan.copy()
    A = gtsam.Pose3.Expmap(rng.normal(size=6))
    f.reanchor(A)
    np.testing.assert_array_equal(f.P, P)
    assert f.T_world_camera.equals(A.compose(T), 1e-12)
    np.testing.assert_allclose(f.R_world_manhattan, A.rotation().matrix() @ R_wm, atol=1e-12)


def _nees_runs(model_scale: float, n_runs: int = 40, n_steps: int = 25) -> np.ndarray:
    """Mean pose NEES at the last step over seeded runs (directions with 2 mrad noise)."""
    sigma_dir = 2e-3
    cov_vo = np.diag([1e-3] * 3 + [5e-3] * 3) ** 2
    values = []
    for seed in range(n_runs):
        rng = np.random.default_rng(seed)
        R_wm = so3_exp(rng.normal(size=3))
        T = gtsam.Pose3()
        f = VanishingPointESKF(K, T, np.diag([1e-10] * 6),
                               VpEkfConfig(vp_model="manhattan", gate_chi2=np.inf,
                                           direction_sigma=sigma_dir))
        for _ in range(n_steps):
            U = gtsam.Pose3(gtsam.Rot3.Rz(0.02), np.array([0.02, 0.0, 0.1]))
            T = T.compose(U)
            U_meas = U.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov_vo)))
            f.predict_vo(U_meas, cov_vo * model_scale)
            dirs = (T.rotation().matrix().T @ R_wm).T
            noisy = []
            for d in dirs:
                n = d + rng.normal(scale=sigma_dir, size=3)
                noisy.append(n / np.linalg.norm(n))
            f.update_directions(np.array(noisy))
        err = f.T_world_camera.localCoordinates(T)
        values.append(err @ np.linalg.solve(f.pose_covariance(), err))
    return np.array(values)


def test_pose_covariance_is_consistent_and_a_mistuned_filter_fails():
    lo, hi = chi2_bounds(6, 40)
    nees = _nees_runs(1.0)
    assert lo <= nees.mean() <= hi, nees.mean()
    # negative control: a VO covariance 10x too small must fail the same check
    assert _nees_runs(0.1).mean() > hi


def test_predicting_from_the_previous_frame_as_keyframe_is_frame_to_frame():
    """set_keyframe + predict_from_keyframe(U) == predict_vo(U) on the camera and structure."""
    rng = np.random.default_rng(4)
    filters = []
    for _ in range(2):
        f = VanishingPointESKF(K, gtsam.Pose3(), np.diag([1e-4] * 6),
                               VpEkfConfig(vp_model="manhattan"))
        f.update_directions(np.eye(3))
        filters.append(f)
    a, b = filters
    for _ in range(3):
        U = gtsam.Pose3.Expmap(rng.normal(scale=0.1, size=6))
        cov = np.diag(rng.uniform(1e-5, 1e-3, size=6))
        a.predict_vo(U, cov)
        b.set_keyframe()
        b.predict_from_keyframe(U, cov)
        assert a.T_world_camera.equals(b.T_world_camera, 1e-12)
        np.testing.assert_allclose(a.P[:9, :9], b.P[:9, :9], rtol=1e-10, atol=1e-14)


def _keyframe_nees_runs(model_scale: float, n_runs: int = 40, n_steps: int = 24,
                        every: int = 4) -> np.ndarray:
    """Mean pose NEES at the last step: odometry against a keyframe every ``every`` frames,
    directions with 2 mrad noise, the keyframe cloned in the filter."""
    sigma_dir = 2e-3
    cov_vo = np.diag([1e-3] * 3 + [5e-3] * 3) ** 2
    values = []
    for seed in range(n_runs):
        rng = np.random.default_rng(100 + seed)
        R_wm = so3_exp(rng.normal(size=3))
        T = T_kf = gtsam.Pose3()
        f = VanishingPointESKF(K, T, np.diag([1e-10] * 6),
                               VpEkfConfig(vp_model="manhattan", gate_chi2=np.inf,
                                           direction_sigma=sigma_dir))
        for step in range(1, n_steps + 1):
            T = T.compose(gtsam.Pose3(gtsam.Rot3.Rz(0.02), np.array([0.02, 0.0, 0.1])))
            noise = gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov_vo))
            f.predict_from_keyframe(T_kf.between(T).compose(noise), cov_vo * model_scale)
            dirs = (T.rotation().matrix().T @ R_wm).T
            noisy = [d + rng.normal(scale=sigma_dir, size=3) for d in dirs]
            f.update_directions(np.array([n / np.linalg.norm(n) for n in noisy]))
            if step % every == 0:
                f.set_keyframe()
                T_kf = T
        err = f.T_world_camera.localCoordinates(T)
        values.append(err @ np.linalg.solve(f.pose_covariance(), err))
    return np.array(values)


def test_keyframe_odometry_is_consistent_and_a_mistuned_filter_fails():
    lo, hi = chi2_bounds(6, 40)
    nees = _keyframe_nees_runs(1.0)
    assert lo <= nees.mean() <= hi, nees.mean()
    assert _keyframe_nees_runs(0.1).mean() > hi


def test_keyframe_odometry_drifts_less_than_summing_its_increments():
    """The point of cloning: between keyframes the odometry's errors do not add up."""
    f = VanishingPointESKF(K, gtsam.Pose3(), np.diag([1e-10] * 6),
                           VpEkfConfig(vp_model="manhattan"))
    cov_vo = np.diag([1e-3] * 3 + [5e-3] * 3) ** 2
    T = gtsam.Pose3()
    for _ in range(8):  # 8 frames against one keyframe: one increment's uncertainty
        T = T.compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.05])))
        f.predict_from_keyframe(T, cov_vo)
    A = T.inverse().AdjointMap()
    np.testing.assert_allclose(f.pose_covariance(), cov_vo + A @ A.T * 1e-10, rtol=1e-9)


def test_gating_rejects_a_wrong_direction():
    f = VanishingPointESKF(K, gtsam.Pose3(), np.diag([1e-8] * 6),
                           VpEkfConfig(vp_model="manhattan", direction_sigma=1e-3))
    f.update_directions(np.eye(3))
    wrong = so3_exp(np.array([0.0, 0.0, np.deg2rad(8.0)]))[:, 0]  # 8 deg off axis x
    out = f.update_directions(wrong[None])
    assert out[0].status == "gated" and out[0].nis > 9.21


def test_level_rotation_puts_z_up_and_x_forward():
    from pipelines.vpslam import level_rotation

    rng = np.random.default_rng(3)
    for _ in range(20):
        # a tilted camera (x right, y down, z forward) in a level world, axes permuted
        tilt = so3_exp(rng.normal(scale=0.1, size=3))
        R_world_camera = tilt @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
        perm = list(itertools.permutations(range(3)))[rng.integers(6)]
        signs = rng.choice([-1.0, 1.0], 3)
        R_world_manhattan = np.eye(3)[:, perm] * signs
        R_new_old = level_rotation(R_world_camera, R_world_manhattan)
        np.testing.assert_allclose(R_new_old, np.eye(3), atol=1e-12)
