"""perception.odometry: motion recovery on the simulated corridor, failures, covariance."""
from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from estimation.covariance import check_consistency, nees
from perception.errors import PerceptionError
from perception.odometry import (
    COV_CALIBRATION,
    OdometryConfig,
    covariance_model,
    floor_matrix,
    information_to_covariance,
    pnp_guess,
    rgbd_odometry,
)
from perception.rgbd import RgbdFrame
from perception.simulation.corridor import (
    CorridorConfig,
    build_corridor_scene,
    corridor_trajectory,
    render_frame,
)

# seed 5 was used neither for calibrating the covariance (6-11) nor for the benchmark (3, 4);
# a corridor like the calibration ones (15 m, 2 boxes), its first 22 pairs (5 m of walk).
# (On an 8 m corridor, whose end wall is in range for most frames, the VO errs less and the
# mean NEES is ~3.3: the calibrated covariance is conservative there.)
CONFIG = CorridorConfig(seed=5, length=15.0, clutter=2)
N_PAIRS = 22


@pytest.fixture(scope="module")
def frames():
    scene = build_corridor_scene(CONFIG)
    stamps, poses = corridor_trajectory(CONFIG)
    _, open_poses = corridor_trajectory(CONFIG, -CONFIG.exposure_time)   # motion blur
    rng = np.random.default_rng(55)
    out = []
    for k in range(N_PAIRS + 1):
        rgb, depth = render_frame(scene, poses[k], CONFIG.intrinsics, rng, open_poses[k])
        out.append(RgbdFrame(k, float(stamps[k]), rgb, depth, poses[k]))
    return out


@pytest.fixture(scope="module")
def results(frames):
    # the simulated corridor's own covariance model (COV_CALIBRATION)
    return [rgbd_odometry(frames[k], frames[k + 1], CONFIG.intrinsics,
                          config=OdometryConfig(cov_model="information"))
            for k in range(N_PAIRS)]


def _truth(frames, k):
    return frames[k].T_world_camera_gt.between(frames[k + 1].T_world_camera_gt)


def test_recovers_the_known_motion(frames, results):
    result = results[0]
    assert result.success and result.reason == "" and result.init == "pnp"
    error = result.T_prev_curr.localCoordinates(_truth(frames, 0))
    assert np.linalg.norm(error[3:]) < 0.01                       # < 1 cm of a 24 cm step
    # the simulated camera (vignetting, faint texture, 3.5 m depth) leaves ~2 mrad of pitch
    assert np.degrees(np.linalg.norm(error[:3])) < 0.3
    # counted on depth subsampled by 2 (information_stride): ~1/4 of the pixels
    assert result.correspondences > 5000 and result.ms > 0
    # Open3D's information is ordered [rotation, translation]: its translation block is
    # (number of correspondences) x identity, the rotation block depends on the points
    np.testing.assert_allclose(result.information[3:, 3:], result.correspondences * np.eye(3),
                               rtol=1e-6)
    assert not np.allclose(np.diag(result.information[:3, :3]), result.correspondences)
    np.testing.assert_allclose(result.cov, result.cov.T)
    assert np.all(np.linalg.eigvalsh(result.cov) > 0)
    for k, later in enumerate(results):
        assert later.success, later.reason
        error = later.T_prev_curr.localCoordinates(_truth(frames, k))
        assert np.linalg.norm(error[3:]) < 0.02


def test_dense_refinement_from_a_close_guess(frames):
    truth = _truth(frames, 2)
    guess = truth.compose(gtsam.Pose3(gtsam.Rot3.Ypr(0.003, 0, 0), np.array([0.01, 0, 0.02])))
    result = rgbd_odometry(frames[2], frames[3], CONFIG.intrinsics, guess,
                           OdometryConfig(pnp_init=False))
    assert result.success and result.init == "given"
    assert np.linalg.norm(result.T_prev_curr.localCoordinates(truth)[3:]) < 0.01


def test_pnp_guess_is_close(frames):
    guess, inliers = pnp_guess(frames[0], frames[1], CONFIG.intrinsics)
    assert inliers >= 15
    assert np.linalg.norm(guess.localCoordinates(_truth(frames, 0))[3:]) < 0.03


def test_blank_pair_fails_with_a_reason():
    intr = CONFIG.intrinsics
    blank = RgbdFrame(0, 0.0, np.zeros((intr.height, intr.width, 3), np.uint8),
                      np.zeros((intr.height, intr.width), np.float32))
    result = rgbd_odometry(blank, blank, intr)
    assert not result.success and "depth" in result.reason
    assert result.T_prev_curr.equals(gtsam.Pose3(), 0.0)
    np.testing.assert_allclose(np.diag(result.cov), [1.0] * 3 + [100.0] * 3)


