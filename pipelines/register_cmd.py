"""`octofactor register SOURCE TARGET` and `octofactor calibrate HEADSET MAP` (SOURCE TARGET
order everywhere: the headset cloud is registered to the map).

Both read semantic PLY files (perception.semantic_cloud layout; plain x y z PLYs work for
``--method gicp``), run GICP-SE(3) or Semantic-ICP and write RESULT.json with T
(T_target_source, 4x4), covariance (6x6, [rotation, translation]), converged, reason,
iterations, rescued (Semantic-ICP's second start: ``RegistrationConfig.semantic_rescue``),
inliers, fitness, rmse, time_s, covariance_diagnostic (quantisation pitch,
model-error share, correlation ratio, re-association gain, symmetric, direction gap, overlap,
off-surface share, voxel pitch of same-voxel matching, cell-crossing bias, map error, plane
tilt, covariance_trusted) and, with --gt, d_se3 (eq. (9)),
t_err_m, r_err_rad and nees.

``calibrate`` registers the headset cloud (source) to the robot's semantic map (target): the
result is T_map_headset. ``--left-handed`` first converts the headset's left-handed frame
(HoloLens/Unity: x right, y up, z forward) to a right-handed one by negating one axis
(``--flip-axis``, default z); the reported T then maps the converted (right-handed) headset
coordinates into the map, and "T_map_headset_left_handed" = T * diag(1, 1, -1, 1) maps raw
headset coordinates (a reflection, so not a rotation).
"""
from __future__ import annotations

import json
import sys

from pipelines.cli_common import add_config, add_output


def register(add_command) -> None:
    parser = add_command("register", "register two point-cloud PLY files (GICP-SE(3) or "
                                     "Semantic-ICP) and write RESULT.json")
    parser.add_argument("source", metavar="SOURCE", help="source cloud (PLY)")
    parser.add_argument("target", metavar="TARGET", help="target cloud (PLY)")
    _common(parser, default_method="gicp")
    parser.set_defaults(func=run_register)

    parser = add_command("calibrate", "calibrate a headset against the robot's semantic map "
                                      "(Semantic-ICP of the headset cloud to the map)")
    parser.add_argument("headset_pos", metavar="HEADSET", nargs="?",
                        help="headset semantic cloud (PLY; the source)")
    parser.add_argument("map_pos", metavar="MAP", nargs="?",
                        help="robot semantic map (PLY; the target)")
    parser.add_argument("--headset", help="the headset cloud, by name (instead of HEADSET)")
    parser.add_argument("--map", dest="robot_map", metavar="MAP",
                        help="the robot's map, by name (instead of MAP)")
    parser.add_argument("--left-handed", action="store_true",
                        help="the headset cloud is in a left-handed frame (HoloLens/Unity)")
    parser.add_argument("--flip-axis", choices=("x", "y", "z"), default="z",
                        help="axis negated to make the left-handed frame right-handed (z)")
    parser.add_argument("--graph", metavar="OUT.g2o",
                        help="also write a two-node pose graph (map=0, headset=1) with the "
                             "calibration factor")
    _common(parser, default_method="semantic")
    parser.set_defaults(func=run_calibrate)


