"""Frame-to-frame RGB-D visual odometry (Open3D's hybrid photometric + geometric odometry).

Open3D's ``compute_rgbd_odometry(source, target, ...)`` returns the transform that maps
source-camera points into the target camera, so with source = current and target = previous
it is ``T_prev_curr``. Its 6x6 information matrix is ordered [rotation, translation] (the
translation block is the number of correspondences times the identity) and belongs to a
*left* perturbation, T = exp(xi) T_hat, expressed in the previous camera's frame; GTSAM's
tangent space is the right perturbation T = T_hat exp(xi_r) with xi_r = Ad(T_hat^-1) xi, so
the covariance is carried over with the adjoint of T_hat^-1.

That information matrix counts every pixel as an independent unit-variance point, which is
badly shaped for a corridor (rotation and lateral motion look 15x worse than they are,
forward motion better); it is scaled and given a per-axis floor calibrated on the simulated
corridor for 640- and 320-pixel-wide images (:data:`COV_CALIBRATION`) so that the NEES
against ground truth is close to its chi-square mean of 6 (benchmarks/corridor_sim.py
measures it on other seeds).

Open3D's dense odometry converges only from a guess within a few centimetres along a
monotonous corridor (with 0.24 m steps from identity it settles on ~zero forward motion and
still reports success), so the guess comes from sparse features first: Shi-Tomasi corners
of the previous image, pyramidal Lucas-Kanade tracks (forward-backward checked), their
previous-frame depth and ``cv2.solvePnPRansac``. When that fails, the caller's ``T_init``
(e.g. constant velocity) or the identity is used.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from perception.errors import PerceptionError
from perception.rgbd import CameraIntrinsics, RgbdFrame

# (cov_scale, cov_floor) per image width, fitted on the simulated corridor (seeds 1, 2, 6, 7;
# 15 m, 2 clutter boxes; 640x480 renders, resized with INTER_AREA / INTER_NEAREST for 320).
# Open3D's point-to-point information overstates the rotation and lateral uncertainty ~15x
# and understates the forward one, so it is scaled down and a per-axis floor is added; the
# large tz floor (along the optical axis) is the forward-motion error that photometric
# odometry makes in a monotonous corridor. Fitted so that each axis and the 6-dof NEES have
# their chi-square means; at 640 one gross 1.2 cm vertical outlier (NEES ~200) of the 208
# pairs was left out of the fit (it is for the filter's gate). Errors are heavy-tailed:
# ~10 % of the pairs lie above the 95 % chi-square quantile on the fitting set.
COV_CALIBRATION: dict[int, tuple[float, tuple[float, ...]]] = {
    640: (0.00244, (8.1e-5, 5.9e-5, 9e-6, 1.54e-4, 2.47e-4, 2.21e-3)),
    320: (0.00258, (2.64e-4, 2.0e-4, 9e-6, 5.94e-4, 1.33e-3, 6.93e-3)),
}


def covariance_model(width: int, config: OdometryConfig | None = None
                     ) -> tuple[float, tuple[float, ...]]:
    """Return (cov_scale, cov_floor): the config's, else the calibration of the nearest width.

    Widths between or beyond the calibrated ones take the nearest (in log ratio): the model
    is only measured at the calibrated widths.
    """
    nearest = min(COV_CALIBRATION, key=lambda w: abs(np.log(w / max(width, 1))))
    scale, floor = COV_CALIBRATION[nearest]
    if config is not None and config.cov_scale is not None:
        scale = config.cov_scale
    if config is not None and config.cov_floor is not None:
        floor = config.cov_floor
    return scale, tuple(floor)


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
    cov_scale : float or None
        Multiplies inv(information); None: from :data:`COV_CALIBRATION` for the image width.
    cov_floor : tuple of 6 float or None
        Standard deviations [rx, ry, rz (rad), tx, ty, tz (m)] in the current camera frame
        added in quadrature to the diagonal; None: from :data:`COV_CALIBRATION`.
    failure_sigma : tuple of float
        Standard deviations (rad, m) of the covariance returned with a failure.
    pnp_init : bool
        Initialise from features + PnP (else from ``T_init``).
    pnp_min_inliers : int
        Fewer PnP inliers fall back to ``T_init``.
    max_disagreement : tuple of float
        (m, degrees): a dense result further than this from the PnP guess is a failure
        (the dense refinement slid along the corridor).
    """

    iterations: tuple[int, ...] = (20, 10, 5)
    depth_diff_max: float = 0.07
    depth_min: float = 0.3
    depth_max: float = 8.0
    min_valid_fraction: float = 0.05
    min_correspondences: int = 2000
    max_translation: float = 1.0
    max_rotation_deg: float = 30.0
    cov_scale: float | None = None
    cov_floor: tuple[float, ...] | None = None
    failure_sigma: tuple[float, float] = (1.0, 10.0)
    pnp_init: bool = True
    pnp_min_inliers: int = 15
    max_disagreement: tuple[float, float] = (0.05, 3.0)


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
    init : str
        Where the dense odometry started: "pnp", "given" (T_init) or "identity".
    information : np.ndarray or None
        Open3D's raw 6x6 information matrix ([rotation, translation], left perturbation in
        the previous camera frame, unit-variance points); None on failure.
    """

    T_prev_curr: gtsam.Pose3
    cov: np.ndarray
    success: bool
    reason: str
    ms: float
    correspondences: int = 0
    init: str = "identity"
    information: np.ndarray | None = None


def _failure(T_init: gtsam.Pose3, config: OdometryConfig, reason: str, start: float,
             init: str = "identity") -> OdometryResult:
    sigma_rot, sigma_trans = config.failure_sigma
    cov = np.diag([sigma_rot ** 2] * 3 + [sigma_trans ** 2] * 3)
    return OdometryResult(T_init, cov, False, reason, (time.perf_counter() - start) * 1e3, 0,
                          init)


def pnp_guess(prev: RgbdFrame, curr: RgbdFrame, intr: CameraIntrinsics,
              config: OdometryConfig = OdometryConfig()) -> tuple[gtsam.Pose3 | None, int]:
    """Return (T_prev_curr or None, PnP inliers) from tracked corners and previous depth."""
    import cv2

    gray_prev = cv2.cvtColor(prev.rgb, cv2.COLOR_RGB2GRAY)
    gray_curr = cv2.cvtColor(curr.rgb, cv2.COLOR_RGB2GRAY)
    depth = prev.depth_m
    mask = (np.isfinite(depth) & (depth > config.depth_min) & (depth < config.depth_max))
    # a low quality level: one strong door corner must not suppress the faint texture corners
    corners = cv2.goodFeaturesToTrack(gray_prev, 500, 0.001, 8, mask=mask.astype(np.uint8))
    if corners is None or len(corners) < config.pnp_min_inliers:
        return None, 0
    lk = dict(winSize=(21, 21), maxLevel=4)
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(gray_prev, gray_curr, corners, None, **lk)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray_curr, gray_prev, tracked, None, **lk)
    good = ((status[:, 0] == 1) & (status_back[:, 0] == 1)
            & (np.linalg.norm(back - corners, axis=2)[:, 0] < 1.0))
    if np.count_nonzero(good) < config.pnp_min_inliers:
        return None, 0
    uv_prev = corners[good, 0].astype(np.float64)
    uv_curr = tracked[good, 0].astype(np.float64)
    cols = np.clip(np.rint(uv_prev[:, 0]).astype(int), 0, intr.width - 1)
    rows = np.clip(np.rint(uv_prev[:, 1]).astype(int), 0, intr.height - 1)
    z = depth[rows, cols].astype(np.float64)
    keep = mask[rows, cols]
    points_prev = np.stack([(uv_prev[:, 0] - intr.cx) * z / intr.fx,
                            (uv_prev[:, 1] - intr.cy) * z / intr.fy, z], axis=1)[keep]
    if points_prev.shape[0] < config.pnp_min_inliers:
        return None, 0
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points_prev, uv_curr[keep], intr.K, None,
                                                 reprojectionError=2.0, iterationsCount=100)
    n_inliers = 0 if inliers is None else len(inliers)
    if not ok or n_inliers < config.pnp_min_inliers:
        return None, n_inliers
    rotation, _ = cv2.Rodrigues(rvec)
    # solvePnP gives T_curr_prev (previous-frame points into the current camera)
    T_curr_prev = gtsam.Pose3(gtsam.Rot3.ClosestTo(rotation), tvec.ravel())
    return T_curr_prev.inverse(), n_inliers


def _check_frame(frame: RgbdFrame, intr: CameraIntrinsics, which: str) -> None:
    shape = (intr.height, intr.width)
    if frame.depth_m.shape != shape or frame.rgb.shape[:2] != shape:
        raise PerceptionError(f"{which} frame: rgb {frame.rgb.shape} / depth "
                              f"{frame.depth_m.shape} do not match the camera's {shape}")
    if frame.rgb.ndim != 3 or frame.rgb.shape[2] != 3 or frame.rgb.dtype != np.uint8:
        raise PerceptionError(f"{which} frame: rgb must be (H, W, 3) uint8")


def information_to_covariance(info: np.ndarray, T_prev_curr: gtsam.Pose3,
                              config: OdometryConfig | None = None, width: int = 640
                              ) -> np.ndarray:
    """Return the GTSAM-order right-perturbation covariance from Open3D's information matrix.

    cov_left = cov_scale * inv(info) (left perturbation in the previous camera frame),
    cov = Ad(T^-1) cov_left Ad(T^-1)^T, plus the diagonal floor; scale and floor from
    ``config`` or, when it leaves them None, from :data:`COV_CALIBRATION` for ``width``.
    """
    cov_scale, cov_floor = covariance_model(width, config)
    cov_left = cov_scale * np.linalg.inv(info)
    adjoint = T_prev_curr.inverse().AdjointMap()
    cov = adjoint @ cov_left @ adjoint.T
    cov = cov + np.diag(np.square(np.asarray(cov_floor, dtype=float)))
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
        Guess of T_prev_curr used when the feature + PnP guess fails or is disabled
        (``config.pnp_init``); identity by default. Pass the previous increment (constant
        velocity) when the camera moves more than a few centimetres per frame.
    config : OdometryConfig

    Failures (too few depth pixels, no convergence, too few correspondences, implausible
    motion, dense result far from the PnP guess, singular information) return
    ``success=False`` with the reason, the guess (PnP's if it had one, else ``T_init``) as
    the pose and a very large covariance; never an exception. Frames that do not match the
    camera size raise PerceptionError.
    """
    import open3d as o3d

    start = time.perf_counter()
    init = "identity" if T_init is None else "given"
    T_init = gtsam.Pose3() if T_init is None else T_init
    _check_frame(prev, intr, "previous")
    _check_frame(curr, intr, "current")
    for which, frame in (("previous", prev), ("current", curr)):
        depth = frame.depth_m
        valid = np.count_nonzero(np.isfinite(depth) & (depth > config.depth_min)
                                 & (depth < config.depth_max))
        if valid < config.min_valid_fraction * depth.size:
            return _failure(T_init, config, f"too few valid depth pixels in the {which} frame "
                                            f"({valid})", start, init)
    T_pnp = None
    if config.pnp_init:
        T_pnp, _ = pnp_guess(prev, curr, intr, config)
        if T_pnp is not None:
            T_init, init = T_pnp, "pnp"

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
        return _failure(T_init, config, "Open3D odometry did not converge", start, init)
    correspondences = int(round(info[5, 5]))
    if correspondences < config.min_correspondences:
        return _failure(T_init, config, f"too few correspondences ({correspondences})", start,
                        init)
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(info))):
        return _failure(T_init, config, "non-finite motion or information", start, init)
    # re-orthonormalise: Open3D accumulates small increments in double precision
    T_prev_curr = gtsam.Pose3(gtsam.Rot3.ClosestTo(T[:3, :3]), T[:3, 3])
    angle = np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(T_prev_curr.rotation())))
    distance = float(np.linalg.norm(T_prev_curr.translation()))
    if distance > config.max_translation or angle > config.max_rotation_deg:
        return _failure(T_init, config, f"implausible motion ({distance:.2f} m, "
                                        f"{angle:.1f} deg)", start, init)
    if T_pnp is not None:
        delta = T_pnp.localCoordinates(T_prev_curr)
        moved, turned = np.linalg.norm(delta[3:]), np.degrees(np.linalg.norm(delta[:3]))
        if moved > config.max_disagreement[0] or turned > config.max_disagreement[1]:
            return _failure(T_init, config, f"dense result {moved:.3f} m / {turned:.1f} deg "
                                            "from the PnP guess", start, init)
    if np.linalg.cond(info) > 1e12:
        return _failure(T_init, config, "singular information matrix", start, init)
    cov = information_to_covariance(info, T_prev_curr, config, intr.width)
    return OdometryResult(T_prev_curr, cov, True, "", (time.perf_counter() - start) * 1e3,
                          correspondences, init, np.array(info))
