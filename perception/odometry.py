"""Frame-to-frame RGB-D visual odometry (Open3D's hybrid photometric + geometric odometry).

Open3D's ``compute_rgbd_odometry(source, target, ...)`` returns the transform that maps
source-camera points into the target camera, so with source = current and target = previous
it is ``T_prev_curr``. Its 6x6 information matrix is ordered [rotation, translation] (the
translation block is the number of correspondences times the identity) and belongs to a
*left* perturbation, T = exp(xi) T_hat, expressed in the previous camera's frame; GTSAM's
tangent space is the right perturbation T = T_hat exp(xi_r) with xi_r = Ad(T_hat^-1) xi, so
the covariance is carried over with the adjoint of T_hat^-1.

That information matrix counts every pixel as an independent unit-variance point, which is
far too confident; :class:`OdometryConfig` scales it by ``cov_scale`` (and adds a small floor)
calibrated on the simulated corridor so that the NEES against ground truth has mean ~6
(benchmarks/corridor_sim.py measures it).

The odometry converges only from a guess within a few centimetres along a monotonous
corridor (the photometric term has little to hold on to): pass the previous increment as
``T_init`` (constant velocity) when frames are 0.3 s apart.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from perception.errors import PerceptionError
from perception.rgbd import CameraIntrinsics, RgbdFrame


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of :func:`rgbd_odometry`.

    Attributes
    ----------
    iterations : tuple of int
        Gauss-Newton iterations per pyramid level, coarse to fine (Open3D's option).
    depth_diff_max : float
        Largest depth difference (m) of a correspondence.
    depth_min, depth_max : float
        Depth range (m) used.
    min_valid_fraction : float
        Below this share of valid depth pixels in either frame the pair fails.
    min_correspondences : int
        Below this many correspondences (from the information matrix) the pair fails.
    max_translation, max_rotation_deg : float
        Larger increments are reported as failures (divergence), m and degrees.
    cov_scale : float
        Multiplies inv(information) (calibrated on the simulated corridor).
    cov_floor : tuple of float
        Standard deviations (rad, m) added in quadrature to the diagonal
        [rotation, translation], so that no direction is trusted below this.
    failure_sigma : tuple of float
        Standard deviations (rad, m) of the covariance returned with a failure.
    """

    iterations: tuple[int, ...] = (20, 10, 5)
    depth_diff_max: float = 0.07
    depth_min: float = 0.3
    depth_max: float = 8.0
    min_valid_fraction: float = 0.05
    min_correspondences: int = 2000
    max_translation: float = 1.0
    max_rotation_deg: float = 30.0
    cov_scale: float = 1.0
    cov_floor: tuple[float, float] = (1e-4, 1e-3)
    failure_sigma: tuple[float, float] = (1.0, 10.0)


@dataclass(frozen=True)
class OdometryResult:
    """The relative motion between two RGB-D frames.

    Attributes
    ----------
    T_prev_curr : gtsam.Pose3
        Maps current-camera coordinates into the previous camera (the guess on failure).
    cov : np.ndarray
        (6, 6) covariance of T_prev_curr in GTSAM's tangent order [rotation, translation]
        (right perturbation, current-camera frame); very large on failure.
    success : bool
    reason : str
        "" on success, else why the pair failed.
    ms : float
        Wall time of the call in milliseconds.
    correspondences : int
        Number of pixel correspondences at the finest level (0 on failure).
    """

    T_prev_curr: gtsam.Pose3
    cov: np.ndarray
    success: bool
    reason: str
    ms: float
    correspondences: int = 0


def _failure(T_init: gtsam.Pose3, config: OdometryConfig, reason: str, start: float
             ) -> OdometryResult:
    sigma_rot, sigma_trans = config.failure_sigma
    cov = np.diag([sigma_rot ** 2] * 3 + [sigma_trans ** 2] * 3)
    return OdometryResult(T_init, cov, False, reason, (time.perf_counter() - start) * 1e3, 0)


def _check_frame(frame: RgbdFrame, intr: CameraIntrinsics, which: str) -> None:
    shape = (intr.height, intr.width)
    if frame.depth_m.shape != shape or frame.rgb.shape[:2] != shape:
        raise PerceptionError(f"{which} frame: rgb {frame.rgb.shape} / depth "
                              f"{frame.depth_m.shape} do not match the camera's {shape}")
    if frame.rgb.ndim != 3 or frame.rgb.shape[2] != 3 or frame.rgb.dtype != np.uint8:
        raise PerceptionError(f"{which} frame: rgb must be (H, W, 3) uint8")