def _common(parser, default_method: str) -> None:
    parser.add_argument("--method", choices=("gicp", "semantic"), default=default_method,
                        help=f"registration method ({default_method})")
    add_config(parser, "RegistrationConfig")
    parser.add_argument("--init", metavar="T.txt", help="initial T_target_source (4x4 text)")
    parser.add_argument("--gt", metavar="T.txt", help="ground-truth T_target_source (4x4 text)")
    parser.add_argument("--max-corr", type=float, default=None, metavar="D",
                        help="correspondence distance d_max at convergence, m (0.2)")
    parser.add_argument("--initial-corr", type=float, default=None, metavar="D",
                        help="d_max of the first iteration, annealed to --max-corr (none)")
    parser.add_argument("--alpha", type=float, default=None,
                        help="Cauchy kernel alpha, used as given (default: "
                        "from the residuals, or 2.0 on a voxel-lattice map)")
    parser.add_argument("--semantic-weight", choices=("inside", "outside"), default=None,
                        help="omega inside the Cauchy kernel (eq. (7)) or outside (Parkison)")
    parser.add_argument("--surface-radius", default=None, metavar="auto|none|R",
                        help="measure residuals between local surface means within R m; "
                        "auto: sqrt(3) x the voxel pitch when a cloud is a voxel-centre map "
                        "(default), none: between the samples")
    parser.add_argument("--max-iterations", type=int, default=None,
                        help="outer iterations at the final correspondence distance (60)")
    parser.add_argument("--systematic-sigma", default=None, metavar="S|SX,SY,SZ",
                        help="standard deviation (m) of an offset common to the whole source "
                        "that the data cannot show (the sensors' calibration or depth bias), "
                        "isotropic or along the target's x, y, z; added to the covariance (0)")
    parser.add_argument("--systematic-rotation-sigma", type=float, default=None, metavar="RAD",
                        help="standard deviation (rad, per axis) of a rotation of the whole "
                        "source about its own origin that the data cannot show (a sensor's "
                        "extrinsic rotation error); added to the covariance (0)")
    parser.add_argument("--plane-tilt", type=float, default=None, metavar="RAD",
                        help="on a voxel-lattice map (voxel centres, as an octree stores it), "
                        "the standard deviation (rad) of its planes' tilts against the "
                        "lattice that the map lost (default 0.001, a real room's map); 0: "
                        "planes exactly parallel to the lattice, as the room simulator builds "
                        "them")
    parser.add_argument("--estimator", metavar="NAME",
                        help="a registration estimator from `octofactor plugins` (overrides "
                        "--method; receives the clouds, --init and the class probabilities)")
    add_output(parser, "RESULT.json: T, covariance, convergence, errors with --gt",
               metavar="RESULT.json", required=False)


def _load(path: str, method: str):
    from estimation.errors import FormatError
    from perception.semantic_cloud import SemanticCloud

    try:
        return SemanticCloud.read_ply(path)
    except FormatError as exc:
        if method != "gicp" or "neither" not in str(exc):
            raise
    # geometry-only PLY (its header already checked by read_ply): fine for GICP
    import numpy as np

    from estimation.ply import read_ply_quietly
    from perception.errors import PerceptionError

    points = read_ply_quietly(path).point.positions.numpy().astype(float)
    try:
        return SemanticCloud(points, np.ones((len(points), 1)))
    except PerceptionError as exc:
        raise FormatError(path, str(exc)) from None


def _register(args, source, target, flip=None) -> tuple:
    import numpy as np

    from estimation.covariance import nees
    from estimation.errors import OctofactorError
    from estimation.registration import Registration, pose_error, read_transform

    if args.method == "semantic" or getattr(args, "estimator", None):
        from perception.errors import PerceptionError
        from perception.semantic_cloud import common_classes

        try:  # label files: one class list over the label values of both
            source, target = common_classes(source, target)
        except PerceptionError as exc:
            if args.method == "semantic":
                raise OctofactorError(f"source and target classes: {exc}: Semantic-ICP "
                                      "needs one label set") from None
    config = registration_config(args)
    init = read_transform(args.init) if args.init else None
    semantic = args.method == "semantic"
    if getattr(args, "estimator", None):
        import time

        from estimation.plugins import create_estimator

        estimator = create_estimator(args.estimator, kind="registration")
        start = time.perf_counter()
        result = estimator.register(source.points, target.points,
                                    np.eye(4) if init is None else init,
                                    source_probs=source.probs, target_probs=target.probs)
        elapsed = time.perf_counter() - start
    else:
        reg = Registration(source.points, target.points, config,
                           source.probs if semantic else None, target.probs if semantic else None)
        result = reg.run(init)
        elapsed = result.time_s
    out = {
        "method": getattr(result, "method", getattr(args, "estimator", None)),
        "T": np.asarray(result.T).tolist(), "covariance": np.asarray(result.covariance).tolist(),
        "converged": bool(result.converged), "reason": getattr(result, "reason", ""),
        "iterations": getattr(result, "iterations", None),
        "rescued": bool(getattr(result, "rescued", False)),
        "inliers": getattr(result, "inliers", None), "fitness": getattr(result, "fitness", None),
        "rmse": getattr(result, "rmse", None), "time_s": elapsed,
        "cost_log": list(getattr(result, "cost_log", [])),
        "source_points": len(source), "target_points": len(target),
    }
    diagnostic = getattr(result, "diagnostic", None)
    plugin = bool(getattr(args, "estimator", None))  # (not run with this config)
    if diagnostic is not None:
        out["covariance_diagnostic"] = {
            "quantisation_pitch_m": diagnostic.quantisation_pitch,
            "model_error_share": diagnostic.model_error_share,
            "correlation_ratio": diagnostic.correlation_ratio,
            "reassociation_gain": diagnostic.reassociation_gain,
            "symmetric": bool(diagnostic.symmetric),
            "direction_gap": (None if not diagnostic.symmetric
                              else float(diagnostic.direction_gap)),
            "overlap": (None if np.isnan(diagnostic.overlap[0])
                        else [float(v) for v in diagnostic.overlap]),
            "off_surface": (None if np.isnan(getattr(diagnostic, "off_surface", np.nan))
                            else float(diagnostic.off_surface)),
            "voxel_pitch_m": getattr(diagnostic, "voxel_pitch", None),
            "crossing_bias_m": getattr(diagnostic, "crossing_bias", None),
            "map_error_m": getattr(diagnostic, "map_error", None),
            "plane_tilt_rad": getattr(diagnostic, "plane_tilt", None),
            "lattice_noise_m": getattr(diagnostic, "lattice_noise", None),
            "inplane_quantisation": bool(getattr(diagnostic, "inplane_quantisation", False)),
            # (inputs, errors common to the whole source that the data cannot show: ours)
            "systematic_sigma_m": None if plugin else config.systematic_sigma,
            "systematic_rotation_sigma_rad": None if plugin else config.systematic_rotation_sigma,
            "covariance_trusted": bool(diagnostic.trusted)}
    alpha = getattr(result, "cauchy_alpha", None)
    if alpha is not None:
        out["cauchy_alpha"] = float(alpha)
    if flip is not None:
        out["T_left_handed"] = (result.T @ flip).tolist()
    if args.gt:
        T_gt = read_transform(args.gt)
        err = pose_error(result.T, T_gt)
        out.update(d_se3=err.d_se3, t_err_m=err.t_err_m, r_err_rad=err.r_err_rad,
                   nees=float(nees(err.tangent, result.covariance)))
    return out, result


