"""Vanishing-point EKF SLAM on a TUM-layout RGB-D sequence (Ji, Yamashita, Asama).

:class:`VpSlam` is the SLAM as one per-frame step (``step(frame) -> FrameResult``, in the
style of KISS-ICP's ``register_frame``):

    frame -> RGB-D odometry against the previous frame (prediction, eq. (9)-(10))
          -> the structure's directions: depth surface normals and line vanishing points
             (update, eq. (11)-(18), Mahalanobis-gated)
          -> a PoseGraph node at the filtered pose with its covariance, the VO between
             factor, and the 5 cm voxel-filtered scan (section 4)

:func:`run_vpslam` is a loop over ``step`` plus I/O and timing; the octree map is fused from
the graph's scans at the filtered poses (eq. (19)-(20)) with :func:`mapping.fuse`, the same
function ``octofactor map`` runs on the written ``graph.graph``.

Failures never stop the run: an unreadable frame is named on stderr and counted; a failed VO
step predicts with the last increment and ``vo_failure_sigma``; frames without a direction
just predict. World frame: docs/vp_ekf.md ("World frame").
"""
from __future__ import annotations

import json
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from estimation.config import coerce_fields
from estimation.errors import OctofactorError
from estimation.fileio import atomic_write
from estimation.vp_ekf import VpEkfConfig
from perception.odometry import OdometryConfig

VP_MODELS = ("manhattan", "point", "none")
# The default pipeline gates each direction at the 95 % chi-square quantile (2 dof; the
# paper's filter keeps VpEkfConfig's 99 %): the detectors' errors on real images are heavy-
# tailed, and on the development sequences the 95 % gate is as good or better everywhere
# (benchmarks/vpslam_real.py, docs/vp_ekf.md).
GATE_95 = 5.991464547107979
DETECTORS = ("normals+lines", "normals", "lines", "seed")
WORLD_FRAMES = ("auto", "groundtruth", "manhattan", "camera")
DIRECTION_FACTORS = ("fixed", "predicted", "none")


@dataclass(frozen=True)
class VpSlamConfig:
    """Settings of :class:`VpSlam` and :func:`run_vpslam`.

    Attributes
    ----------
    vp_model : "manhattan" (default: up to three directions of the structure), "point" (the
        paper's one VP) or "none" (VO only: the paper's baseline). The filter's
        ``ekf.vp_model`` follows it.
    detector : where the directions come from: "normals+lines" (default: depth surface
        normals, after OPVO, then line VPs of :func:`perception.vanishing_points.
        detect_manhattan`, as LPVO adds lines), "normals", "lines" or "seed" (the paper's
        Hough detector, one forward VP; with vp_model "point")
    world_frame : "auto" (ground truth of the first frame when it has one, else the
        Manhattan frame), "groundtruth", "manhattan" (z along the vertical direction, x along
        the dominant horizontal one, origin at the first camera), or "camera" (the paper: the
        first body frame, camera looking along world x)
    ekf : VpEkfConfig, the filter (state parametrisation, gate, VO-failure sigma); the
        default gates at the 95 % chi-square quantile (:data:`GATE_95`)
    odometry : OdometryConfig, the RGB-D odometry and its covariance model
    vp_pixel_floor : px, added in quadrature to a line detector's VP covariance
    voxel_size : m, the voxel filter of section 4 (5 cm in the paper)
    map_resolution : m, octree leaf size
    max_range : m, rays longer than this are cut in the map (-1: no limit)
    backproject_stride : keep every n-th pixel row/column before the voxel filter
    build_map : False skips scans and octree
    vo_scale : image scale for the RGB-D odometry only (VP and map keep full resolution)
    keyframes : False (default): frame-to-frame odometry (the paper); True: the odometry
        measures each frame against the last keyframe, whose pose the filter clones, so
        frame-to-frame errors do not accumulate between keyframes (docs/vp_ekf.md). Needs a
        filter with ``set_keyframe``/``predict_from_keyframe`` (the error-state one); others
        run frame to frame.
    keyframe_translation, keyframe_rotation_deg : m, degrees; a frame further than this from
        the keyframe (filtered poses) becomes the next keyframe
    vp_min_motion : (degrees, m); directions are measured only on frames that turned or moved
        at least this much since the last frame measured (either suffices): consecutive
        views of one scene give errors that are far from independent. (0, 0), the default,
        measures every frame (docs/vp_ekf.md gives the trade-off measured on real data)
    estimator : name of a registered filter estimator (``octofactor plugins``) whose
        ``slam_filter(K, T_world_camera, cov_pose, ekf_config)`` builds the filter
    overlap : True (default): the direction detectors' work that needs no prediction (depth
        normals, line or seed vanishing points) runs in a worker thread while the odometry
        runs (Open3D and OpenCV release the GIL); the results are the same either way
    direction_factors : each direction the filter accepted becomes a graph direction factor
        whose world direction is the filter's prediction of the structure axis at that
        update ("predicted", default), the axis as the filter estimated it when it was first
        accepted ("fixed"), or no factor ("none"); docs/vp_ekf.md ("The pose graph")
    """

    vp_model: str = "manhattan"
    detector: str = "normals+lines"
    world_frame: str = "auto"
    ekf: VpEkfConfig = field(default_factory=lambda: VpEkfConfig(vp_model="manhattan",
                                                                 gate_chi2=GATE_95))
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    vp_pixel_floor: float = 1.0
    voxel_size: float = 0.05
    map_resolution: float = 0.05
    max_range: float = 5.0
    backproject_stride: int = 4
    build_map: bool = True
    vo_scale: float = 1.0
    keyframes: bool = False
    vp_min_motion: tuple[float, float] = (0.0, 0.0)
    keyframe_translation: float = 0.03
    keyframe_rotation_deg: float = 3.0
    estimator: str = "vp_ekf"
    direction_factors: str = "predicted"
    overlap: bool = True

    def __post_init__(self):
        coerce_fields(self)  # VpSlamConfig(**report["config"]) == the run's config
        for name, allowed in (("vp_model", VP_MODELS), ("detector", DETECTORS),
                              ("world_frame", WORLD_FRAMES),
                              ("direction_factors", DIRECTION_FACTORS)):
            if getattr(self, name) not in allowed:
                raise OctofactorError(f"{name} must be one of {', '.join(allowed)}, got "
                                      f"{getattr(self, name)!r}")
        if self.vp_model == "point" and self.detector not in ("seed", "lines"):
            object.__setattr__(self, "detector", "seed")
        if self.vp_model == "manhattan" and self.detector == "seed":
            raise OctofactorError("the seed detector gives one VP: use vp_model='point'")
        if self.vp_model != "none" and self.ekf.vp_model != self.vp_model:
            object.__setattr__(self, "ekf", replace(self.ekf, vp_model=self.vp_model))
        deg, m = self.vp_min_motion
        if not (0 <= deg <= 180 and 0 <= m <= 100):  # also refuses NaN
            raise OctofactorError(f"vp_min_motion must be (0-180 degrees, 0-100 m), got "
                                  f"{self.vp_min_motion!r}")
        if not 0.1 <= self.vo_scale <= 1.0:
            raise OctofactorError(f"vo_scale must be in [0.1, 1], got {self.vo_scale}")

    @classmethod
    def paper(cls, **changes) -> VpSlamConfig:
        """The seed paper's system: 9-D Euler state, one VP point from the Hough detector,
        odometry covariance of the simulated corridor. The Euler filter runs in the paper's
        local frame (first body frame at the origin); poses are mapped to the world frame."""
        base = cls(vp_model="point", detector="seed", world_frame="auto",
                   ekf=VpEkfConfig(vp_model="point", state="euler"),
                   odometry=OdometryConfig(cov_model="information"), keyframes=False)
        return replace(base, **changes)

    def to_dict(self) -> dict:
        """Nested dict of the settings (for report.json)."""
        return asdict(self)


