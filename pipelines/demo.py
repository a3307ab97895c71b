"""The demo: every capability on built-in synthetic data, results and figures in one folder."""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .plotting import covariance_ellipse, save_figure, use_agg, world_translation_covariance


@dataclass(frozen=True)
class PoseGraphDemoResult:
    initial_error: float
    final_error: float
    ate_initial_m: float
    ate_optimized_m: float
    files: tuple[str, ...]


def pose_graph_demo(out_dir: Path, seed: int = 0) -> PoseGraphDemoResult:
    """Simulate a noisy loop (odometry + one loop closure), optimise it, write files and a PNG."""
    from estimation.io import write_g2o, write_tum
    from estimation.pose_graph import PoseGraph
    from estimation.simulation import simulate_loop_graph

    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sim = simulate_loop_graph(rng, n_poses=36, odometry_sigmas=(0.02, 0.08))
    graph = sim.graph
    initial = copy.deepcopy(graph.nodes)
    result = graph.optimize("lm")
    covariances = {i: graph.marginal_covariance(i) for i in graph.sorted_ids()}

    truth_graph = PoseGraph()
    for i, pose in enumerate(sim.truth):
        truth_graph.add_node(i, pose, timestamp=graph.nodes[i].timestamp)
    initial_graph = PoseGraph()
    for i, node in initial.items():
        initial_graph.add_node(i, node.pose, timestamp=node.timestamp)

    files = {
        "pose_graph_truth.txt": lambda p: write_tum(p, truth_graph),
        "pose_graph_initial.txt": lambda p: write_tum(p, initial_graph),
        "pose_graph_optimized.txt": lambda p: write_tum(p, graph),
        "pose_graph.g2o": lambda p: write_g2o(p, graph),
    }
    for name, write in files.items():
        write(out_dir / name)

    def ate(nodes) -> float:
        errors = [nodes[i].pose.translation() - sim.truth[i].translation() for i in nodes]
        return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))

    plt = use_agg()
    fig, ax = plt.subplots(figsize=(7, 6))
    truth_xy = np.array([p.translation()[:2] for p in sim.truth])
    init_xy = np.array([initial[i].pose.translation()[:2] for i in graph.sorted_ids()])
    opt_xy = np.array([graph.nodes[i].pose.translation()[:2] for i in graph.sorted_ids()])
    ax.plot(*np.vstack([truth_xy, truth_xy[:1]]).T, "k--", lw=1, label="ground truth")
    ax.plot(*init_xy.T, ".-", color="tab:red", lw=1, label="dead reckoning (initial)")
    ax.plot(*opt_xy.T, ".-", color="tab:blue", lw=1.5, label="optimised (LM)")
    for i in graph.sorted_ids():
        node = graph.nodes[i]
        cov_xyz = world_translation_covariance(node.pose.rotation().matrix(), covariances[i])
        ellipse = covariance_ellipse(node.pose.translation()[:2], cov_xyz[:2, :2])
        ax.plot(*ellipse.T, color="tab:blue", lw=0.6, alpha=0.7)
    ax.set_title("Pose graph: loop with one closure, 2-sigma marginal ellipses")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.axis("equal")
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, out_dir / "pose_graph.png")
    summary = PoseGraphDemoResult(result.initial_error, result.final_error, ate(initial),
                                  ate(graph.nodes), (*files, "pose_graph.png"))
    return summary


def corridor_demo(out_dir: Path, quick: bool = False) -> dict:
    """Simulate the corridor, run the VP-EKF SLAM with and without the VP, map it."""
    from perception.simulation.corridor import CorridorConfig, simulate_corridor
    from pipelines.vpslam import VpSlamConfig, run_vpslam

    sequence = out_dir / "corridor_sequence"
    config = CorridorConfig(seed=0, length=6.0 if quick else 20.0)
    n_frames = simulate_corridor(sequence, config, progress=True)
    shared_vo: dict = {}
    results = {}
    from perception.odometry import OdometryConfig

    # the simulator's VO error (a pitch bias coupled with vertical motion) has its own
    # calibrated covariance (perception.odometry.COV_CALIBRATION)
    simulator_vo = OdometryConfig(cov_model="information")
    for name, model in (("with_vp", "manhattan"), ("without_vp", "none")):
        results[name] = run_vpslam(
            sequence, out_dir / f"vpslam_{name}",
            VpSlamConfig(vp_model=model, build_map=(model != "none"), odometry=simulator_vo),
            progress=True, odometry_cache=shared_vo, name=f"vpslam_{name}")
    _plot_vp_comparison(results, out_dir / "vpslam_comparison.png")
    summary = {"frames": n_frames, "corridor_length_m": config.length}
    if results["with_vp"].tree is not None:
        summary["shared_graph"] = shared_graph_demo(out_dir / "shared_graph", sequence, config,
                                                    results["with_vp"].graph)
    for name, result in results.items():
        keys = ("ate_aligned_rmse_m", "ate_unaligned_rmse_m", "rot_err_mean_deg",
                "final_drift_xyz_m", "ms_per_frame_median", "vo_ms_per_frame_median",
                "map_ms_per_frame_mean", "total_ms_per_frame_median", "vp_updates", "vp_gated")
        summary[name] = {key: result.report.get(key) for key in keys}
    tree = results["with_vp"].tree
    if tree is not None:
        summary["map"] = {
            "resolution_m": tree.resolution, "nodes": int(tree.size()),
            "leaves": int(tree.num_leaf_nodes()), "memory_bytes": int(tree.memory_usage()),
            "bt_bytes": (out_dir / "vpslam_with_vp" / "map.bt").stat().st_size,
        }
        _plot_map_slice(tree, out_dir / "map_slice.png")
    return summary