def registration_config(args):
    """RegistrationConfig of --config FILE (else the CLI's d_max 0.2 m) and the flags given."""
    from dataclasses import replace

    from estimation.registration import RegistrationConfig
    from pipelines.cli_common import base_config, changes

    config = base_config(args, RegistrationConfig,
                         RegistrationConfig(max_correspondence_distance=0.2))
    update = changes(args, {"max_corr": "max_correspondence_distance",
                            "initial_corr": "initial_correspondence_distance",
                            "alpha": "cauchy_alpha", "semantic_weight": "semantic_weight",
                            "max_iterations": "max_iterations",
                            "systematic_rotation_sigma": "systematic_rotation_sigma",
                            "plane_tilt": "plane_tilt"})
    if args.surface_radius is not None:
        update["surface_radius"] = _surface_radius(args.surface_radius)
    if args.systematic_sigma is not None:
        from pipelines.validate import systematic_sigma

        update["systematic_sigma"] = systematic_sigma(args.systematic_sigma)
    if args.alpha is not None:  # a given alpha is used as given, not re-estimated
        update["cauchy_scale"] = "fixed"
    return replace(config, **update)


def _dump(args, command: str) -> bool:
    from pipelines.cli_common import dump_config
    from pipelines.validate import registration_numbers

    registration_numbers(args)  # named in the error, before RegistrationConfig sees them
    return dump_config(args, registration_config(args), command)


def _output(args) -> str:
    from estimation.errors import OctofactorError

    if not args.output:
        raise OctofactorError("the output is missing: give -o/--output RESULT.json")
    return args.output


def _write(path: str, out: dict) -> None:
    from estimation.fileio import atomic_write

    with atomic_write(path, "w") as handle:
        json.dump(out, handle, indent=2)
        handle.write("\n")