@dataclass(frozen=True)
class FrameResult:
    """What :meth:`VpSlam.step` did with one frame.

    Attributes
    ----------
    index, timestamp : the frame's
    T_world_camera : gtsam.Pose3, the filtered pose
    cov_pose : (6, 6) its covariance, GTSAM tangent order [rotation, translation]
    vo : the odometry result (None for the first frame); with keyframes its ``T_prev_curr``
        is measured from the keyframe
    vp_outcomes : list of estimation.vp_ekf.VpUpdate, one per direction tried
    detections : number of directions the detectors gave
    notes : reasons for skipped or degraded steps ("vo: ...", "vp: ...")
    ms : dict of stage times in ms (read is outside the step): vo (with the time of a
        result reused from the odometry cache, vo_reused), vp_ekf, scan
    """

    index: int
    timestamp: float
    T_world_camera: object
    cov_pose: np.ndarray
    vo: object
    vp_outcomes: list
    detections: int
    notes: list
    ms: dict


class VpSlam:
    """The VP-EKF SLAM as a per-frame step.

    Parameters
    ----------
    intrinsics : perception.rgbd.CameraIntrinsics
    config : VpSlamConfig
    odometry_cache : optional dict shared by runs on the same frames (the odometry does not
        depend on the filter); keys (previous index, index, vo_scale)

    Attributes
    ----------
    graph : estimation.PoseGraph, a node per frame, VO between factors, a direction factor
        per accepted direction, scans
    filter : the filter (None before the first frame)
    counts : Counter of updates, gated directions, detections
    world_frame : which world frame was used ("groundtruth", "manhattan", "camera")
    """

    def __init__(self, intrinsics, config: VpSlamConfig = VpSlamConfig(),
                 odometry_cache: dict | None = None):
        from estimation import PoseGraph
        from estimation.plugins import create_estimator

        self.config = config
        self.intrinsics = intrinsics
        self.K = intrinsics.K
        self._estimator = create_estimator(config.estimator, kind="filter")
        if not callable(getattr(self._estimator, "slam_filter", None)):
            raise OctofactorError(
                f"estimator {config.estimator!r} cannot run vpslam: it has no "
                "slam_filter(K, T_world_camera, cov_pose, ekf_config) method (docs/plugins.md)")
        self.vo_intrinsics, self._vo_frame = _vo_resampler(intrinsics, config.vo_scale)
        self.graph = PoseGraph()
        self.filter = None
        self.counts: Counter = Counter()
        self.world_frame = "pending"
        self._cache = odometry_cache
        self._reused_ms = 0.0      # VO time of a cached result, counted in this frame
        self._prev = None          # (index, frame at the VO scale)
        self._partner = None       # the frame the odometry measures against: the keyframe
        self._prev_node = None
        self._T_guess = None       # last increment: the guess and the failure motion
        self._gap = None           # (T, cov) predicted over unreadable frames since the node
        self._accepted = []        # this frame's accepted directions (VpUpdate), for the graph
        self._axes_world = {}      # "fixed" direction factors: axis -> world direction
        self._prior = None         # the first node's prior factor (moved when levelling)
        self._vp_pose = None       # the filter's pose at the last frame with directions
        self._pool = None          # the worker thread of config.overlap (started lazily)
        s_rot, s_trans = config.ekf.vo_failure_sigma
        self._failure_cov = np.diag([s_rot ** 2] * 3 + [s_trans ** 2] * 3)

    # ------------------------------------------------------------------ the step
    def step(self, frame) -> FrameResult:
        """Filter one frame: predict with VO, update with the directions, add a node."""
        notes: list[str] = []
        ms: dict[str, float] = {}
        t0 = time.perf_counter()
        frame_vo = self._vo_frame(frame)
        vo = None
        partner = None
        pending: dict = {}
        if self.filter is None:
            self._start(frame)
        else:
            pending = self._start_detection(frame)
            vo, partner = self._odometry(frame, frame_vo, notes)
            if getattr(vo, "backend", "") == "legacy-textureless":
                self.counts["vo_textureless"] += 1
            self._predict(vo)
        # a VO result reused from the cache counts the time it took when it was computed
        ms["vo_reused"] = self._reused_ms
        ms["vo"] = (time.perf_counter() - t0) * 1e3 + self._reused_ms
        self._reused_ms = 0.0

        t1 = time.perf_counter()
        if self._view_changed():
            outcomes, n_detected = self._directions(frame, notes, pending)
        else:
            outcomes, n_detected = [], 0
            self.counts["vp_same_view"] += 1
        self._accepted = [o for o in outcomes
                          if o.status == "updated" and o.direction_sensor is not None]
        self._maybe_level_world()
        ms["vp_ekf"] = (time.perf_counter() - t1) * 1e3

        t2 = time.perf_counter()
        scan = self._scan(frame) if self.config.build_map else None
        ms["scan"] = (time.perf_counter() - t2) * 1e3
        T_world_camera = self._T_world_local.compose(self.filter.T_world_camera)
        cov_pose = self.filter.pose_covariance()  # right perturbation: unchanged by the map
        self._add_node(frame, T_world_camera, cov_pose, scan, vo, partner)
        self._prev = (frame.index, frame_vo)
        self._next_keyframe(vo, partner)
        return FrameResult(frame.index, frame.timestamp, T_world_camera, cov_pose, vo,
                           outcomes, n_detected, notes, ms)

    def skip(self) -> None:
        """A frame that could not be read: its time still passes (constant velocity)."""
        if self.filter is None:
            return
        self.filter.predict_vo(self._T_guess, self._failure_cov)
        T, cov = self._gap
        self._gap = (T.compose(self._T_guess), cov + self._failure_cov)
        self._prev = None  # the next VO has no previous frame; a keyframe stays valid
        if not self._keyframes:
            self._partner = None

    # ------------------------------------------------------------------ stages
    def _start(self, frame) -> None:
        import gtsam

        cfg = self.config
        use_gt = frame.T_world_camera_gt is not None and cfg.world_frame in (
            "auto", "groundtruth")
        if cfg.world_frame == "groundtruth" and frame.T_world_camera_gt is None:
            raise OctofactorError("world_frame 'groundtruth': the first frame has no ground "
                                  "truth")
        if use_gt:
            T0, self.world_frame = frame.T_world_camera_gt, "groundtruth"
        elif cfg.world_frame == "camera" or cfg.vp_model == "none":
            from estimation.geometry import R_BODY_CAMERA

            # the paper: body frame at the origin, camera looking along world x
            T0, self.world_frame = gtsam.Pose3(gtsam.Rot3(R_BODY_CAMERA), np.zeros(3)), "camera"
        else:
            T0, self.world_frame = gtsam.Pose3(), "pending"  # levelled by the directions
        cov0 = np.diag([1e-6] * 6)
        self._T_world_local = gtsam.Pose3()
        if cfg.ekf.state == "euler":
            # the paper's Euler state is singular at pitch +-90 deg: run it in the paper's
            # local frame (first body frame at the origin) and map its poses to the world
            from estimation.geometry import R_BODY_CAMERA

            T_local0 = gtsam.Pose3(gtsam.Rot3(R_BODY_CAMERA), np.zeros(3))
            if self.world_frame == "pending":
                self.world_frame = "camera"
                T0 = T_local0
            self._T_world_local = T0.compose(T_local0.inverse())
            T0 = T_local0
        self.filter = self._estimator.slam_filter(self.K, T0, cov0, cfg.ekf)
        self._T_guess = gtsam.Pose3()
        self._gap = (gtsam.Pose3(), np.zeros((6, 6)))

    def _predict(self, vo) -> None:
        """Predict with the odometry's measurement (from the keyframe or the previous frame),
        else with constant velocity and ``vo_failure_sigma``."""
        if vo is None or not vo.success:
            self.filter.predict_vo(self._T_guess, self._failure_cov)
            return
        T_before = self.filter.T_world_camera
        if self._keyframes:
            self.filter.predict_from_keyframe(vo.T_prev_curr, vo.cov)
        else:
            self.filter.predict_vo(vo.T_prev_curr, vo.cov)
        self._T_guess = T_before.between(self.filter.T_world_camera)

    @property
    def _keyframes(self) -> bool:
        """Odometry against keyframes (needs a filter that clones them)."""
        return self.config.keyframes and hasattr(self.filter, "predict_from_keyframe")

    def _odometry(self, frame, frame_vo, notes):
        """(odometry result or None, index of the frame it measured from or None).

        Against the keyframe when keyframes are on (else the previous frame); when that
        fails, the previous frame becomes the keyframe and is tried."""
        if self._partner is None:
            notes.append("vo: no previous frame")
            return None, None
        index, partner_vo = self._partner
        guess = self._T_guess
        if self._keyframes:  # from the keyframe to the previous frame, then constant velocity
            guess = self.filter.T_world_keyframe.between(self.filter.T_world_camera
                                                         ).compose(guess)
        vo = self._vo_pair(index, partner_vo, frame, frame_vo, guess)
        if not vo.success and self._keyframes and self._prev is not None \
                and self._prev[0] != index:
            self.counts["vo_keyframe_retries"] += 1
            self.filter.set_keyframe()
            self._partner = self._prev
            index, partner_vo = self._prev
            vo = self._vo_pair(index, partner_vo, frame, frame_vo, self._T_guess)
        if not vo.success:
            notes.append(f"vo: {_reason_class(vo.reason)}")
            return vo, None
        return vo, index

    def _vo_pair(self, index, partner_vo, frame, frame_vo, guess):
        from perception.odometry import rgbd_odometry

        key = (index, frame.index, self.config.vo_scale, self.config.odometry)
        if self._cache is not None and key in self._cache:
            vo = self._cache[key]
            self._reused_ms += float(getattr(vo, "ms", 0.0))
            return vo
        try:
            vo = rgbd_odometry(partner_vo, frame_vo, self.vo_intrinsics, T_init=guess,
                               config=self.config.odometry)
        except OctofactorError as exc:
            vo = _VoFailure(f"error: {type(exc).__name__}")
        if self._cache is not None:
            self._cache[key] = vo
        return vo

    def _next_keyframe(self, vo, partner) -> None:
        """Frame to frame: every frame is the next partner. With keyframes: the current frame
        becomes the keyframe when the odometry failed or it moved too far from the keyframe."""
        if not self._keyframes:
            self._partner = self._prev
            return
        cfg = self.config
        if partner is not None:
            xi = self.filter.T_world_keyframe.localCoordinates(self.filter.T_world_camera)
            if (np.linalg.norm(xi[3:]) <= cfg.keyframe_translation
                    and np.degrees(np.linalg.norm(xi[:3])) <= cfg.keyframe_rotation_deg):
                return
        self.filter.set_keyframe()
        self._partner = self._prev
        self.counts["keyframes"] += 1

    def _view_changed(self) -> bool:
        """True when the camera moved enough since the last frame whose directions were
        measured (config.vp_min_motion) for a new, mostly independent measurement."""
        min_deg, min_m = self.config.vp_min_motion
        last = self._vp_pose
        T = self.filter.T_world_camera
        if last is not None and (min_deg > 0 or min_m > 0):
            xi = last.localCoordinates(T)
            if (np.degrees(np.linalg.norm(xi[:3])) < min_deg
                    and np.linalg.norm(xi[3:]) < min_m):
                return False
        self._vp_pose = T
        return True

    def _start_detection(self, frame) -> dict:
        """Submit the detectors' work that needs no prediction to the worker thread, so that
        it runs while the odometry does ({} when ``config.overlap`` is off, without
        directions, or when whether this view is measured depends on the prediction)."""
        cfg = self.config
        if not cfg.overlap or cfg.vp_model == "none" or any(cfg.vp_min_motion):
            return {}
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vpslam")
        pending = {}
        if cfg.detector in ("normals+lines", "normals"):
            from perception.manhattan_normals import depth_normals

            K = self.K
            pending["normals"] = self._pool.submit(depth_normals, frame.depth_m, K[0, 0],
                                                   K[1, 1], K[0, 2], K[1, 2])
        if cfg.detector in ("normals+lines", "lines", "seed"):
            pending["image"] = self._pool.submit(_detect_in_image, cfg.detector, frame.rgb,
                                                 self.K)
        return pending

    def close(self) -> None:
        """Stop the worker thread (``run_vpslam`` does; a closed VpSlam starts a new one)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _directions(self, frame, notes, pending=None) -> tuple[list, int]:
        """Detect the structure's directions and update the filter; (outcomes, detected).

        ``pending``: futures of :meth:`_start_detection` ("normals", "image") whose results
        replace the same computations here."""
        cfg = self.config
        if cfg.vp_model == "none":
            return [], 0
        pending = pending or {}
        outcomes, detected = [], 0
        if cfg.detector in ("normals+lines", "normals"):
            from perception.manhattan_normals import manhattan_from_depth

            guess = None
            R_wm = getattr(self.filter, "R_world_manhattan", None)
            if R_wm is not None:
                guess = self.filter.T_world_camera.rotation().matrix().T @ R_wm
            normals = pending["normals"].result() if "normals" in pending else None
            found = manhattan_from_depth(frame.depth_m, self.K, guess, normals=normals)
            detected += len(found.directions)
            if len(found.directions):
                outcomes += self.filter.update_directions(found.directions,
                                                          direction_covs=list(found.covs))
        in_image = (pending["image"].result() if "image" in pending
                    else _detect_in_image(cfg.detector, frame.rgb, self.K))
        if cfg.detector in ("normals+lines", "lines"):
            detection = in_image
            detected += len(detection.vps)
            if detection.vps and cfg.vp_model == "manhattan":
                uvs = [vp.uv for vp in detection.vps]
                covs = [None if vp.uv is None else self._pixel_cov(vp.cov)
                        for vp in detection.vps]
                outcomes += self.filter.update_directions(
                    np.array([vp.direction for vp in detection.vps]), uvs, covs)
            elif detection.vps:
                vp = detection.forward()
                if vp is not None:
                    outcomes.append(self.filter.update_vp(vp.uv, self._pixel_cov(vp.cov)))
        if cfg.detector == "seed":
            vp = in_image.forward()
            if vp is not None:
                detected += 1
                outcomes.append(self.filter.update_vp(vp.uv, self._pixel_cov(vp.cov)))
        if detected == 0:
            notes.append("vp: none detected")
        self.counts["vp_detections"] += detected
        for outcome in outcomes:
            if outcome.status in ("updated", "gated", "initialised"):
                self.counts[f"vp_{outcome.status}"] += 1
            else:
                notes.append(f"vp: {outcome.reason}")
        return outcomes, detected

    def _pixel_cov(self, cov) -> np.ndarray:
        cov = np.asarray(cov, dtype=float).reshape(2, 2)
        cov = cov if np.all(np.isfinite(cov)) else np.eye(2) * 1e6
        return cov + np.eye(2) * self.config.vp_pixel_floor ** 2

    def _maybe_level_world(self) -> None:
        """Once the structure is known, make its frame the world (z up, x forward)."""
        if self.world_frame != "pending" or not getattr(self.filter, "vp_initialised", False):
            return
        R_wm = getattr(self.filter, "R_world_manhattan", None)
        if R_wm is None or not hasattr(self.filter, "reanchor"):
            self.world_frame = "camera"
            return
        import gtsam

        R_new_old = level_rotation(self.filter.T_world_camera.rotation().matrix(), R_wm)
        origin = self.filter.T_world_camera.translation()
        A = gtsam.Pose3(gtsam.Rot3(R_new_old), -(R_new_old @ origin))
        self.filter.reanchor(A)
        self._vp_pose = None
        for node in self.graph.nodes.values():  # frames before the structure was found
            node.pose = A.compose(node.pose)
        if self._prior is not None:  # the first node's prior moves with it
            self.graph.factors = [f for f in self.graph.factors if f is not self._prior]
            first = self.graph.nodes[self._prior.nodes[0]]
            self._prior = self.graph.add_prior(first.id, first.pose, self._prior.covariance)
        self._accepted = [replace(o, direction_world=R_new_old @ o.direction_world)
                          for o in self._accepted]
        self.world_frame = "manhattan"

    def _scan(self, frame):
        from estimation import Scan
        from perception.rgbd import backproject, voxel_filter

        points = backproject(frame.depth_m, self.intrinsics, stride=self.config.backproject_stride)
        points = voxel_filter(points, self.config.voxel_size)
        return Scan(points) if len(points) else None

    def _add_node(self, frame, T_world_camera, cov_pose, scan, vo, partner) -> None:
        graph = self.graph
        graph.add_node(frame.index, T_world_camera, frame.timestamp, scan=scan, cov=cov_pose)
        if self._prev_node is None:
            self._prior = graph.add_prior(frame.index, T_world_camera, cov_pose)
        elif partner is not None:  # the odometry's own measurement, keyframe to frame
            graph.add_between(partner, frame.index, vo.T_prev_curr, vo.cov)
        else:  # constant velocity since the last node, over any unreadable frames
            gap_T, gap_cov = self._gap
            graph.add_between(self._prev_node, frame.index, gap_T.compose(self._T_guess),
                              gap_cov + self._failure_cov)
        self._add_directions(frame.index)
        import gtsam

        self._gap = (gtsam.Pose3(), np.zeros((6, 6)))
        self._prev_node = frame.index

    def _add_directions(self, node_id: int) -> None:
        """A direction factor per direction the filter accepted in this frame, with the
        covariance the filter used. The world direction is the filter's estimate of the
        structure axis (docs/vp_ekf.md, "The pose graph")."""
        mode = self.config.direction_factors
        for outcome in self._accepted if mode != "none" else ():
            d_world = outcome.direction_world
            if mode == "fixed":
                d_world = self._axes_world.setdefault(outcome.axis, d_world)
            self.graph.add_direction(node_id, outcome.direction_sensor, d_world,
                                     outcome.direction_cov)
        self._accepted = []


def _detect_in_image(detector: str, rgb: np.ndarray, K: np.ndarray):
    """The image detector's result (VPResult): line VPs, or the seed detector's (None for
    the normals-only detector)."""
    if detector == "normals":
        return None
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    if detector == "seed":
        from perception.vanishing_points import detect_seed

        return detect_seed(bgr, K=K)
    from perception.vanishing_points import detect_manhattan

    return detect_manhattan(bgr, K)


def level_rotation(R_world_camera: np.ndarray, R_world_manhattan: np.ndarray) -> np.ndarray:
    """R_new_old: the rotation that makes the structure's frame the world frame.

    z_new is the structure axis closest to the camera's up (-y of the optical frame), signed
    up; x_new the remaining axis closest to the viewing direction, signed forward.
    """
    up = R_world_camera @ np.array([0.0, -1.0, 0.0])
    forward = R_world_camera @ np.array([0.0, 0.0, 1.0])
    axes = [R_world_manhattan[:, j] for j in range(3)]
    k_up = int(np.argmax([abs(a @ up) for a in axes]))
    z = axes[k_up] * np.sign(axes[k_up] @ up)
    rest = [a for j, a in enumerate(axes) if j != k_up]
    x = max(rest, key=lambda a: abs(a @ forward))
    x = x * (1.0 if x @ forward >= 0 else -1.0)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.vstack([x, y, z])  # rows: new axes in old coordinates


# --------------------------------------------------------------------------- the run

@dataclass(frozen=True)
class VpSlamResult:
    """What :func:`run_vpslam` produced.

    Attributes
    ----------
    graph : estimation.PoseGraph, one node per filtered frame (with scans)
    tree : mapping.OcTree or None
    report : dict, the content of report.json
    timestamps, positions : (N,), (N, 3)
    position_covs : (N, 3, 3) world-frame position covariances
    T_world_camera : (N, 4, 4) filtered poses
    """

    graph: object
    tree: object
    report: dict
    timestamps: np.ndarray
    positions: np.ndarray
    position_covs: np.ndarray
    T_world_camera: np.ndarray
    positions_gt: np.ndarray


#: a run fails (nothing written) when more than this fraction of its frames is unreadable:
#: the trajectory would then be mostly gaps that the filter bridges on its motion model
MAX_SKIPPED_FRACTION = 0.5


def run_vpslam(seq_dir, out_dir=None, config: VpSlamConfig = VpSlamConfig(), intrinsics=None,
               progress: bool = True, max_frames: int | None = None,
               odometry_cache: dict | None = None, name: str | None = None,
               ellipses: bool = True, distortion=None) -> VpSlamResult:
    """Run :class:`VpSlam` over the sequence in ``seq_dir``; write the outputs to ``out_dir``.

    ``intrinsics`` (perception.rgbd.CameraIntrinsics) overrides the sequence's camera file.
    ``name`` labels the run: report.json, the figure's legend and ``<name>.txt`` (a copy of
    trajectory.txt, so that evo and ``octofactor eval`` tell runs apart); ``ellipses`` False
    draws no 2-sigma ellipses in trajectory.png.
    With ``out_dir`` None nothing is written (benchmarks). Runs of several filter variants on
    one sequence can share the odometry through the same ``odometry_cache`` dict (only runs
    on the same frames: the same ``distortion``). ``distortion`` (OpenCV k1, k2, p1, p2[, k3])
    undistorts every frame on reading (perception.rgbd.Undistorter).
    """
    from perception.rgbd import TumRgbdSequence

    sequence = TumRgbdSequence(seq_dir, intrinsics=intrinsics, distortion=distortion)
    n_frames = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    if n_frames == 0:
        raise OctofactorError(f"{seq_dir}: the sequence has no associated frames")
    check_intrinsics(sequence)
    slam = VpSlam(sequence.intrinsics, config, odometry_cache)
    skipped_frames: Counter = Counter()
    skipped_list: list[dict] = []
    notes_count: Counter = Counter()
    timings: dict[str, list] = {"read": [], "vo": [], "vp_ekf": [], "scan": [], "total": []}
    results: list[FrameResult] = []
    indices = range(n_frames)
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="vpslam", unit="frame")
    try:
        for index in indices:
            start = time.perf_counter()
            try:
                frame = sequence[index]
            except OctofactorError as exc:
                reason = str(exc)
                print(f"vpslam: skipped frame {index}: {reason}", file=sys.stderr)
                skipped_frames[type(exc).__name__] += 1
                skipped_list.append({"index": index, "reason": reason})
                slam.skip()
                continue
            timings["read"].append((time.perf_counter() - start) * 1e3)
            result = slam.step(frame)
            results.append(result)
            for note in result.notes:
                notes_count[note] += 1
            for key in ("vo", "vp_ekf", "scan"):
                timings[key].append(result.ms[key])
            timings["total"].append((time.perf_counter() - start) * 1e3 + result.ms["vo_reused"])
    finally:
        slam.close()
    if not results:
        raise OctofactorError(f"{seq_dir}: no frame could be read")
    if len(skipped_list) > MAX_SKIPPED_FRACTION * n_frames:
        first = skipped_list[0]
        raise OctofactorError(
            f"{seq_dir}: {len(skipped_list)} of {n_frames} frames could not be read (more than "
            f"{MAX_SKIPPED_FRACTION:.0%}; frame {first['index']}: {first['reason']}); nothing "
            "written")
    tree, map_ms = None, None
    if config.build_map:
        t_map = time.perf_counter()
        tree = _fuse(slam.graph, config)
        map_ms = (time.perf_counter() - t_map) * 1e3 / len(results)
    T = np.array([r.T_world_camera.matrix() for r in results])
    covs = np.array([r.T_world_camera.rotation().matrix() @ r.cov_pose[3:, 3:]
                     @ r.T_world_camera.rotation().matrix().T for r in results])
    stamps = np.array([r.timestamp for r in results])
    gt_positions = np.array([np.full(3, np.nan) if g is None else np.asarray(g.translation())
                             for g in (sequence.groundtruth_at(t) for t in stamps)])
    report = _report(config, slam, results, skipped_frames, skipped_list, notes_count,
                     timings, map_ms, sequence, stamps, T, covs[-1], name)
    out = VpSlamResult(slam.graph, tree, report, stamps, T[:, :3, 3], covs, T, gt_positions)
    if out_dir is not None:
        write_outputs(out, out_dir, sequence, ellipses=ellipses)
    return out


def check_intrinsics(sequence) -> None:
    """One-line error when the intrinsics cannot belong to the images (first frame's size,
    principal point inside the image, finite positive focal lengths and depth scale)."""
    intr = sequence.intrinsics
    values = (intr.fx, intr.fy, intr.cx, intr.cy, intr.depth_scale)
    if not all(np.isfinite(v) for v in values) or intr.fx <= 0 or intr.fy <= 0 \
            or intr.depth_scale <= 0:
        raise OctofactorError(f"{sequence.seq_dir}: intrinsics must be finite with positive "
                              f"fx, fy and depth scale, got {values}")
    if not (0 <= intr.cx <= intr.width and 0 <= intr.cy <= intr.height):
        raise OctofactorError(f"{sequence.seq_dir}: principal point ({intr.cx}, {intr.cy}) "
                              f"lies outside the {intr.width}x{intr.height} image")
    size = sequence.first_image_size()
    if size is not None and size != (intr.width, intr.height):
        raise OctofactorError(f"{sequence.seq_dir}: the images are {size[0]}x{size[1]} but "
                              f"the intrinsics are for {intr.width}x{intr.height}")
    if intr.fx > 20 * intr.width or intr.fy > 20 * intr.height:
        raise OctofactorError(f"{sequence.seq_dir}: focal length ({intr.fx}, {intr.fy}) does "
                              f"not fit a {intr.width}x{intr.height} image")


def _fuse(graph, config: VpSlamConfig):
    from mapping import fuse

    return fuse(graph, config.map_resolution, max_range=config.max_range)


def write_outputs(result: VpSlamResult, out_dir, sequence=None, ellipses: bool = True) -> None:
    """trajectory.txt (TUM) and its copy <name>.txt when the run has a name, graph.g2o,
    graph.graph (OctoMap ScanGraph: poses + scans), map.bt, map.ot, trajectory.png and
    report.json."""
    from estimation.io import write_g2o, write_scan_graph, write_tum

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.txt", result.graph)
    name = result.report.get("name")
    if name and safe_file_stem(name) != "trajectory":
        # evo and `octofactor eval` label a trajectory by its file name
        write_tum(out / f"{safe_file_stem(name)}.txt", result.graph)
    write_g2o(out / "graph.g2o", result.graph)
    if result.tree is not None:
        write_scan_graph(out / "graph.graph", result.graph)
        # .ot first: writing .bt converts the tree to max-likelihood, as OctoMap's
        # writeBinary does, and the .ot must keep the full log-odds.
        result.tree.write_ot(out / "map.ot")
        result.tree.write_bt(out / "map.bt")
    plot_trajectory(result, out / "trajectory.png", ellipses=ellipses)
    with atomic_write(out / "report.json", "w") as handle:
        json.dump(result.report, handle, indent=2)
        handle.write("\n")


def safe_file_stem(name: str) -> str:
    """``name`` usable as a file name stem (path separators and spaces replaced)."""
    import re

    return re.sub(r"[^A-Za-z0-9._+-]+", "_", name).strip("._") or "run"


def plot_trajectory(result: VpSlamResult, path, ellipses: bool = True) -> None:
    """Top (x-y) and side (x-z) views, estimate vs ground truth, thin 2-sigma ellipses under
    the trajectory (Fig. 8); the legend names the run."""
    from pipelines.plotting import covariance_ellipse, save_figure, use_agg

    plt = use_agg()
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    p, gt, covs = result.positions, result.positions_gt, result.position_covs
    step = max(1, len(p) // 40)
    label_est = result.report.get("name") or "estimate"
    for ax, (a, b), label in ((axes[0], (0, 1), "y [m]"), (axes[1], (0, 2), "z [m]")):
        if np.isfinite(gt).all(axis=1).any():
            ax.plot(gt[:, a], gt[:, b], "k-", lw=1.2, label="ground truth", zorder=3)
        ax.plot(p[:, a], p[:, b], "b.-", lw=0.8, ms=2, label=label_est, zorder=4)
        for k in range(0, len(p), step) if ellipses else ():
            ellipse = covariance_ellipse(p[k, [a, b]], covs[k][np.ix_([a, b], [a, b])])
            ax.plot(ellipse[:, 0], ellipse[:, 1], "r-", lw=0.3, alpha=0.5, zorder=2,
                    label="2-sigma" if k == 0 else None)
        ax.set_ylabel(label)
        ax.grid(True, lw=0.3)
    axes[0].set_title(f"VP-EKF SLAM ({result.report['vp_model']}): top and side views"
                      + (", 2-sigma ellipses" if ellipses else ""))
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_xlabel("x [m]")
    save_figure(fig, path)


# --------------------------------------------------------------------------- helpers

@dataclass(frozen=True)
class _VoFailure:
    """An odometry call that raised instead of returning a failure."""

    reason: str
    success: bool = False


def _vo_resampler(intr, scale: float):
    """(intrinsics, frame -> frame) for running the odometry on resized images."""
    if scale == 1.0:
        return intr, lambda frame: frame
    from perception.rgbd import resize_frame

    width, height = max(1, round(intr.width * scale)), max(1, round(intr.height * scale))
    return intr.resized(width, height), lambda frame: resize_frame(frame, width, height)


def _reason_class(reason: str) -> str:
    """The VO failure reason without its numbers (so the report can count them)."""
    return reason.split(" (")[0] if reason else "failed"


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def _report(config, slam, results, skipped_frames, skipped_list, notes_count, timings,
            map_ms, sequence, stamps, T, final_position_cov, name) -> dict:
    report = {
        "name": name,
        "frames": len(results),
        "vp_model": config.vp_model,
        "detector": config.detector if config.vp_model != "none" else None,
        "filter_state": config.ekf.state,
        "world_frame": slam.world_frame,
        "estimator": config.estimator,
        "distortion": None if sequence.distortion is None else list(sequence.distortion),
        "vp_detections": int(slam.counts["vp_detections"]),
        "vp_updates": int(slam.counts["vp_updated"]),
        "vp_gated": int(slam.counts["vp_gated"]),
        "vp_initialised": int(slam.counts["vp_initialised"]),
        "vp_same_view": int(slam.counts["vp_same_view"]),
        "vo_textureless_pairs": int(slam.counts["vo_textureless"]),
        "skipped_frames": dict(sorted(skipped_frames.items())),
        "skipped_frame_list": skipped_list,
        "skipped_updates": dict(sorted(notes_count.items())),
        "ms_per_frame_median": _median(timings["vp_ekf"]),
        "vo_ms_per_frame_median": _median(timings["vo"]),
        "read_ms_per_frame_median": _median(timings["read"]),
        "scan_ms_per_frame_median": _median(timings["scan"]),
        "map_ms_per_frame_mean": map_ms,
        "total_ms_per_frame_median": _median(timings["total"]),
        "final_position_sigma_m": np.sqrt(np.diag(final_position_cov)).tolist(),
        "config": config.to_dict(),
    }
    report["keyframes"] = int(slam.counts["keyframes"]) if slam._keyframes else None
    metrics = sequence_metrics(sequence, stamps, T)
    report.update(metrics)
    report.update(pose_nees(sequence, results) if slam.world_frame == "groundtruth"
                  else {"pose_nees_mean": None, "pose_nees_in_95": None})
    return report


def pose_nees(sequence, results) -> dict:
    """Mean pose NEES (6 dof) against ground truth and the share of frames inside the 95 %
    chi-square bound: the filter's honesty on real data (world frame = ground truth's)."""
    import gtsam
    from scipy.stats import chi2

    nees = []
    for r in results:
        gt = sequence.groundtruth_at(r.timestamp)
        if gt is None:
            continue
        xi = gtsam.Pose3.Logmap(r.T_world_camera.between(gt))
        try:
            nees.append(float(xi @ np.linalg.solve(r.cov_pose, xi)))
        except np.linalg.LinAlgError:
            continue
    if not nees:
        return {"pose_nees_mean": None, "pose_nees_in_95": None}
    nees = np.array(nees)
    return {"pose_nees_mean": float(np.mean(nees)),
            "pose_nees_in_95": float(np.mean(nees <= chi2.ppf(0.95, 6)))}


METRIC_KEYS = ("matched", "ate_aligned_rmse_m", "ate_unaligned_rmse_m",
               "ate_origin_aligned_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg",
               "rot_err_mean_deg", "aligned_rot_err_mean_deg")


def sequence_metrics(sequence, stamps, T) -> dict:
    """evo-style metrics against the sequence's groundtruth.txt (None without it)."""
    from estimation.errors import EstimationError
    from estimation.evaluation import evaluate_trajectory

    empty = {key: None for key in METRIC_KEYS}
    empty["final_drift_xyz_m"] = None
    gt = sequence.groundtruth_arrays()
    if gt is None:
        return empty
    t_gt, T_gt = gt
    try:
        m = evaluate_trajectory(t_gt, T_gt, stamps, T).to_dict()
    except EstimationError as exc:
        empty["evaluation"] = str(exc)
        return empty
    out = {key: m[key] for key in METRIC_KEYS}
    last_gt = sequence.groundtruth_at(stamps[-1])
    out["final_drift_xyz_m"] = (None if last_gt is None else
                                (T[-1][:3, 3] - np.asarray(last_gt.translation())).tolist())
    return out