def information_to_covariance(info: np.ndarray, T_prev_curr: gtsam.Pose3,
                              config: OdometryConfig = OdometryConfig()) -> np.ndarray:
    """Return the GTSAM-order right-perturbation covariance from Open3D's information matrix.

    cov_left = cov_scale * inv(info) (left perturbation in the previous camera frame),
    cov = Ad(T^-1) cov_left Ad(T^-1)^T, plus the diagonal floor.
    """
    cov_left = config.cov_scale * np.linalg.inv(info)
    adjoint = T_prev_curr.inverse().AdjointMap()
    cov = adjoint @ cov_left @ adjoint.T
    floor_rot, floor_trans = config.cov_floor
    cov = cov + np.diag([floor_rot ** 2] * 3 + [floor_trans ** 2] * 3)
    return 0.5 * (cov + cov.T)


def rgbd_odometry(prev: RgbdFrame, curr: RgbdFrame, intr: CameraIntrinsics,
                  T_init: gtsam.Pose3 | None = None,
                  config: OdometryConfig = OdometryConfig()) -> OdometryResult:
    """Return T_prev_curr, its covariance and a success flag from two RGB-D frames.

    Parameters
    ----------
    prev, curr : RgbdFrame
        Consecutive frames (rgb uint8, depth_m float32 metres, 0 = invalid).
    intr : CameraIntrinsics
    T_init : gtsam.Pose3, optional
        Initial guess of T_prev_curr (identity by default); pass the previous increment
        when the camera moves more than a few centimetres per frame.
    config : OdometryConfig

    Failures (too few depth pixels, no convergence, too few correspondences, implausible
    motion, singular information) return ``success=False`` with the reason, the guess as
    the pose and a very large covariance; never an exception. Frames that do not match the
    camera size raise PerceptionError.
    """
    import open3d as o3d

    start = time.perf_counter()
    T_init = gtsam.Pose3() if T_init is None else T_init
    _check_frame(prev, intr, "previous")
    _check_frame(curr, intr, "current")
    for which, frame in (("previous", prev), ("current", curr)):
        depth = frame.depth_m
        valid = np.count_nonzero(np.isfinite(depth) & (depth > config.depth_min)
                                 & (depth < config.depth_max))
        if valid < config.min_valid_fraction * depth.size:
            return _failure(T_init, config, f"too few valid depth pixels in the {which} frame "
                                            f"({valid})", start)

    def rgbd_image(frame: RgbdFrame):
        depth = np.where(np.isfinite(frame.depth_m), frame.depth_m, 0).astype(np.float32)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(frame.rgb)), o3d.geometry.Image(depth),
            depth_scale=1.0, depth_trunc=config.depth_max, convert_rgb_to_intensity=True)

    pinhole = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy,
                                                intr.cx, intr.cy)
    option = o3d.pipelines.odometry.OdometryOption(
        iteration_number_per_pyramid_level=o3d.utility.IntVector(list(config.iterations)),
        depth_diff_max=config.depth_diff_max, depth_min=config.depth_min,
        depth_max=config.depth_max)
    # source = current, target = previous: Open3D's result maps source into target
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok, T, info = o3d.pipelines.odometry.compute_rgbd_odometry(
            rgbd_image(curr), rgbd_image(prev), pinhole, T_init.matrix(),
            o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), option)
    if not ok:
        return _failure(T_init, config, "Open3D odometry did not converge", start)
    correspondences = int(round(info[5, 5]))
    if correspondences < config.min_correspondences:
        return _failure(T_init, config, f"too few correspondences ({correspondences})", start)
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(info))):
        return _failure(T_init, config, "non-finite motion or information", start)
    # re-orthonormalise: Open3D accumulates small increments in double precision
    T_prev_curr = gtsam.Pose3(gtsam.Rot3.ClosestTo(T[:3, :3]), T[:3, 3])
    angle = np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(T_prev_curr.rotation())))
    distance = float(np.linalg.norm(T_prev_curr.translation()))
    if distance > config.max_translation or angle > config.max_rotation_deg:
        return _failure(T_init, config, f"implausible motion ({distance:.2f} m, "
                                        f"{angle:.1f} deg)", start)
    if np.linalg.cond(info) > 1e12:
        return _failure(T_init, config, "singular information matrix", start)
    cov = information_to_covariance(info, T_prev_curr, config)
    return OdometryResult(T_prev_curr, cov, True, "", (time.perf_counter() - start) * 1e3,
                          correspondences)
