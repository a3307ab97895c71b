"""Vanishing-point EKF SLAM on a TUM-layout RGB-D sequence (Ji, Yamashita, Asama).

Per frame: read the images -> RGB-D odometry against the previous frame (prediction,
eq. (9)-(10)) -> vanishing point(s) (update, eq. (11)-(18)) -> a PoseGraph node at the
filtered pose with its marginal covariance and a VO between-factor -> 5 cm voxel filter
and octree insertion at the filtered pose (eq. (19)-(20)). Then the files: trajectory
(TUM), graph (g2o), map (.bt, .ot), figure and report.

Failures never stop the run: a missing/unreadable frame or a failed VO step predicts with
a constant-velocity guess and an inflated covariance; frames without a VP just predict.
Every skipped update is counted with its reason in the report.
"""
from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from estimation.errors import OctofactorError
from estimation.fileio import atomic_write


@dataclass(frozen=True)
class VpSlamConfig:
    """Settings of :func:`run_vpslam`.

    Attributes
    ----------
    vp_model : "point" (the paper: seed detector, one VP point), "manhattan" (up to three
        Manhattan VPs as directions) or "none" (VO only: the paper's baseline)
    vp_distance : d of eq. (12) in metres
    gate_chi2 : Mahalanobis gate of eq. (15) (chi-square, 2 dof; default 99 %)
    gate_recovery_frames : after this many consecutive frames whose VP updates were all
        gated, the filter is taken to have been misled (a VO outlier beyond its covariance,
        then the VO's pitch bias carries the state ever further from the VP, so every later
        VP is gated too): the pose covariance is inflated by ``gate_recovery_scale`` times
        the last VO covariance (an identity VO step: the missed error is taken to have the
        VO's own shape, whose pitch and vertical motion are coupled, so the VP can correct
        both) and the frame's VP is applied again; 0 disables it
    gate_recovery_scale : multiple of the VO covariance added on a recovery
    vp_pixel_floor : px, added in quadrature to the detector's VP covariance
    vo_failure_sigma : (rad, m) per-frame standard deviations when VO fails
    voxel_size : m, the voxel filter of section 4 (5 cm in the paper)
    map_resolution : m, octree leaf size
    max_range : m, rays longer than this are cut in the map (-1: no limit)
    backproject_stride : keep every n-th pixel row/column before the voxel filter (4 at
        640x480: 2.7 cm between samples at the Xtion's 3.5 m range, still denser than the
        5 cm voxels, and a quarter of the points of stride 2)
    build_map : False skips clouds and octree
    vo_scale : image scale for the RGB-D odometry only (0.5: a quarter of the pixels;
        on the simulated corridor ~3.8x faster with ~1.5x larger errors, covariance
        calibrated for 320 px; VP and map keep full resolution)
    estimator : name of a registered filter estimator (``octofactor plugins``) whose
        ``slam_filter(K, T_world_camera, cov_pose, ekf_config)`` builds the filter this
        pipeline steps (docs/plugins.md); the built-in is ``vp_ekf``
    """

    vp_model: str = "point"
    vp_distance: float = 1000.0
    gate_chi2: float = 9.21034037197618  # chi2.ppf(0.99, 2)
    vp_pixel_floor: float = 1.0
    gate_recovery_frames: int = 3
    gate_recovery_scale: float = 50.0
    vo_failure_sigma: tuple[float, float] = (0.05, 0.15)
    voxel_size: float = 0.05
    map_resolution: float = 0.05
    max_range: float = 5.0
    backproject_stride: int = 4
    build_map: bool = True
    vo_scale: float = 1.0
    estimator: str = "vp_ekf"

    def __post_init__(self):
        if self.vp_model not in ("point", "manhattan", "none"):
            raise OctofactorError(
                f"vp_model must be point, manhattan or none, got {self.vp_model!r}")
        if not 0.1 <= self.vo_scale <= 1.0:
            raise OctofactorError(f"vo_scale must be in [0.1, 1], got {self.vo_scale}")


