"""Frame-to-frame RGB-D visual odometry (Open3D's hybrid photometric + geometric odometry).

Two Open3D backends (:class:`OdometryConfig` ``backend``): the tensor one,
``open3d.t.pipelines.odometry.rgbd_odometry_multi_scale`` (default: ~5x faster on the CPU
at 640x480), and the legacy ``open3d.pipelines.odometry.compute_rgbd_odometry`` (kept as
the reference). Both are called with source = current and target = previous, so their
result, which maps source-camera points into the target camera, is ``T_prev_curr``. Their
6x6 point-to-point information matrix (the tensor backend's from
``compute_odometry_information_matrix``, on depth subsampled by 2) is ordered [rotation,
translation] (the translation block is the number of correspondences times the identity)
and belongs to a *left* perturbation, T = exp(xi) T_hat, expressed in the previous camera's
frame; GTSAM's tangent space is the right perturbation T = T_hat exp(xi_r) with
xi_r = Ad(T_hat^-1) xi, so the covariance is carried over with the adjoint of T_hat^-1.

That information matrix counts every pixel as an independent unit-variance point, which
says nothing about the errors that matter in a corridor (a pitch error coupled with a
vertical translation error, see :data:`COV_CALIBRATION`); it is scaled and a full 6x6
floor is added, both calibrated on the simulated corridor per backend and image width so
that the NEES against ground truth is close to its chi-square mean of 6
(benchmarks/corridor_sim.py fits the table and checks it on other seeds).

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

from estimation.config import coerce_fields
from perception.errors import PerceptionError
from perception.rgbd import CameraIntrinsics, RgbdFrame

# (cov_scale, cov_floor) per backend and image width: cov = cov_scale * inv(information)
# (moved to the right perturbation) + cov_floor, fitted by maximum likelihood on simulated
# corridors (perception.simulation.corridor defaults, 15 m, 2 clutter boxes; tensor backend:
# seeds 6-11, 310 pairs, at 640 and seeds 6-9, 206 pairs, at 320 (INTER_AREA /
# INTER_NEAREST resize); legacy: seeds 6-7, 104 pairs; benchmarks/corridor_sim.py --fit).
# Per corridor the fitted model's mean NEES ranges 5.0-7.9 (the bias varies with the doors).
# The floor is the errors' second moment minus the scaled information part: a full 6x6
# matrix in [rx ry rz tx ty tz] of the current camera, because the dominant error is a pitch error
# ~99 % correlated with a vertical translation error (the camera seems to rotate about the
# scene ~3 m ahead: faint texture, vignetting and 3.5 m of depth leave that direction weakly
# observed; the tensor backend's pitch error has a mean of ~-1.8 mrad per pair). Open3D's
# point-to-point information (one unit-variance point per pixel) gives a pitch sigma of
# ~0.5 mrad where the errors are ~2.4 mrad rms, and no pitch-vertical coupling. Errors are
# heavy-tailed: ~8-12 % of the pairs lie above the 95 % chi-square quantile.
COV_CALIBRATION: dict[str, dict[int, tuple[float, tuple]]] = {
    "tensor": {
        640: (0.0006813, (
            (6.227e-06, -2.298e-07, -2.37e-08, 8.894e-07, 1.927e-05, 1.128e-07),
            (-2.298e-07, 1.235e-07, 6.855e-09, -2.998e-07, -7.383e-07, -2.56e-07),
            (-2.37e-08, 6.855e-09, 2.748e-08, -1.089e-08, -8.8e-08, -6.138e-08),
            (8.894e-07, -2.998e-07, -1.089e-08, 7.721e-07, 2.842e-06, 6.149e-07),
            (1.927e-05, -7.383e-07, -8.8e-08, 2.842e-06, 6.037e-05, 2.053e-07),
            (1.128e-07, -2.56e-07, -6.138e-08, 6.149e-07, 2.053e-07, 9.922e-06))),
        # at 320 the likelihood is best without the information part: a constant covariance
        320: (0.0, (
            (1.432e-05, -2.014e-07, -1.115e-07, 2.074e-06, 4.346e-05, -1.687e-06),
            (-2.014e-07, 7.536e-07, 8.757e-09, -1.728e-06, -7.523e-07, -2.146e-07),
            (-1.115e-07, 8.757e-09, 1.392e-07, -2.749e-08, -3.266e-07, -6.481e-07),
            (2.074e-06, -1.728e-06, -2.749e-08, 4.389e-06, 6.934e-06, -3.16e-07),
            (4.346e-05, -7.523e-07, -3.266e-07, 6.934e-06, 0.0001343, -7.986e-06),
            (-1.687e-06, -2.146e-07, -6.481e-07, -3.16e-07, -7.986e-06, 5.026e-05))),
    },
    # measured at 640 only (other widths take it: nearest calibrated width)
    "legacy": {
        640: (0.002868, (
            (7.091e-06, 9.944e-08, -8.023e-08, -3.076e-08, 2.097e-05, 1.992e-06),
            (9.944e-08, 5.162e-08, -1.492e-08, -9.587e-08, 2.535e-07, -4.131e-08),
            (-8.023e-08, -1.492e-08, 8.848e-09, 1.867e-08, -2.215e-07, -1.192e-07),
            (-3.076e-08, -9.587e-08, 1.867e-08, 2.082e-07, -1.065e-08, 3.514e-07),
            (2.097e-05, 2.535e-07, -2.215e-07, -1.065e-08, 6.212e-05, 5.927e-06),
            (1.992e-06, -4.131e-08, -1.192e-07, 3.514e-07, 5.927e-06, 2.67e-05))),
    },
}


# The "motion" covariance model: per-axis standard deviations that grow with the
# increment, sigma_rot = a + b |omega|, sigma_trans = c + d |t| (|omega| in rad, |t| in m),
# isotropic per block. Fitted by maximum likelihood on the real development sequences
# (../shared/data/rgbd: ICL-NUIM office kt0 and TUM fr1/rpy, 247 pairs of this module's
# default odometry against ground truth; benchmarks/vo_covariance.py --gaps 1 --fit gives
# (8.27e-4, 0.0988, 4.97e-4, 0.349)). A scaled inverse information matrix was part of the
# fitted family; its maximum-likelihood weight was zero. Per-sequence NEES of the fit: 2.3 on
# ICL-NUIM, 8.5 on TUM (mean, 6 expected): errors grow with motion (blur, rolling shutter,
# colour-depth asynchrony), which the point-to-point information matrix does not see.
MOTION_COV_MODEL = (8.4e-4, 0.098, 5.0e-4, 0.35)

# The default model ("coupled") keeps those standard deviations and adds the correlations
# that the scene's geometry implies: a small rotation of the camera and a sideways translation
# move the image of a distant scene alike, so their errors are correlated (the rotation-
# translation ambiguity). The correlation matrix of Open3D's inverse information matrix
# carries that structure; taken whole it is too sharp (a ridge), so it is shrunk towards the
# identity: corr = (1 - c) I + c corr_info. It matters when the directions correct the
# rotation: the filter then also corrects the translation that compensated a rotation error.
# Per pair (benchmarks/vo_covariance.py, errors against ground truth) the likelihood is best
# near c = 0.5 on TUM fr1/rpy and beyond 0.75 on ICL-NUIM, and given the *true* rotation
# error the coupling predicts part of the translation error on both (ICL rms 1.10 -> 0.96 mm,
# TUM 3.62 -> 2.79 mm at c = 0.5). The filter, though, applies it to the corrections of real
# direction measurements, whose errors are not independent of the odometry's (the same depth
# images): with ground-truth directions c = 0.5 lowers the ICL-NUIM ATE (0.571 -> 0.529 cm),
# with the detectors' it raises it above VO alone (0.567 -> 0.574 cm). c = 0.3 keeps the VP
# run's aligned ATE below VO alone's on both development sequences (ICL 0.556, TUM 4.15,
# raw TUM 5.27 cm; VO alone 0.567 / 4.84 / 5.70) at most of the TUM gain of 0.5 (3.84 / 5.02).
COUPLING = 0.3


def motion_covariance(T_prev_curr: gtsam.Pose3,
                      model: tuple[float, float, float, float] = MOTION_COV_MODEL
                      ) -> np.ndarray:
    """The (6, 6) [rotation, translation] covariance of :data:`MOTION_COV_MODEL` for an
    increment (right perturbation, current-camera frame)."""
    a, b, c, d = model
    xi = gtsam.Pose3.Logmap(T_prev_curr)
    s_rot = a + b * float(np.linalg.norm(xi[:3]))
    s_trans = c + d * float(np.linalg.norm(T_prev_curr.translation()))
    return np.diag([s_rot ** 2] * 3 + [s_trans ** 2] * 3)


def floor_matrix(cov_floor) -> np.ndarray:
    """Return the (6, 6) floor covariance: diag(sigma^2) from 6 sigmas, or the 6x6 given."""
    floor = np.asarray(cov_floor, dtype=float)
    if floor.shape == (6,):
        return np.diag(np.square(floor))
    if floor.shape == (6, 6):
        # the tables are rounded to 4 digits: keep the (nearly singular) matrix PSD
        values, vectors = np.linalg.eigh(0.5 * (floor + floor.T))
        return (vectors * np.maximum(values, 0.0)) @ vectors.T
    raise PerceptionError(f"cov_floor must be 6 sigmas or a 6x6 matrix, got shape {floor.shape}")


def covariance_model(width: int, config: OdometryConfig | None = None
                     ) -> tuple[float, tuple[float, ...]]:
    """Return (cov_scale, cov_floor): the config's, else the calibration of the nearest width.

    The calibration belongs to the config's backend (default config: the default backend).
    Widths between or beyond the calibrated ones take the nearest (in log ratio): the model
    is only measured at the calibrated widths.
    """
    table = COV_CALIBRATION[(config or OdometryConfig()).backend]
    nearest = min(table, key=lambda w: abs(np.log(w / max(width, 1))))
    scale, floor = table[nearest]
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
    backend : str
        "tensor": Open3D's tensor odometry (``open3d.t.pipelines.odometry.
        rgbd_odometry_multi_scale``, CPU), "legacy": ``open3d.pipelines.odometry.
        compute_rgbd_odometry`` (slower, kept as the reference).
    method : str
        Residual of the tensor backend: "hybrid" (photometric + point-to-plane),
        "point_to_plane" or "intensity"; the legacy backend is always hybrid.
    iterations : tuple of int
        Gauss-Newton iterations per pyramid level, coarse to fine (Open3D's option). The
        default skips the full-resolution level (0 iterations; the tensor backend then runs
        on half-size images and never builds it): from the PnP guess the half- and
        quarter-resolution levels reach the same accuracy on the corridor at a third of the
        cost (the errors are set by the scene, not by the last pixel).
    information_stride : int
        Tensor backend: the information matrix is computed on the depth images subsampled
        by this factor (the count of correspondences shrinks by its square; the calibrated
        ``cov_scale`` absorbs that).
    depth_diff_max : float
        Largest depth difference (m) of a correspondence.
    depth_min, depth_max : float
        Depth range (m) used.
    min_valid_fraction : float
        Below this share of valid depth pixels in either frame the pair fails.
    min_correspondences : int
        Below this many correspondences (from the information matrix; with the tensor
        backend its count times ``information_stride`` squared) the pair fails.
    max_translation, max_rotation_deg : float
        Larger increments are reported as failures (divergence), m and degrees.
    cov_scale : float or None
        Multiplies inv(information); None: from :data:`COV_CALIBRATION` for the image width.
    cov_floor : tuple or None
        Added to the scaled inverse information: 6 standard deviations [rx, ry, rz (rad),
        tx, ty, tz (m)] in the current camera frame (a diagonal), or a full 6x6 covariance
        (rows as tuples; it carries correlations such as pitch with vertical motion);
        None: from :data:`COV_CALIBRATION`.
    failure_sigma : tuple of float
        Standard deviations (rad, m) of the covariance returned with a failure.
    pnp_init : bool
        Initialise from features + PnP (else from ``T_init``).
    pnp_min_inliers : int
        Fewer PnP inliers fall back to ``T_init``.
    pnp_corners, pnp_window : int
        Most Shi-Tomasi corners tracked, and the Lucas-Kanade window (pixels).
    max_disagreement : tuple of float
        (m, degrees): a dense result further than this from the PnP guess is a failure
        (the dense refinement slid along the corridor).
    cov_model : str
        "coupled" (default): the standard deviations of :data:`MOTION_COV_MODEL` with the
        geometry's rotation-translation correlations (see :data:`COUPLING`);
        "motion": :data:`MOTION_COV_MODEL` alone (no correlations), fitted on real RGB-D
        sequences;
        "information": ``cov_scale`` x inverse information + ``cov_floor``, from
        :data:`COV_CALIBRATION` (fitted on the simulated corridor, whose VO error is a
        pitch bias coupled with vertical motion: use it on the simulator).
    coupling : float
        "coupled" model: weight in [0, 1] of the information matrix's correlations.
    textureless_fallback : bool
        When the feature + PnP guess finds nothing to track (no texture), run Open3D's
        legacy hybrid odometry instead of the tensor one, on half-size images: the tensor
        hybrid leans on the photometric term (scaling the image contrast by 0.3 or 3 moves its
        ICL-NUIM ATE from 0.57 to 1.2-1.6 cm) and drifts where the image is flat; the legacy
        hybrid weighs the depth residual about 30:1 (Open3D's LAMBDA_HYBRID_DEPTH = 0.968) and
        keeps its accuracy there (ICL-NUIM with its texture blurred away, docs/vp_ekf.md).
        Only with ``pnp_init`` and the tensor backend; ``OdometryResult.backend`` says which
        ran.
    """

    backend: str = "tensor"
    method: str = "hybrid"
    iterations: tuple[int, ...] = (10, 5, 0)
    information_stride: int = 2
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
    pnp_corners: int = 300
    pnp_window: int = 15
    max_disagreement: tuple[float, float] = (0.05, 3.0)
    cov_model: str = "coupled"
    coupling: float = COUPLING
    textureless_fallback: bool = True

    def __post_init__(self):
        coerce_fields(self)  # lists (JSON, TOML) -> tuples: equal to the original config
        if self.cov_model not in ("coupled", "motion", "information"):
            raise PerceptionError(f"cov_model must be 'coupled', 'motion' or 'information', "
                                  f"got {self.cov_model!r}")
        if not 0.0 <= self.coupling <= 1.0:
            raise PerceptionError(f"coupling must be in [0, 1], got {self.coupling!r}")


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
        Number of pixel correspondences counted by the information matrix (the tensor
        backend counts on depth subsampled by ``information_stride``; 0 on failure).
    init : str
        Where the dense odometry started: "pnp", "given" (T_init) or "identity".
    backend : str
        Which dense odometry ran: "tensor", "legacy", or "legacy-textureless" (the
        ``textureless_fallback``, on half-size images); "" when none did.
    information : np.ndarray or None
        Open3D's raw 6x6 information matrix ([rotation, translation], left perturbation in
        the previous camera frame, unit-variance points; the tensor backend's on depth
        subsampled by ``information_stride``); None on failure.
    """

    T_prev_curr: gtsam.Pose3
    cov: np.ndarray
    success: bool
    reason: str
    ms: float
    correspondences: int = 0
    init: str = "identity"
    information: np.ndarray | None = None
    backend: str = ""


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
    corners = cv2.goodFeaturesToTrack(gray_prev, config.pnp_corners, 0.001, 8,
                                      mask=mask.astype(np.uint8))
    if corners is None or len(corners) < config.pnp_min_inliers:
        return None, 0
    lk = dict(winSize=(config.pnp_window, config.pnp_window), maxLevel=4)
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
    cov_model = (config or OdometryConfig()).cov_model
    if cov_model == "motion":
        return motion_covariance(T_prev_curr)
    if cov_model == "coupled":
        if info is None or not np.all(np.isfinite(info)):
            return motion_covariance(T_prev_curr)
        adjoint = T_prev_curr.inverse().AdjointMap()
        shape = adjoint @ np.linalg.inv(info) @ adjoint.T
        scale = 1.0 / np.sqrt(np.diag(shape))
        lam = (config or OdometryConfig()).coupling
        corr = (1.0 - lam) * np.eye(6) + lam * shape * np.outer(scale, scale)
        sigma = np.sqrt(np.diag(motion_covariance(T_prev_curr)))
        return corr * np.outer(sigma, sigma)
    cov_scale, cov_floor = covariance_model(width, config)
    cov_left = cov_scale * np.linalg.inv(info)
    adjoint = T_prev_curr.inverse().AdjointMap()
    cov = adjoint @ cov_left @ adjoint.T
    cov = cov + floor_matrix(cov_floor)
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

    backend = config.backend
    if (backend == "tensor" and config.pnp_init and T_pnp is None
            and config.textureless_fallback):
        backend = "legacy-textureless"
    try:
        if backend == "tensor":
            ok, T, info = _dense_tensor(prev, curr, intr, T_init, config)
            # the information is counted on subsampled depth
            stride = max(1, int(config.information_stride))
        elif backend == "legacy-textureless":
            ok, T, info = _dense_legacy(prev, curr, intr, T_init, config, factor=2)
            stride = 2
        else:
            ok, T, info = _dense_legacy(prev, curr, intr, T_init, config)
            stride = 1
    except RuntimeError as exc:  # Open3D raises when no pixel corresponds at all
        return _failure(T_init, config, f"Open3D odometry failed ({exc})", start, init)
    if not ok:
        return _failure(T_init, config, "Open3D odometry did not converge", start, init)
    correspondences = int(round(info[5, 5]))
    # compare the full-resolution estimate of the count
    if correspondences * stride ** 2 < config.min_correspondences:
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
                          correspondences, init, np.array(info), backend)


def _dense_legacy(prev: RgbdFrame, curr: RgbdFrame, intr: CameraIntrinsics,
                  T_init: gtsam.Pose3, config: OdometryConfig, factor: int = 1):
    """(converged, T_prev_curr 4x4, information 6x6) from Open3D's legacy hybrid odometry.

    ``factor`` > 1 runs it on images shrunk by that factor (``perception.rgbd.resize_frame``),
    dropping as many trailing (finest) pyramid levels of ``config.iterations``; the
    information matrix then counts the shrunk image's pixels."""
    import open3d as o3d

    from perception.rgbd import resize_frame

    size = (intr.width // factor, intr.height // factor)

    def rgbd_image(frame: RgbdFrame):
        frame = resize_frame(frame, *size)
        depth = np.where(np.isfinite(frame.depth_m), frame.depth_m, 0).astype(np.float32)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(frame.rgb)), o3d.geometry.Image(depth),
            depth_scale=1.0, depth_trunc=config.depth_max, convert_rgb_to_intensity=True)

    levels = [int(n) for n in config.iterations]
    shrink = factor
    while shrink > 1 and len(levels) > 1:
        levels.pop()
        shrink //= 2
    cam = intr.resized(*size) if factor > 1 else intr
    pinhole = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy,
                                                cam.cx, cam.cy)
    option = o3d.pipelines.odometry.OdometryOption(
        iteration_number_per_pyramid_level=o3d.utility.IntVector(levels),
        depth_diff_max=config.depth_diff_max, depth_min=config.depth_min,
        depth_max=config.depth_max)
    # source = current, target = previous: Open3D's result maps source into target
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok, T, info = o3d.pipelines.odometry.compute_rgbd_odometry(
            rgbd_image(curr), rgbd_image(prev), pinhole, T_init.matrix(),
            o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), option)
    return ok, np.asarray(T), np.asarray(info)