def test_flat_wall_without_texture_fails():
    # a uniform grey fronto-parallel wall: depth everywhere, nothing to track
    intr = CONFIG.intrinsics
    wall = RgbdFrame(0, 0.0, np.full((intr.height, intr.width, 3), 128, np.uint8),
                     np.full((intr.height, intr.width), 2.0, np.float32))
    result = rgbd_odometry(wall, wall, intr, gtsam.Pose3(gtsam.Rot3(), np.array([0, 0, 5.0])))
    assert not result.success and result.reason


def test_frame_of_the_wrong_size_raises(frames):
    small = RgbdFrame(0, 0.0, np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10), np.float32))
    with pytest.raises(PerceptionError, match="do not match"):
        rgbd_odometry(frames[0], small, CONFIG.intrinsics)


def test_left_to_right_covariance_by_monte_carlo(rng):
    # xi_left ~ N(0, C): T = exp(xi_left) T_hat; GTSAM's tangent: T = T_hat exp(xi_right)
    A = rng.normal(size=(6, 6))
    cov_left = A @ A.T * 1e-4 + np.eye(6) * 1e-6
    T_hat = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([0.5, -1.0, 2.0]))
    config = OdometryConfig(cov_scale=1.0, cov_floor=(0.0,) * 6, cov_model="information")
    expected = information_to_covariance(np.linalg.inv(cov_left), T_hat, config)
    samples = rng.multivariate_normal(np.zeros(6), cov_left, size=4000)
    right = np.array([T_hat.localCoordinates(gtsam.Pose3.Expmap(xi).compose(T_hat))
                      for xi in samples])
    np.testing.assert_allclose(np.cov(right.T), expected, atol=0.08 * np.abs(expected).max())
    # the identity-transform control: without the adjoint the covariance would differ
    assert not np.allclose(np.cov(right.T), cov_left, atol=0.08 * np.abs(expected).max())


def test_covariance_is_consistent_with_the_errors(frames, results):
    errors = np.array([r.T_prev_curr.localCoordinates(_truth(frames, k))
                       for k, r in enumerate(results)])
    covs = np.array([r.cov for r in results])
    # the covariance was calibrated on other seeds (1, 2, 6, 7): 95 % chi-square bounds for
    # the mean NEES of these 16 pairs
    check = check_consistency(nees(errors, covs), dof=6)
    assert check.passed, check
    # mis-tuned controls must fail the same check: over- and under-confident by 10x
    assert not check_consistency(nees(errors, covs / 10), dof=6).passed
    assert not check_consistency(nees(errors, covs * 10), dof=6).passed


def test_covariance_model_follows_the_image_width_and_backend():
    table = COV_CALIBRATION[OdometryConfig().backend]
    assert covariance_model(640) == table[640]
    assert covariance_model(320) == table[320]
    assert covariance_model(1280) == table[640]    # nearest calibrated width
    assert covariance_model(300) == table[320]
    # a quarter of the pixels: the calibrated floor is larger on every axis
    tensor = COV_CALIBRATION["tensor"]
    assert np.all(np.diag(floor_matrix(tensor[320][1])) >= np.diag(floor_matrix(tensor[640][1])))
    for backend in ("tensor", "legacy"):
        calibration = COV_CALIBRATION[backend]
        assert covariance_model(640, OdometryConfig(backend=backend)) == calibration[640]
    # legacy is measured at 640 only: 320 takes it
    assert covariance_model(320, OdometryConfig(backend="legacy")) == COV_CALIBRATION[
        "legacy"][640]
    config = OdometryConfig(cov_scale=2.0)
    assert covariance_model(640, config) == (2.0, table[640][1])


def test_floor_matrix_accepts_sigmas_or_a_matrix():
    np.testing.assert_allclose(floor_matrix((1, 2, 3, 4, 5, 6)), np.diag([1, 4, 9, 16, 25, 36]))
    full = floor_matrix(COV_CALIBRATION["tensor"][640][1])
    assert np.all(np.linalg.eigvalsh(full) >= 0)
    # the calibrated floor couples pitch (camera rx) with vertical motion (camera ty)
    assert full[0, 4] / np.sqrt(full[0, 0] * full[4, 4]) > 0.9
    with pytest.raises(PerceptionError, match="6 sigmas or a 6x6"):
        floor_matrix((1.0, 2.0))