@dataclass
class _Timings:
    read: list = field(default_factory=list)
    vo: list = field(default_factory=list)
    vp_ekf: list = field(default_factory=list)
    map: list = field(default_factory=list)
    total: list = field(default_factory=list)


@dataclass(frozen=True)
class VpSlamResult:
    """What :func:`run_vpslam` produced.

    Attributes
    ----------
    graph : estimation.PoseGraph, one node per filtered frame
    tree : mapping.OcTree or None
    report : dict, the content of report.json
    timestamps, positions, positions_gt : (N,), (N, 3), (N, 3) (nan rows without GT)
    position_covs : (N, 3, 3) world-frame position covariances
    """

    graph: object
    tree: object
    report: dict
    timestamps: np.ndarray
    positions: np.ndarray
    positions_gt: np.ndarray
    position_covs: np.ndarray


def run_vpslam(seq_dir, out_dir=None, config: VpSlamConfig = VpSlamConfig(), intrinsics=None,
               progress: bool = True, max_frames: int | None = None,
               odometry_cache: dict | None = None) -> VpSlamResult:
    """Run the VP-EKF SLAM on the sequence in ``seq_dir``; write the outputs to ``out_dir``.

    ``intrinsics`` (perception.rgbd.CameraIntrinsics) overrides the sequence's camera file.
    With ``out_dir`` None nothing is written (benchmarks). The visual odometry does not
    depend on the filter, so runs of several filter variants on one sequence can share it:
    pass the same ``odometry_cache`` dict (keyed by frame-index pairs; the reported VO
    time is then the time measured when the entry was computed).
    """
    import gtsam

    from estimation import PoseGraph, Scan
    from estimation.plugins import create_estimator
    from estimation.vp_ekf import VpEkfConfig
    from perception.odometry import rgbd_odometry
    from perception.rgbd import TumRgbdSequence, backproject, voxel_filter

    estimator = create_estimator(config.estimator, kind="filter")
    if not callable(getattr(estimator, "slam_filter", None)):
        raise OctofactorError(
            f"estimator {config.estimator!r} cannot run vpslam: it has no "
            "slam_filter(K, T_world_camera, cov_pose, ekf_config) method (docs/plugins.md)")
    sequence = TumRgbdSequence(seq_dir, intrinsics=intrinsics)
    intr = sequence.intrinsics
    vo_intr, vo_frame = _vo_resampler(intr, config.vo_scale)
    K = intr.K
    n_frames = len(sequence) if max_frames is None else min(len(sequence), max_frames)
    if n_frames == 0:
        raise OctofactorError(f"{seq_dir}: the sequence has no associated frames")

    tree, map_note = _make_tree(config) if config.build_map else (None, "disabled")
    graph = PoseGraph()
    counts = Counter()
    skipped = Counter()
    timings = _Timings()
    rows_t, rows_p, rows_gt, rows_cov = [], [], [], []
    ekf = None
    prev_frame = None
    prev_index = None
    prev_node = None
    T_guess = gtsam.Pose3()  # constant-velocity guess for the VO and for failures
    # motion predicted over unreadable frames since the last node (for its between-factor;
    # the covariances are summed without transport: they are inflated guesses anyway)
    gap_T, gap_cov = gtsam.Pose3(), np.zeros((6, 6))
    failure_cov = np.diag([config.vo_failure_sigma[0] ** 2] * 3
                          + [config.vo_failure_sigma[1] ** 2] * 3)
    pixel_floor = np.eye(2) * config.vp_pixel_floor ** 2
    last_vo_cov = failure_cov  # the shape of a recovery inflation (see the config)
    gated_run = 0  # consecutive frames whose VP updates were all gated

    indices = range(n_frames)
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="vpslam", unit="frame")
    for index in indices:
        start = time.perf_counter()
        try:
            frame = sequence[index]
        except OctofactorError as exc:
            skipped[f"frame unreadable: {type(exc).__name__}"] += 1
            if ekf is not None:
                # the frame's time still passes: constant velocity, inflated covariance
                ekf.predict_vo(T_guess, failure_cov)
                gap_T, gap_cov = gap_T.compose(T_guess), gap_cov + failure_cov
                prev_frame = None  # the next VO has no partner: it predicts from the guess
            continue
        timings.read.append((time.perf_counter() - start) * 1e3)
        counts["frames"] += 1

        t_vo = time.perf_counter()
        frame_vo = vo_frame(frame)
        resize_ms = (time.perf_counter() - t_vo) * 1e3
        if ekf is None:
            T0 = frame.T_world_camera_gt  # paper convention when no GT: body at identity
            cov0 = np.diag([1e-6] * 3 + [1e-6] * 3)
            ekf = estimator.slam_filter(K, T0, cov0, VpEkfConfig(
                vp_model="point" if config.vp_model == "none" else config.vp_model,
                vp_distance=config.vp_distance, gate_chi2=config.gate_chi2,
                vo_failure_sigma=config.vo_failure_sigma))
            vo_result = None
        else:
            t_vo = time.perf_counter()
            if prev_frame is None:
                vo_result = None
                skipped["vo: no previous frame"] += 1
                ekf.predict_vo(T_guess, failure_cov)
            else:
                cache_key = (prev_index, index, config.vo_scale)
                if odometry_cache is not None and cache_key in odometry_cache:
                    vo_result, measured_ms = odometry_cache[cache_key]
                    t_vo = time.perf_counter() - measured_ms / 1e3
                    start -= measured_ms / 1e3  # the frame's total counts the VO it reuses
                else:
                    try:
                        vo_result = rgbd_odometry(prev_frame, frame_vo, vo_intr, T_init=T_guess)
                    except OctofactorError as exc:  # e.g. a frame of the wrong size
                        vo_result = _VoFailure(f"error: {type(exc).__name__}")
                    if odometry_cache is not None:
                        odometry_cache[cache_key] = (
                            vo_result, (time.perf_counter() - t_vo) * 1e3)
                if vo_result.success:
                    ekf.predict_vo(vo_result.T_prev_curr, vo_result.cov)
                    T_guess, last_vo_cov = vo_result.T_prev_curr, vo_result.cov
                else:
                    skipped[f"vo: {_reason_class(vo_result.reason)}"] += 1
                    ekf.predict_vo(T_guess, failure_cov)
            timings.vo.append((time.perf_counter() - t_vo) * 1e3 + resize_ms)

        # --- vanishing points and EKF update
        t_vp = time.perf_counter()
        try:
            detection = _vp_detect(config, frame, K, counts, skipped)
            outcomes = _vp_update(ekf, config, detection, pixel_floor)
            if outcomes and all(o.status == "gated" for o in outcomes):
                gated_run += 1
                if config.gate_recovery_frames and gated_run >= config.gate_recovery_frames:
                    # the VO pitch bias drags a misled filter further away every frame:
                    # widen the orientation and let this frame's VP pull it back
                    ekf.predict_vo(gtsam.Pose3(), config.gate_recovery_scale * last_vo_cov)
                    counts["vp_gate_recoveries"] += 1
                    outcomes = _vp_update(ekf, config, detection, pixel_floor)
                    gated_run = 0
            elif outcomes:
                gated_run = 0
            for outcome in outcomes:
                _count(outcome, counts, skipped)
        except OctofactorError as exc:  # a detector or update error skips this frame's update
            skipped[f"vp: error: {type(exc).__name__}"] += 1
        timings.vp_ekf.append((time.perf_counter() - t_vp) * 1e3)

        # --- pose graph node and VO factor
        T_world_camera = ekf.T_world_camera
        cov_pose = ekf.pose_covariance()
        points_voxel = None
        t_map = time.perf_counter()
        if tree is not None:
            points = backproject(frame.depth_m, intr, stride=config.backproject_stride)
            points_voxel = voxel_filter(points, config.voxel_size)
            if len(points_voxel):
                # eq. (19)-(20): p_world = R_t p_sensor + x_S,t at the filtered pose
                R = T_world_camera.rotation().matrix()
                t = np.asarray(T_world_camera.translation())
                tree.insert_point_cloud((points_voxel @ R.T + t).astype(np.float32), t,
                                        max_range=config.max_range)
            timings.map.append((time.perf_counter() - t_map) * 1e3)
        graph.add_node(index, T_world_camera, frame.timestamp,
                       scan=None if points_voxel is None else Scan(points_voxel),
                       cov=cov_pose)
        if prev_node is None:
            graph.add_prior(index, T_world_camera, cov_pose)
        else:
            if vo_result is not None and vo_result.success:
                step_T, step_cov = vo_result.T_prev_curr, vo_result.cov
            else:
                step_T, step_cov = T_guess, failure_cov
            graph.add_between(prev_node, index, gap_T.compose(step_T), gap_cov + step_cov)
        gap_T, gap_cov = gtsam.Pose3(), np.zeros((6, 6))
        prev_node = index
        prev_frame, prev_index = frame_vo, index

        R_wc = T_world_camera.rotation().matrix()
        rows_t.append(frame.timestamp)
        rows_p.append(np.asarray(T_world_camera.translation(), dtype=float))
        rows_cov.append(R_wc @ cov_pose[3:, 3:] @ R_wc.T)
        gt = frame.T_world_camera_gt
        rows_gt.append(np.full(3, np.nan) if gt is None else np.asarray(gt.translation(), float))
        timings.total.append((time.perf_counter() - start) * 1e3)

    if ekf is None:
        raise OctofactorError(f"{seq_dir}: no frame could be read")
    positions, positions_gt = np.array(rows_p), np.array(rows_gt)
    report = _report(config, counts, skipped, timings, positions, positions_gt, map_note,
                     rows_cov[-1])
    result = VpSlamResult(graph, tree, report, np.array(rows_t), positions, positions_gt,
                          np.array(rows_cov))
    if out_dir is not None:
        write_outputs(result, out_dir)
    return result


