"""`octofactor eval GT EST`: ATE, RPE and rotation errors of a trajectory, as evo computes them."""
from __future__ import annotations


def register(add_command) -> None:
    parser = add_command("eval", "evaluate an estimated trajectory against ground truth "
                         "(TUM or KITTI files; ATE/RPE as evo_ape/evo_rpe)")
    parser.add_argument("gt", metavar="GT", help="ground-truth trajectory (TUM or KITTI)")
    parser.add_argument("est", metavar="EST", help="estimated trajectory (TUM or KITTI)")
    parser.add_argument("--format", choices=("auto", "tum", "kitti"), default="auto",
                        help="file format of both files; auto: 12 numbers a line is KITTI, "
                        "8 is TUM (default: auto)")
    parser.add_argument("--max-diff", type=float, default=0.02, metavar="SECONDS",
                        help="largest time difference of an associated pair (default: 0.02)")
    parser.add_argument("--delta", type=int, default=1, metavar="FRAMES",
                        help="RPE frame distance, in matched poses (default: 1)")
    parser.add_argument("-o", "--output", metavar="FILE.json",
                        help="write all metrics as JSON")
    parser.set_defaults(func=run)


def format_table(metrics) -> str:
    """The human-readable summary printed by ``octofactor eval``."""
    m = metrics
    return "\n".join([
        f"matched:           {m.matched} pairs (ground truth {m.gt_poses} poses, estimate "
        f"{m.est_poses}; first matched estimate #{m.first_matched_est_index})",
        f"ATE aligned:       rmse {m.ate_aligned_rmse_m:.6f} m  mean {m.ate_aligned_mean_m:.6f}"
        f"  median {m.ate_aligned_median_m:.6f}  max {m.ate_aligned_max_m:.6f}  (SE(3) Umeyama)",
        f"ATE unaligned:     rmse {m.ate_unaligned_rmse_m:.6f} m",
        f"ATE origin-align:  rmse {m.ate_origin_aligned_rmse_m:.6f} m",
        f"RPE (delta {m.rpe_delta_frames}):     trans rmse {m.rpe_trans_rmse_m:.6f} m  "
        f"rot rmse {m.rpe_rot_rmse_deg:.4f} deg  ({m.rpe_pairs} pairs)",
        f"rotation error:    mean {m.rot_err_mean_deg:.4f} deg  max {m.rot_err_max_deg:.4f} deg"
        f"  (relative to the first matched frame); aligned mean "
        f"{m.aligned_rot_err_mean_deg:.4f} deg",
    ])


def run(args) -> int:
    import json
    import os

    from estimation.errors import OctofactorError
    from estimation.evaluation import evaluate_trajectory
    from estimation.fileio import atomic_write
    from estimation.trajectory_io import read_trajectory
    from pipelines.validate import integer, number

    number("--max-diff", args.max_diff, 0.0, 1e6, low_open=True)
    integer("--delta", args.delta, 1, 10**9)

    for path in (args.gt, args.est):
        if not os.path.isfile(path):
            raise OctofactorError(f"{path}: no such file")
    t_gt, T_gt = read_trajectory(args.gt, args.format)
    t_est, T_est = read_trajectory(args.est, args.format)
    if (t_gt is None) != (t_est is None):
        raise OctofactorError(f"{args.gt} and {args.est}: one file is TUM (timestamps), the "
                              "other KITTI (none); give both in the same format")
    metrics = evaluate_trajectory(t_gt, T_gt, t_est, T_est, max_diff=args.max_diff,
                                  rpe_delta=args.delta)
    if not args.quiet:
        print(format_table(metrics))
    if args.output:
        with atomic_write(args.output, "w") as handle:
            json.dump(metrics.to_dict(), handle, indent=2)
            handle.write("\n")
    return 0
