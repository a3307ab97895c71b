"""`octofactor vpslam SEQ_DIR -o OUT`: vanishing-point EKF SLAM on a TUM-layout RGB-D sequence."""
from __future__ import annotations

import argparse

from pipelines.cli_common import add_config, add_output, add_seed


def register(add_command) -> None:
    parser = add_command(
        "vpslam", "vanishing-point EKF SLAM (Ji et al.) on a TUM-layout RGB-D sequence: "
                  "trajectory, pose graph, octree map, figure and report")
    parser.add_argument("seq_dir", metavar="SEQ_DIR",
                        help="folder with rgb.txt, depth.txt, camera.txt [, groundtruth.txt]")
    add_output(parser, "output folder", metavar="OUT_DIR", old_option="--out", required=False)
    parser.add_argument("--name", default=None,
                        help="the run's name in report.json, the figure's legend and "
                        "OUT_DIR/<name>.txt (a copy of trajectory.txt, so evo labels runs "
                        "apart); default: the output folder's name (two runs on one sequence "
                        "get different names)")
    parser.add_argument("--intrinsics", metavar="FX,FY,CX,CY", type=_intrinsics,
                        help="override the sequence's camera file (image size from camera.txt "
                             "or the first image)")
    parser.add_argument("--distortion", metavar="K1,K2,P1,P2[,K3]", default=None,
                        type=_distortion,
                        help="the colour camera's lens distortion (OpenCV order; TUM fr1: "
                             "0.2624,-0.9531,-0.0054,0.0026,1.1633): frames are undistorted "
                             "on reading, the intrinsics stay the pinhole camera")
    parser.add_argument("--depth-scale", type=float, default=None,
                        help="depth PNG units per metre (TUM: 5000; default from camera.txt)")
    parser.add_argument("--no-vp", action="store_true",
                        help="VO only, no vanishing-point update (the paper's baseline)")
    parser.add_argument("--vp-model", choices=("manhattan", "point"), default=None,
                        help="manhattan (default): up to three directions of the structure; "
                             "point: the paper's one VP (eq. (11)-(13))")
    parser.add_argument("--detector", choices=("normals+lines", "normals", "lines", "seed"),
                        default=None,
                        help="direction source (default normals+lines: depth surface normals "
                             "and line VPs; seed: the paper's Hough detector, with --vp-model "
                             "point)")
    parser.add_argument("--filter", choices=("error", "euler"), default=None,
                        help="error (default): error-state EKF on SE(3), any pose; euler: the "
                             "paper's 9-D Euler state")
    parser.add_argument("--world-frame", choices=("auto", "groundtruth", "manhattan", "camera"),
                        default=None, help="auto (default): ground truth of the first frame, "
                                           "else the level Manhattan frame (docs/vp_ekf.md)")
    parser.add_argument("--vo-cov", choices=("coupled", "motion", "information"), default=None,
                        help="odometry covariance: coupled (default: fitted on real RGB-D, with "
                             "the geometry's rotation-translation correlations), motion (the "
                             "same sigmas, uncorrelated) or information (fitted on the "
                             "simulated corridor)")
    parser.add_argument("--keyframes", action="store_true", default=None,
                        help="odometry against keyframes (cloned in the filter) instead of "
                             "frame to frame (docs/vp_ekf.md)")
    parser.add_argument("--vp-min-motion", metavar="DEG,M", default=None,
                        type=_numbers(2, "DEG,M"),
                        help="measure directions only on frames that turned DEG or moved M "
                             "since the last one measured (default 0,0: every frame)")
    parser.add_argument("--direction-factors", choices=("predicted", "fixed", "none"),
                        default=None,
                        help="graph.g2o gets a direction factor per direction the filter "
                             "accepted, its world direction the filter's prediction of the "
                             "axis (predicted, default), the axis when first accepted (fixed), "
                             "or none (docs/vp_ekf.md)")
    parser.add_argument("--paper", action="store_true",
                        help="the seed paper's system: Euler state, point model, seed detector, "
                             "first body frame, simulator-fitted VO covariance (flags after it "
                             "still apply)")
    parser.add_argument("--vp-distance", type=float, default=None,
                        help="d of eq. (12) in metres (point model; default 1000: a direction)")
    parser.add_argument("--gate", type=float, default=None,
                        help="chi-square gate of eq. (15), 2 dof (default: 95 %% = 5.99; "
                             "--paper: 99 %% = 9.21)")
    parser.add_argument("--resolution", type=float, default=None,
                        help="octree leaf size (m; default 0.05)")
    parser.add_argument("--max-range", type=float, default=None,
                        help="cut map rays at this range (m, -1: no limit; default 5)")
    parser.add_argument("--no-map", action="store_true", help="skip clouds and octree")
    parser.add_argument("--vo-scale", type=float, default=None,
                        help="image scale for the odometry only (default 1; 0.5: ~4x faster, "
                        "noisier)")
    parser.add_argument("--max-frames", type=int, default=None, help="use the first N frames")
    parser.add_argument("--estimator", default=None, metavar="NAME",
                        help="filter estimator from `octofactor plugins` (vp_ekf)")
    parser.add_argument("--no-ellipses", action="store_true",
                        help="draw no 2-sigma ellipses in trajectory.png")
    add_config(parser, "VpSlamConfig")
    add_seed(parser, None, "OpenCV's RANSAC of the PnP guess; the detectors' samplers are "
             "seeded by their configs")
    parser.set_defaults(func=run)