HEADSET_OFFSET = ((0.25, -0.15, 0.05), (0.15, -0.25, 0.40))  # rad (x, y, z), m: camera frame
HEADSET_INIT_ERROR = (0.15, 8.0)  # m, deg: the calibration's initial guess is this far off


def shared_graph_demo(out_dir: Path, sequence: Path, config, graph) -> dict:
    """One pose graph: the SLAM run, the headset calibration and the map.

    ``graph`` is the VP-SLAM run's graph (VO between factors, direction factors, the first
    node's prior, the voxel-filtered scans). A headset looks at the corridor from a pose near
    the middle of the run (a known offset from the camera's true pose there); its cloud is
    registered with GICP-SE(3) to the map around the middle node -- the scans of the nodes
    within +-6 of it, in that node's frame, as the graph places them -- and the result
    (T_node_headset with its covariance) is a ``calibration`` between factor from that node to
    a new headset node, which carries the headset cloud as its scan. The whole graph is
    optimised (LM); the headset pose and its marginal covariance (which includes the SLAM's
    uncertainty at the anchor node) go to ``headset.json``; the map is fused from the
    optimised graph (``map.bt``, ``graph.graph``, ``graph.g2o`` + sidecar).
    """
    import gtsam

    from estimation.covariance import nees
    from estimation.fileio import atomic_write
    from estimation.io import write_g2o, write_scan_graph
    from estimation.pose_graph import Scan
    from estimation.registration import Registration, RegistrationConfig
    from mapping import fuse
    from perception.rgbd import TumRgbdSequence, backproject, voxel_filter
    from perception.simulation.corridor import build_corridor_scene, render_frame

    out_dir.mkdir(parents=True, exist_ok=True)
    ids = graph.sorted_ids()
    anchor = ids[len(ids) // 2]
    T_world_anchor_gt = TumRgbdSequence(sequence).groundtruth_at(graph.nodes[anchor].timestamp)
    rotation, translation = HEADSET_OFFSET
    T_anchor_headset_gt = gtsam.Pose3(gtsam.Rot3.RzRyRx(*rotation), np.array(translation))
    T_world_headset_gt = T_world_anchor_gt.compose(T_anchor_headset_gt)
    rng = np.random.default_rng([config.seed, 13])
    intr = config.intrinsics
    _, depth = render_frame(build_corridor_scene(config), T_world_headset_gt, intr, rng)
    headset = voxel_filter(backproject(depth, intr, stride=2), 0.05).astype(float)

    # the map around the anchor, in the anchor's frame, as the graph places the scans
    T_world_anchor = graph.nodes[anchor].pose
    window = [j for j in ids if abs(j - anchor) <= 6 and graph.nodes[j].scan is not None]
    submap = np.vstack([
        _transform(T_world_anchor.between(graph.nodes[j].pose), graph.nodes[j].scan.points)
        for j in window])
    offset = gtsam.Pose3.Expmap(np.r_[_random_unit(rng) * np.radians(HEADSET_INIT_ERROR[1]),
                                      _random_unit(rng) * HEADSET_INIT_ERROR[0]])
    init = T_anchor_headset_gt.compose(offset)
    registration = Registration(headset, voxel_filter(submap, 0.05).astype(float),
                                RegistrationConfig(max_correspondence_distance=0.1,
                                                   initial_correspondence_distance=0.5))
    result = registration.run(init.matrix())
    summary = {"anchor_node": anchor, "window_nodes": len(window),
               "headset_points": len(headset), "map_points": len(submap),
               "initial_offset": f"{HEADSET_INIT_ERROR[0]} m / {HEADSET_INIT_ERROR[1]} deg",
               "registration_converged": bool(result.converged)}
    if not result.converged:  # a wrong constraint is worse than none
        summary["reason"] = result.reason
        return summary
    headset_id = ids[-1] + 1
    graph.add_node(headset_id, T_world_anchor.compose(result.pose),
                   graph.nodes[anchor].timestamp, scan=Scan(headset.astype(np.float32)),
                   frame="headset")
    result.add_to_pose_graph(graph, anchor, headset_id, kind="calibration")
    optimised = graph.optimize("lm")
    cov = graph.marginal_covariance(headset_id)
    T_world_headset = graph.nodes[headset_id].pose
    xi = gtsam.Pose3.Logmap(T_world_headset.between(T_world_headset_gt))  # T_gt = T Exp(xi)
    tree = fuse(graph, 0.05, max_range=5.0)
    write_g2o(out_dir / "graph.g2o", graph)
    write_scan_graph(out_dir / "graph.graph", graph)
    tree.write_bt(out_dir / "map.bt")
    summary.update({
        "headset_node": headset_id, "factors": graph.factor_counts(),
        "initial_error": optimised.initial_error, "final_error": optimised.final_error,
        "T_world_headset": T_world_headset.matrix().tolist(),
        "covariance": cov.tolist(), "covariance_order": "[rotation, translation], body frame",
        "sigma_rot_deg": np.degrees(np.sqrt(np.diag(cov)[:3])).tolist(),
        "sigma_trans_m": np.sqrt(np.diag(cov)[3:]).tolist(),
        "T_world_headset_gt": T_world_headset_gt.matrix().tolist(),
        "t_err_m": float(np.linalg.norm(T_world_headset.translation()
                                        - T_world_headset_gt.translation())),
        "r_err_deg": float(np.degrees(np.linalg.norm(xi[:3]))),
        "nees": float(nees(xi, cov)),
        "registration_covariance": np.asarray(result.covariance).tolist(),
        "anchor_covariance": graph.marginal_covariance(anchor).tolist(),
        "map_nodes": int(tree.size()),
    })
    with atomic_write(out_dir / "headset.json", "w") as handle:
        json.dump(summary, handle, indent=2)
        handle.write("\n")
    return summary


def _transform(T, points: np.ndarray) -> np.ndarray:
    M = T.matrix()
    return np.asarray(points, dtype=float) @ M[:3, :3].T + M[:3, 3]


def _random_unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _plot_vp_comparison(results: dict, path: Path) -> None:
    plt = use_agg()
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    any_result = next(iter(results.values()))
    gt = any_result.positions_gt
    for ax, axis, label in ((axes[0], 1, "y [m]"), (axes[1], 2, "z [m]")):
        ax.plot(gt[:, 0], gt[:, axis], "k-", lw=1.2, label="ground truth")
        for (name, result), colour in zip(results.items(), ("tab:blue", "tab:red")):
            p, covs = result.positions, result.position_covs
            ax.plot(p[:, 0], p[:, axis], ".-", color=colour, ms=2, lw=0.8,
                    label=name.replace("_", " "))
            for k in range(0, len(p), max(1, len(p) // 25)):
                ellipse = covariance_ellipse(p[k, [0, axis]],
                                             covs[k][np.ix_([0, axis], [0, axis])])
                ax.plot(*ellipse.T, color=colour, lw=0.4, alpha=0.7)
        ax.set_ylabel(label)
        ax.grid(True, lw=0.3)
    axes[0].set_title("VP-EKF SLAM on the simulated corridor: with vs without the vanishing "
                      "point (2-sigma ellipses)")
    axes[0].legend(fontsize=8)
    axes[1].set_xlabel("x [m] (along the corridor)")
    save_figure(fig, path)


def _plot_map_slice(tree, path: Path) -> None:
    from mapping.export import save_height_slice

    save_height_slice(tree, path)


def calibration_demo(out_dir: Path, quick: bool = False) -> dict:
    """Simulate the room; calibrate each headset view with GICP-SE(3) and Semantic-ICP
    from a wide initial offset (1.0 m / 40 deg about the cloud's centroid)."""
    from tqdm import tqdm

    from estimation.registration import RegistrationConfig, pose_error, register
    from estimation.registration.metrics import offset_about_centroid
    from perception.semantic_cloud import SemanticCloud
    from perception.simulation.room import RoomConfig, simulate_room

    room_dir = out_dir / "room"
    views = ("tv", "desk") if quick else ("tv", "desk", "shelf", "dining")
    written = simulate_room(room_dir, RoomConfig(seed=0, label_accuracy=0.9), views=views)
    robot_map = SemanticCloud.read_ply(written["robot_map"])
    # (plane_tilt 0: the simulator's map is a voxel lattice whose planes lie exactly on it)
    config = RegistrationConfig(max_correspondence_distance=0.2,
                                initial_correspondence_distance=1.0, plane_tilt=0.0)
    rng = np.random.default_rng(0)
    rows = []
    jobs = [(view, method) for view in views for method in ("gicp", "semantic")]
    inits = {}
    for view, method in tqdm(jobs, desc="calibration", unit="run"):
        headset = SemanticCloud.read_ply(written[f"headset_{view}"])
        T_gt = np.loadtxt(written[f"T_map_headset_{view}"])
        if view not in inits:  # both methods start from the same guess
            inits[view] = T_gt @ offset_about_centroid(rng, headset.points.mean(axis=0),
                                                       1.0, 40.0)
        semantic = method == "semantic"
        result = register(headset.points, robot_map.points, inits[view], config,
                          headset.probs if semantic else None,
                          robot_map.probs if semantic else None)
        error = pose_error(result.T, T_gt)
        rows.append({"view": view, "method": "Semantic-ICP" if semantic else "GICP-SE(3)",
                     "converged": bool(result.converged), "d_se3": error.d_se3,
                     "t_err_m": error.t_err_m, "r_err_deg": float(np.degrees(error.r_err_rad)),
                     "time_s": result.time_s, "points": len(headset)})
    return {"label_accuracy": 0.9,
            "initial_offset": "1.0 m / 40 deg about the headset cloud's centroid",
            "rows": rows}


SUCCESS_D_SE3 = 0.1  # a calibration counts as a success below this d_SE(3)


def consistency_demo(quick: bool = False) -> dict:
    """Mean NEES with its 95 % chi-square band for the pose graph and the VP-EKF."""
    from estimation.builtin_estimators import VPEKFEstimator
    from estimation.covariance import check_consistency
    from estimation.plugins import filter_nees
    from estimation.simulation import loop_graph_joint_nees

    n_runs = 30 if quick else 100
    values = [loop_graph_joint_nees(1000 + seed, 10) for seed in range(n_runs)]
    graph_check = check_consistency(np.array(values), dof=60)
    ekf_runs = [filter_nees(VPEKFEstimator(), VPEKFEstimator().simulate(
        np.random.default_rng(seed), 30)) for seed in range(n_runs)]
    ekf_check = check_consistency(np.array(ekf_runs), dof=9, min_fraction=0.8)
    return {
        "pose_graph": {"runs": n_runs, "dof": 60, "mean_nees": graph_check.mean,
                       "band": [graph_check.lower, graph_check.upper],
                       "passed": graph_check.passed},
        "vp_ekf": {"runs": n_runs, "dof": 9, "mean_nees": ekf_check.mean,
                   "band": [ekf_check.lower, ekf_check.upper],
                   "steps_inside": ekf_check.fraction_inside, "passed": ekf_check.passed},
    }


def write_report_md(out_dir: Path, report: dict) -> None:
    """out/report.md: the key numbers and the figures of every stage."""
    from estimation.fileio import atomic_write

    lines = ["# octofactor demo", "",
             "All data are synthetic and generated by this run (seed 0).", ""]
    pg = report["pose_graph"]
    lines += ["## Pose graph (loop with one closure)", "",
              f"GTSAM error {pg['initial_error']:.4g} -> {pg['final_error']:.4g}; ATE "
              f"{pg['ate_initial_m']:.3f} m (dead reckoning) -> {pg['ate_optimized_m']:.3f} m "
              "(optimised).", "", "![pose graph](pose_graph.png)", ""]
    corridor = report.get("corridor")
    if corridor:
        lines += ["## VP-EKF SLAM on the simulated corridor", "",
                  f"{corridor['frames']} frames, corridor {corridor['corridor_length_m']:.0f} m.",
                  "", "| run | ATE [m] | final drift x, y, z [m] | VP+EKF ms | VO ms | "
                  "total ms/frame |", "|---|---|---|---|---|---|"]
        for name in ("with_vp", "without_vp"):
            r = corridor[name]
            drift = ", ".join(f"{v:+.3f}" for v in (r["final_drift_xyz_m"] or []))
            ate = r["ate_unaligned_rmse_m"]
            lines.append(f"| {name.replace('_', ' ')} | {ate:.3f} | {drift} | "
                         f"{r['ms_per_frame_median']:.1f} | {r['vo_ms_per_frame_median']:.0f} | "
                         f"{r['total_ms_per_frame_median']:.0f} |")
        lines += ["", "![VP comparison](vpslam_comparison.png)", "",
                  "![trajectory with VP](vpslam_with_vp/trajectory.png)", ""]
        if "map" in corridor:
            m = corridor["map"]
            lines += ["## Octree map (fused at the VP-EKF poses)", "",
                      f"Resolution {m['resolution_m']} m: {m['nodes']} nodes, {m['leaves']} "
                      f"leaves, {m['memory_bytes']} B in memory, .bt {m['bt_bytes']} B "
                      f"(vpslam_with_vp/map.bt, .ot beside it).", "",
                      "![map slice](map_slice.png)", ""]
    shared = (corridor or {}).get("shared_graph")
    if shared and "headset_node" in shared:
        sig_r, sig_t = shared["sigma_rot_deg"], shared["sigma_trans_m"]
        lines += ["## One pose graph: SLAM, headset calibration and map", "",
                  f"The SLAM run's graph ({shared['factors']}) with the headset registered "
                  f"(GICP-SE(3), initial offset {shared['initial_offset']}) to the map around "
                  f"node {shared['anchor_node']}, optimised together (LM, error "
                  f"{shared['initial_error']:.4g} -> {shared['final_error']:.4g}).", "",
                  f"Headset pose error {shared['t_err_m'] * 100:.1f} cm / "
                  f"{shared['r_err_deg']:.2f} deg; marginal 1-sigma rotation "
                  f"{', '.join(f'{v:.2f}' for v in sig_r)} deg, translation "
                  f"{', '.join(f'{v * 100:.1f}' for v in sig_t)} cm (NEES "
                  f"{shared['nees']:.1f}, 6 dof). Files: shared_graph/headset.json, graph.g2o, "
                  "graph.graph, map.bt.", ""]
    elif shared:
        lines += ["## One pose graph: SLAM, headset calibration and map", "",
                  "The headset registration did not converge: no calibration factor.", ""]
    calibration = report.get("calibration")
    if calibration:
        lines += ["## Robot-headset calibration in the simulated room (Table 1 style)", "",
                  f"Headset label accuracy {calibration['label_accuracy']:.0%}; initial offset "
                  f"{calibration['initial_offset']}.", "",
                  f"| view | method | converged | success (d_SE(3) < {SUCCESS_D_SE3}) | d_SE(3) | "
                  "t error [m] | r error [deg] | time [s] |", "|---|---|---|---|---|---|---|---|"]
        for row in calibration["rows"]:
            lines.append(f"| {row['view']} | {row['method']} | {row['converged']} | "
                         f"{row['d_se3'] < SUCCESS_D_SE3} | {row['d_se3']:.4f} | "
                         f"{row['t_err_m']:.4f} | {row['r_err_deg']:.2f} | {row['time_s']:.2f} |")
        lines.append("")
    consistency = report.get("consistency")
    if consistency:
        lines += ["## Consistency (NEES, seeded Monte Carlo)", "",
                  "| estimator | runs | dof | mean NEES | 95 % band | passed |",
                  "|---|---|---|---|---|---|"]
        for name, c in consistency.items():
            lines.append(f"| {name} | {c['runs']} | {c['dof']} | {c['mean_nees']:.2f} | "
                         f"[{c['band'][0]:.2f}, {c['band'][1]:.2f}] | {c['passed']} |")
        lines.append("")
    with atomic_write(out_dir / "report.md", "w") as handle:
        handle.write("\n".join(lines))


def run_demo(out_dir: Path, quick: bool = False) -> dict:
    """Run every demo stage that is available and write ``report.json``; return the report."""
    from estimation.fileio import atomic_write

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    pg = pose_graph_demo(out_dir)
    report["pose_graph"] = {
        "initial_error": pg.initial_error, "final_error": pg.final_error,
        "ate_initial_m": pg.ate_initial_m, "ate_optimized_m": pg.ate_optimized_m,
    }
    print(f"pose graph: error {pg.initial_error:.4g} -> {pg.final_error:.4g}, "
          f"ATE {pg.ate_initial_m:.3f} m -> {pg.ate_optimized_m:.3f} m")
    report["corridor"] = corridor_demo(out_dir, quick)
    report["calibration"] = calibration_demo(out_dir, quick)
    report["consistency"] = consistency_demo(quick)
    with atomic_write(out_dir / "report.json", "w") as handle:
        json.dump(report, handle, indent=2)
    write_report_md(out_dir, report)
    return report