def test_tensor_and_legacy_backends_agree(frames):
    legacy = rgbd_odometry(frames[1], frames[2], CONFIG.intrinsics,
                           config=OdometryConfig(backend="legacy", iterations=(10, 5, 3)))
    tensor = rgbd_odometry(frames[1], frames[2], CONFIG.intrinsics,
                           config=OdometryConfig(cov_model="information"))
    assert legacy.success and tensor.success
    truth = _truth(frames, 1)
    for result in (legacy, tensor):
        assert np.linalg.norm(result.T_prev_curr.localCoordinates(truth)[3:]) < 0.02
    assert np.linalg.norm(legacy.T_prev_curr.localCoordinates(tensor.T_prev_curr)[3:]) < 0.02
    with pytest.raises(PerceptionError, match="unknown odometry method"):
        rgbd_odometry(frames[1], frames[2], CONFIG.intrinsics,
                      config=OdometryConfig(method="ransac"))


def test_coupled_covariance_keeps_the_motion_sigmas_and_adds_the_geometry_correlation():
    """The default VO covariance: motion-model sigmas, correlations shrunk from Open3D's
    information matrix (a fronto-parallel wall: pitch and vertical translation trade off)."""
    from perception.odometry import information_to_covariance, motion_covariance

    rng = np.random.default_rng(5)
    # information of unit-variance points on a wall at z = 2 m (left perturbation)
    points = np.column_stack([rng.uniform(-1, 1, 500), rng.uniform(-0.7, 0.7, 500),
                              np.full(500, 2.0)])
    J = np.zeros((len(points), 3, 6))
    for k, p in enumerate(points):
        J[k, :, :3] = -np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        J[k, :, 3:] = np.eye(3)
    info = np.einsum("kij,kil->jl", J, J)
    T = gtsam.Pose3(gtsam.Rot3.Rx(0.01), np.array([0.0, 0.0, 0.02]))
    motion = motion_covariance(T)
    off = information_to_covariance(info, T, OdometryConfig(cov_model="coupled", coupling=0.0))
    np.testing.assert_allclose(off, motion, rtol=1e-12)
    cov = information_to_covariance(info, T, OdometryConfig())  # default: coupled, 0.3
    np.testing.assert_allclose(np.diag(cov), np.diag(motion), rtol=1e-9)
    np.linalg.cholesky(cov)
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    # rotation about x and translation along y explain the same image motion: correlated
    # (nearly fully in the information; the default keeps COUPLING of it)
    from perception.odometry import COUPLING

    assert abs(corr[0, 4]) > 0.9 * COUPLING
    assert abs(corr[0, 5]) < 0.05  # depth translation is not
    with pytest.raises(PerceptionError):
        OdometryConfig(coupling=1.5)


ICL = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd" / "icl_of_kt0"


@pytest.mark.skipif(not ICL.is_dir(), reason="../shared/data/rgbd is missing")
def test_a_textureless_pair_runs_the_depth_weighted_odometry():
    """Real ICL-NUIM depth with the texture blurred away (Gaussian sigma 12 px, 10 % contrast):
    nothing to track, so the legacy hybrid (depth residual weighted ~30:1) replaces the tensor
    hybrid, which leans on the photometric term. Measured over 8 pairs: median translation
    error 2.4 mm with the fallback, 24 mm without it. With the texture, the tensor one runs."""
    import cv2

    from perception.rgbd import CameraIntrinsics, TumRgbdSequence

    intr = CameraIntrinsics(481.2, 480.0, 319.5, 239.5, 640, 480, 5000.0)
    sequence = TumRgbdSequence(ICL, intrinsics=intr)
    frames = [sequence[i] for i in range(30, 39)]

    def flat(frame):
        blurred = cv2.GaussianBlur(frame.rgb, (0, 0), 12).astype(np.float32)
        rgb = blurred.mean() + 0.1 * (blurred - blurred.mean())
        return RgbdFrame(frame.index, frame.timestamp, np.clip(rgb, 0, 255).astype(np.uint8),
                         frame.depth_m, frame.T_world_camera_gt)

    def errors(pairs, config):
        out = []
        for a, b in pairs:
            vo = rgbd_odometry(a, b, intr, config=config)
            assert vo.success, vo.reason
            truth = a.T_world_camera_gt.between(b.T_world_camera_gt)
            out.append((vo.backend, np.linalg.norm(vo.T_prev_curr.between(truth).translation())))
        return out

    textured = list(zip(frames[:-1], frames[1:]))
    assert {b for b, _ in errors(textured[:2], OdometryConfig())} == {"tensor"}
    blank = [(flat(a), flat(b)) for a, b in textured]
    fallback = errors(blank, OdometryConfig())
    tensor = errors(blank, OdometryConfig(textureless_fallback=False))
    assert {b for b, _ in fallback} == {"legacy-textureless"}
    assert {b for b, _ in tensor} == {"tensor"}
    median_fallback = np.median([e for _, e in fallback])
    median_tensor = np.median([e for _, e in tensor])
    assert median_fallback < 0.25 * median_tensor and median_fallback < 0.005