_TENSOR_METHODS = {"hybrid": "Hybrid", "point_to_plane": "PointToPlane",
                   "intensity": "Intensity"}


def _dense_tensor(prev: RgbdFrame, curr: RgbdFrame, intr: CameraIntrinsics,
                  T_init: gtsam.Pose3, config: OdometryConfig):
    """(converged, T_prev_curr 4x4, information 6x6) from Open3D's tensor odometry.

    Trailing pyramid levels with 0 iterations are never built: the images are halved once
    per such level (colour INTER_AREA, depth INTER_NEAREST, intrinsics with pixel centres
    at integers) and the remaining levels run on them; Open3D would otherwise still prepare
    the full-resolution level it does not iterate on (a third of the time at 640x480). The
    information matrix (Open3D's point-to-point one, same layout as the legacy backend's)
    is computed on depth subsampled by ``config.information_stride``.
    """
    import cv2
    import open3d as o3d

    odometry = o3d.t.pipelines.odometry
    if config.method not in _TENSOR_METHODS:
        raise PerceptionError(f"unknown odometry method {config.method!r}; expected one of "
                              f"{sorted(_TENSOR_METHODS)}")
    levels = [int(n) for n in config.iterations]
    factor = 1
    while len(levels) > 1 and levels[-1] == 0:
        levels.pop()
        factor *= 2

    def depth_of(frame: RgbdFrame) -> np.ndarray:
        depth = frame.depth_m
        # the tensor odometry has no minimum depth: too-near pixels become invalid (0)
        keep = np.isfinite(depth) & (depth >= config.depth_min)
        return np.ascontiguousarray(np.where(keep, depth, 0), dtype=np.float32)

    def shrink(image: np.ndarray, by: int, interpolation: int) -> np.ndarray:
        if by == 1:
            return np.ascontiguousarray(image)
        size = (intr.width // by, intr.height // by)
        return np.ascontiguousarray(cv2.resize(image, size, interpolation=interpolation))

    def camera(by: int) -> np.ndarray:
        return intr.resized(intr.width // by, intr.height // by).K

    def rgbd_image(frame: RgbdFrame, depth: np.ndarray):
        return o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(shrink(frame.rgb, factor, cv2.INTER_AREA)),
            o3d.t.geometry.Image(depth))

    depth_prev, depth_curr = depth_of(prev), depth_of(curr)
    dense_prev = shrink(depth_prev, factor, cv2.INTER_NEAREST)
    dense_curr = shrink(depth_curr, factor, cv2.INTER_NEAREST)
    criteria = [odometry.OdometryConvergenceCriteria(n) for n in levels]
    params = odometry.OdometryLossParams(depth_outlier_trunc=config.depth_diff_max)
    # source = current, target = previous: Open3D's result maps source into target
    result = odometry.rgbd_odometry_multi_scale(
        rgbd_image(curr, dense_curr), rgbd_image(prev, dense_prev),
        o3d.core.Tensor(camera(factor), o3d.core.float64),
        o3d.core.Tensor(T_init.matrix()), 1.0, config.depth_max, criteria,
        getattr(odometry.Method, _TENSOR_METHODS[config.method]), params)
    T = result.transformation.numpy()
    if result.fitness <= 0:
        return False, T, np.zeros((6, 6))
    stride = max(1, int(config.information_stride))
    if stride == factor:
        info_prev, info_curr = dense_prev, dense_curr
    else:
        info_prev = shrink(depth_prev, stride, cv2.INTER_NEAREST)
        info_curr = shrink(depth_curr, stride, cv2.INTER_NEAREST)
    info = odometry.compute_odometry_information_matrix(
        o3d.t.geometry.Image(info_curr), o3d.t.geometry.Image(info_prev),
        o3d.core.Tensor(camera(stride), o3d.core.float64), result.transformation,
        config.depth_diff_max, 1.0, config.depth_max)
    return True, T, info.numpy()