def write_outputs(result: VpSlamResult, out_dir) -> None:
    """trajectory.txt, graph.g2o, map.bt, map.ot, trajectory.png and report.json."""
    from estimation.io import write_g2o, write_tum

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.txt", result.graph)
    write_g2o(out / "graph.g2o", result.graph)
    if result.tree is not None:
        # .ot first: writing .bt converts the tree to max-likelihood, as OctoMap's
        # writeBinary does, and the .ot must keep the full log-odds.
        result.tree.write_ot(out / "map.ot")
        result.tree.write_bt(out / "map.bt")
    plot_trajectory(result, out / "trajectory.png")
    with atomic_write(out / "report.json", "w") as handle:
        json.dump(result.report, handle, indent=2)
        handle.write("\n")


def plot_trajectory(result: VpSlamResult, path) -> None:
    """Top (x-y) and side (x-z) views, estimate vs ground truth, 2-sigma ellipses (Fig. 8)."""
    from pipelines.plotting import covariance_ellipse, save_figure, use_agg

    plt = use_agg()
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    p, gt, covs = result.positions, result.positions_gt, result.position_covs
    step = max(1, len(p) // 40)
    for ax, (a, b), name in ((axes[0], (0, 1), "y [m]"), (axes[1], (0, 2), "z [m]")):
        if np.isfinite(gt).all(axis=1).any():
            ax.plot(gt[:, a], gt[:, b], "k-", lw=1.2, label="ground truth")
        ax.plot(p[:, a], p[:, b], "b.-", lw=0.8, ms=2, label="estimate")
        for k in range(0, len(p), step):
            ellipse = covariance_ellipse(p[k, [a, b]], covs[k][np.ix_([a, b], [a, b])])
            ax.plot(ellipse[:, 0], ellipse[:, 1], "r-", lw=0.5)
        ax.set_ylabel(name)
        ax.grid(True, lw=0.3)
    axes[0].set_title(f"VP-EKF SLAM ({result.report['vp_model']}): top and side views, "
                      "2-sigma ellipses (vertical axes stretched)")
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_xlabel("x [m]")
    save_figure(fig, path)


# --------------------------------------------------------------------------- helpers

def _make_tree(config: VpSlamConfig):
    try:
        from mapping import OcTree

        return OcTree(config.map_resolution), "ok"
    except (ImportError, AttributeError) as exc:  # the mapping package is optional here
        import sys

        print(f"vpslam: map skipped ({exc})", file=sys.stderr)
        return None, f"skipped: {exc}"


def _vp_detect(config, frame, K, counts, skipped):
    """The frame's VP detection (None without one, or for vp_model "none"); counts it."""
    from perception.vanishing_points import detect_manhattan, detect_seed

    if config.vp_model == "none":
        return None
    bgr = np.ascontiguousarray(frame.rgb[..., ::-1])
    if config.vp_model == "point":
        vp = detect_seed(bgr, K=K).forward()
        if vp is None:
            skipped["vp: none detected"] += 1
        else:
            counts["vp_detections"] += 1
        return vp
    detection = detect_manhattan(bgr, K)
    if not detection.vps:
        skipped["vp: none detected"] += 1
        return None
    counts["vp_detections"] += len(detection.vps)
    return detection


def _vp_update(ekf, config, detection, pixel_floor) -> list:
    """Update the filter with a detection (eq. (11)-(18)); the outcomes, not yet counted."""
    if detection is None:
        return []
    if config.vp_model == "point":
        return [ekf.update_vp(detection.uv, _finite_cov(detection.cov) + pixel_floor)]
    uvs = [vp.uv for vp in detection.vps]
    covs = [None if vp.uv is None else _finite_cov(vp.cov) + pixel_floor
            for vp in detection.vps]
    return list(ekf.update_directions(np.array([vp.direction for vp in detection.vps]), uvs,
                                      covs))


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


def _finite_cov(cov) -> np.ndarray:
    cov = np.asarray(cov, dtype=float).reshape(2, 2)
    return cov if np.all(np.isfinite(cov)) else np.eye(2) * 1e6


def _reason_class(reason: str) -> str:
    """The VO failure reason without its numbers (so the report can count them)."""
    return reason.split(" (")[0] if reason else "failed"


def _count(outcome, counts: Counter, skipped: Counter) -> None:
    if outcome.status == "updated":
        counts["vp_updates"] += 1
    elif outcome.status == "gated":
        counts["vp_gated"] += 1
    elif outcome.status == "initialised":
        counts["vp_initialised"] += 1
    else:
        skipped[f"vp: {outcome.reason}"] += 1


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def _report(config, counts, skipped, timings, positions, positions_gt, map_note,
            final_position_cov) -> dict:
    has_gt = np.isfinite(positions_gt).all(axis=1)
    report = {
        "frames": int(counts["frames"]),
        "vp_model": config.vp_model,
        "estimator": config.estimator,
        "vp_detections": int(counts["vp_detections"]),
        "vp_updates": int(counts["vp_updates"]),
        "vp_gated": int(counts["vp_gated"]),
        "vp_initialised": int(counts["vp_initialised"]),
        "vp_gate_recoveries": int(counts["vp_gate_recoveries"]),
        "skipped_updates": dict(sorted(skipped.items())),
        "ate_rmse_m": None,
        "final_drift_xyz_m": None,
        "ms_per_frame_median": _median(timings.vp_ekf),
        "map_ms_per_frame_median": _median(timings.map),
        "vo_ms_per_frame_median": _median(timings.vo),
        "read_ms_per_frame_median": _median(timings.read),
        "total_ms_per_frame_median": _median(timings.total),
        "map": map_note,
        # world frame, like final_drift_xyz_m: compare them axis by axis
        "final_position_sigma_m": np.sqrt(np.diag(final_position_cov)).tolist(),
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(config).items()},
    }
    if has_gt.any():
        err = positions[has_gt] - positions_gt[has_gt]
        report["ate_rmse_m"] = float(math.sqrt(np.mean(np.sum(err ** 2, axis=1))))
        last = np.flatnonzero(has_gt)[-1]
        report["final_drift_xyz_m"] = (positions[last] - positions_gt[last]).tolist()
        report["travel_m"] = float(np.sum(np.linalg.norm(np.diff(positions_gt[has_gt], axis=0),
                                                         axis=1)))
    return report