def _summary(out: dict) -> str:
    """One line; a plug-in's result may not report iterations, inliers or a reason."""
    parts = [f"converged={out['converged']}" + (f" ({out['reason']})" if out["reason"] else "")]
    if out.get("rescued"):
        parts.append("second start with geometric annealing (the first was not trusted)")
    for key, unit in (("iterations", "iterations"), ("inliers", "inliers")):
        if out[key] is not None:
            parts.append(f"{out[key]} {unit}")
    parts.append(f"{out['time_s']:.3f} s")
    text = f"{out['method']}: " + ", ".join(parts)
    if "d_se3" in out:
        text += (f"; d_SE(3)={out['d_se3']:.4f}, t_err={out['t_err_m']:.4f} m, "
                 f"r_err={out['r_err_rad']:.4f} rad")
    diagnostic = out.get("covariance_diagnostic")
    if diagnostic and not diagnostic["covariance_trusted"]:
        from estimation.registration import RegistrationConfig
        from estimation.registration.gicp import INSIDE_TRUSTED_COVERAGE, source_inside_target

        overlap = diagnostic.get("overlap")
        gap = diagnostic.get("direction_gap")
        inside = overlap is not None and source_inside_target(*overlap)
        if not out["converged"]:
            text += "; covariance not trusted (the estimate did not converge)"
        elif gap is not None and gap > RegistrationConfig.trust_gap:
            text += (f"; covariance not trusted (the two directions found different "
                     f"solutions: gap {gap:.0f}, another basin?)")
        elif (diagnostic.get("off_surface") or 0.0) > RegistrationConfig.trust_off_surface:
            text += (f"; covariance not trusted ({diagnostic['off_surface']:.0%} of the source's "
                     f"points near the target lie just off its surfaces: another basin?)")
        elif inside and diagnostic.get("map_error_m") is None:
            text += ("; covariance not trusted (the source lies inside a map whose voxel "
                     "grid was not found: the map's representation error is not in it)")
        elif inside and overlap[0] < INSIDE_TRUSTED_COVERAGE:
            text += (f"; covariance not trusted (the source lies inside a map, but only "
                     f"{overlap[0]:.1%} of it on the map's surfaces: another basin?)")
        else:
            text += (f"; covariance not trusted (residuals correlated beyond its blocks: "
                     f"ratio {diagnostic['correlation_ratio']:.2f})")
    return text


def run_register(args) -> int:
    if _dump(args, "register"):
        return 0
    output = _output(args)
    from pipelines.validate import registration_options

    registration_options(args)  # before the clouds are read
    source = _load(args.source, args.method)
    target = _load(args.target, args.method)
    out, _ = _register(args, source, target)
    _write(output, out)
    print(_summary(out))
    return 0 if out["converged"] else 1


def run_calibrate(args) -> int:
    import numpy as np

    from estimation.errors import OctofactorError

    if _dump(args, "calibrate"):
        return 0
    # named flags fill their slots; the positionals fill the rest in the order HEADSET MAP
    paths = {"headset": args.headset, "map": args.robot_map}
    positionals = [p for p in (args.headset_pos, args.map_pos) if p is not None]
    for which in ("headset", "map"):
        if paths[which] is None and positionals:
            paths[which] = positionals.pop(0)
    if positionals:
        raise OctofactorError(f"too many clouds: {', '.join(positionals)} (calibrate HEADSET "
                              "MAP, or --headset H --map M)")
    missing = [k for k, v in paths.items() if v is None]
    if missing:
        raise OctofactorError(f"missing the {' and the '.join(missing)} cloud: calibrate "
                              "HEADSET MAP (or --headset H --map M)")
    output = _output(args)
    from pipelines.validate import registration_options

    registration_options(args)  # before the clouds are read
    headset = _load(paths["headset"], args.method)  # source first, as in register
    robot_map = _load(paths["map"], args.method)
    flip = None
    if args.left_handed:
        flip = np.eye(4)
        flip["xyz".index(args.flip_axis), "xyz".index(args.flip_axis)] = -1.0
        headset = headset.transformed(flip)
    out, result = _register(args, headset, robot_map, flip)
    out["frames"] = "T = T_map_headset (headset -> robot map)"
    if args.left_handed:
        out["frames"] += f"; headset axis {args.flip_axis} negated first (left-handed input)"
    _write(output, out)
    if args.graph and not result.converged:
        print(f"not writing {args.graph}: the calibration did not converge", file=sys.stderr)
    elif args.graph:
        import gtsam

        from estimation.io import write_pose_graph
        from estimation.pose_graph import PoseGraph

        pg = PoseGraph()
        pg.add_node(0, gtsam.Pose3(), frame="robot_map")
        pg.add_node(1, result.pose, frame="headset")
        pg.add_prior(0, gtsam.Pose3(), np.eye(6) * 1e-10)
        result.add_to_pose_graph(pg, 0, 1, kind="calibration")
        write_pose_graph(args.graph, pg)
    print(_summary(out))
    return 0 if out["converged"] else 1


def _surface_radius(text: str) -> float | str | None:
    """Parse --surface-radius: "auto", "none" or a positive number of metres."""
    from estimation.errors import OctofactorError

    if text in ("auto", "none"):
        return None if text == "none" else "auto"
    try:
        radius = float(text)
    except ValueError:
        radius = float("nan")
    if not 0 < radius <= 1e6:
        raise OctofactorError(f"--surface-radius must be auto, none or a positive number of "
                              f"metres (at most 1e6), got {text!r}")
    return radius