def _numbers(counts, expected: str):
    """An argparse type: comma-separated numbers, as many as one of ``counts``."""
    counts = (counts,) if isinstance(counts, int) else tuple(counts)

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) not in counts:
            raise argparse.ArgumentTypeError(f"expected {expected} (comma-separated numbers)")
        return values

    return parse


def _distortion(text: str) -> tuple[float, ...] | None:
    """--distortion: OpenCV's coefficients, checked by perception.rgbd.check_distortion."""
    from perception.errors import PerceptionError
    from perception.rgbd import check_distortion

    try:
        return check_distortion(_numbers((4, 5, 8), "K1,K2,P1,P2[,K3]")(text))
    except PerceptionError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _intrinsics(text: str) -> tuple[float, float, float, float]:
    import math

    try:
        values = _numbers(4, "fx,fy,cx,cy")(text)
    except argparse.ArgumentTypeError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values) \
            or not all(v > 0 for v in values[:2]):
        raise argparse.ArgumentTypeError("expected fx,fy,cx,cy (four finite numbers, fx and "
                                         "fy > 0)")
    return values  # magnitudes: vpslam.check_intrinsics, against the images


def run(args) -> int:
    import json
    import sys
    from pathlib import Path

    from pipelines.cli_common import dump_config, output_of
    from pipelines.validate import vpslam_options
    from pipelines.vpslam import run_vpslam

    vpslam_options(args)
    intrinsics = None
    if args.intrinsics is not None or args.depth_scale is not None:
        intrinsics = _resolve_intrinsics(Path(args.seq_dir), args.intrinsics, args.depth_scale)
    config = build_config(args)
    if dump_config(args, config, "vpslam"):
        return 0
    if args.seed is not None and not args.deterministic:
        from pipelines.runtime import set_seed

        set_seed(args.seed)
    out_dir = output_of(args)
    name = args.name or Path(out_dir).resolve().name
    result = run_vpslam(args.seq_dir, out_dir, config, intrinsics=intrinsics,
                        progress=not args.quiet, max_frames=args.max_frames, name=name,
                        ellipses=not args.no_ellipses, distortion=args.distortion)
    summary = {k: result.report.get(k) for k in (
        "frames", "vp_updates", "vp_gated", "ate_aligned_rmse_m", "ate_unaligned_rmse_m",
        "rot_err_mean_deg", "final_drift_xyz_m",
        "ms_per_frame_median", "total_ms_per_frame_median")}
    print(json.dumps(summary), file=sys.stdout)
    return 0


def build_config(args):
    """The VpSlamConfig of the command line: --config FILE (or --paper, or the defaults), then
    the flags given."""
    import math
    from dataclasses import replace

    from estimation.errors import OctofactorError
    from pipelines.cli_common import base_config
    from pipelines.vpslam import VpSlamConfig

    if args.config and args.paper:
        raise OctofactorError("give --config FILE or --paper, not both (--paper is a config: "
                              "octofactor vpslam SEQ --paper --dump-config)")
    config = base_config(args, VpSlamConfig,
                         VpSlamConfig.paper() if args.paper else VpSlamConfig())
    ekf, odometry = config.ekf, config.odometry
    if args.filter is not None:
        ekf = replace(ekf, state=args.filter)
    if args.gate is not None:
        if not (args.gate > 0 and math.isfinite(args.gate)):
            raise OctofactorError(f"--gate must be a positive number, got {args.gate}")
        ekf = replace(ekf, gate_chi2=args.gate)
    if args.vp_distance is not None:
        if not math.isfinite(args.vp_distance) or args.vp_distance <= 0:
            raise OctofactorError(f"--vp-distance must be a positive number, got "
                                  f"{args.vp_distance}")
        ekf = replace(ekf, vp_distance=args.vp_distance)
    if args.vo_cov is not None:
        odometry = replace(odometry, cov_model=args.vo_cov)
    vp_model = "none" if args.no_vp else (args.vp_model or config.vp_model)
    changes = dict(vp_model=vp_model, ekf=ekf, odometry=odometry)
    for dest, field in (("resolution", "map_resolution"), ("max_range", "max_range"),
                        ("vo_scale", "vo_scale"), ("estimator", "estimator"),
                        ("world_frame", "world_frame"), ("detector", "detector"),
                        ("keyframes", "keyframes"), ("direction_factors", "direction_factors"),
                        ("vp_min_motion", "vp_min_motion")):
        if getattr(args, dest) is not None:
            changes[field] = getattr(args, dest)
    if args.no_map:
        changes["build_map"] = False
    if args.detector is None and vp_model == "manhattan" and config.detector == "seed":
        changes["detector"] = "normals+lines"  # the seed detector gives one VP
    return replace(config, **changes)


def _resolve_intrinsics(seq_dir, fx_fy_cx_cy, depth_scale):
    """CameraIntrinsics from --intrinsics / --depth-scale over camera.txt (or the first image)."""
    import math
    from dataclasses import replace

    from estimation.errors import FormatError
    from perception.rgbd import (
        CAMERA_FILE_NAME,
        CameraIntrinsics,
        listed_image_size,
        read_camera_file,
    )

    camera_file = seq_dir / CAMERA_FILE_NAME
    if fx_fy_cx_cy is not None:
        # the flag wins: camera.txt (perhaps of another layout) is not read at all
        width, height = listed_image_size(seq_dir)
        base = CameraIntrinsics(*fx_fy_cx_cy, width, height)
        if camera_file.is_file() and depth_scale is None:
            try:
                base = replace(base, depth_scale=read_camera_file(camera_file).depth_scale)
            except FormatError:
                pass  # another layout: TUM's default depth scale
    elif camera_file.is_file():
        base = read_camera_file(camera_file)
    else:
        raise FormatError(camera_file, "camera file not found (give --intrinsics)")
    if depth_scale is not None:
        if not (depth_scale > 0 and math.isfinite(depth_scale)):
            from estimation.errors import OctofactorError
            raise OctofactorError(f"--depth-scale must be positive, got {depth_scale}")
        base = replace(base, depth_scale=depth_scale)
    return base

