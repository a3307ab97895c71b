"""Smoothing a vpslam pose graph: the EKF's trajectory vs the saved graph optimised (issue 13).

For each sequence it runs ``octofactor vpslam`` (in-process, ``--no-map``), then
``octofactor graph optimize run/graph.g2o X.txt`` with Levenberg-Marquardt and with iSAM2
(the graph holds the VO between factors, one direction factor per direction the filter
accepted, and the first node's prior; docs/vp_ekf.md, "The pose graph"), and scores the three
trajectories with ``octofactor eval``'s metrics (estimation.evaluation, as evo): aligned ATE,
unaligned ATE, mean rotation error relative to the first matched frame and after alignment,
RPE. The VO-only graph (``--direction-factors none``: the same run's graph without its
direction factors, optimised) is the baseline the direction factors must beat.

    .venv/bin/python benchmarks/vpslam_smoothing.py [--corridor-seeds 0 1] [--no-real]
        [--frames N] [--work DIR] [--direction-factors predicted|fixed]

Sequences: the simulated corridor (``octofactor simulate corridor --seed S``, 30 m; the
simulator's VO covariance ``--vo-cov information`` as in the demo) and the real development
sequences ../shared/data/rgbd/{icl_of_kt0,tum_fr1_rpy} (default settings). Prints one table
per sequence and a PASS/FAIL per sequence for "LM and iSAM2 at least as accurate as the EKF"
(aligned ATE within 1 mm and mean rotation error within 0.01 deg, or better).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "rgbd"
REAL = [(DATA / "icl_of_kt0", "481.2,480,319.5,239.5"),
        (DATA / "tum_fr1_rpy", "517.3,516.5,318.6,255.3")]
COLUMNS = ("ate_aligned_rmse_m", "ate_unaligned_rmse_m", "rot_err_mean_deg",
           "aligned_rot_err_mean_deg", "rpe_trans_rmse_m")


def _cli(argv) -> None:
    from pipelines.cli import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = main(argv)
    if code != 0:
        raise SystemExit(f"octofactor {' '.join(argv)} failed (exit {code})")


def _metrics(gt_file: Path, est_file: Path) -> dict:
    from estimation.evaluation import evaluate_trajectory
    from estimation.trajectory_io import read_trajectory

    t_gt, T_gt = read_trajectory(gt_file)
    t_est, T_est = read_trajectory(est_file)
    m = evaluate_trajectory(t_gt, T_gt, t_est, T_est).to_dict()
    return {key: m[key] for key in COLUMNS}


def _without_directions(src: Path, dst: Path) -> None:
    from estimation.io import read_g2o, write_g2o

    graph = read_g2o(src)
    graph.factors = [record for record in graph.factors if record.kind != "direction"]
    write_g2o(dst, graph)


def run_sequence(seq: Path, work: Path, flags: list[str]) -> dict:
    """vpslam, then graph optimize (LM, iSAM2) on its graph; the metrics of each trajectory."""
    out = work / "run"
    start = time.perf_counter()
    _cli(["vpslam", str(seq), "-o", str(out), "--quiet", "--no-map", *flags])
    rows = {"EKF": {"s": time.perf_counter() - start}}
    rows["EKF"].update(_metrics(seq / "groundtruth.txt", out / "trajectory.txt"))
    _without_directions(out / "graph.g2o", work / "vo_only.g2o")
    for name, graph, method in (("LM", out / "graph.g2o", "lm"),
                                ("iSAM2", out / "graph.g2o", "isam2"),
                                ("VO-only LM", work / "vo_only.g2o", "lm")):
        target = work / f"{name.replace(' ', '_')}.txt"
        start = time.perf_counter()
        _cli(["graph", "optimize", str(graph), str(target), "--method", method])
        rows[name] = {"s": time.perf_counter() - start}
        rows[name].update(_metrics(seq / "groundtruth.txt", target))
    from estimation.io import read_g2o

    counts = read_g2o(out / "graph.g2o").factor_counts()
    return {"rows": rows, "factors": counts}


def print_table(title: str, result: dict) -> bool:
    rows = result["rows"]
    print(f"\n{title}  (factors: {result['factors']})")
    print(f"{'trajectory':12s} {'ATE al [cm]':>11s} {'ATE unal [cm]':>13s} {'rot [deg]':>10s} "
          f"{'al rot [deg]':>12s} {'RPE [mm]':>9s} {'time [s]':>9s}")
    for name, r in rows.items():
        print(f"{name:12s} {r['ate_aligned_rmse_m'] * 100:11.3f} "
              f"{r['ate_unaligned_rmse_m'] * 100:13.3f} {r['rot_err_mean_deg']:10.3f} "
              f"{r['aligned_rot_err_mean_deg']:12.3f} {r['rpe_trans_rmse_m'] * 1e3:9.2f} "
              f"{r['s']:9.2f}")
    ekf = rows["EKF"]
    ok = all(rows[name]["ate_aligned_rmse_m"] <= ekf["ate_aligned_rmse_m"] + 1e-3
             and rows[name]["rot_err_mean_deg"] <= ekf["rot_err_mean_deg"] + 1e-2
             for name in ("LM", "iSAM2"))
    print(f"target (LM and iSAM2 at least as accurate as the EKF): {'PASS' if ok else 'FAIL'}")
    return ok


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--corridor-seeds", type=int, nargs="*", default=[0])
    parser.add_argument("--no-real", action="store_true", help="skip the real sequences")
    parser.add_argument("--frames", type=int, default=None, help="first N frames only")
    parser.add_argument("--work", type=Path, default=None, help="keep the runs here")
    parser.add_argument("--direction-factors", default="predicted",
                        choices=("predicted", "fixed"))
    args = parser.parse_args(argv)

    base = args.work or Path(tempfile.mkdtemp(prefix="vpslam_smoothing_"))
    common = ["--direction-factors", args.direction_factors]
    if args.frames:
        common += ["--max-frames", str(args.frames)]
    results = []
    for seed in args.corridor_seeds:
        seq = base / f"corridor_{seed}"
        if not (seq / "rgb.txt").is_file():
            _cli(["simulate", "corridor", str(seq), "--seed", str(seed), "--quiet"])
        result = run_sequence(seq, base / f"corridor_{seed}_runs",
                              ["--vo-cov", "information", *common])
        results.append(print_table(f"corridor seed {seed}", result))
    if not args.no_real:
        for seq, intrinsics in REAL:
            if not seq.is_dir():
                print(f"\n{seq}: missing, skipped")
                continue
            result = run_sequence(seq, base / seq.name, ["--intrinsics", intrinsics, *common])
            results.append(print_table(seq.name, result))
    print(f"\nwork folder: {base}")
    return 0 if all(results) else 1


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    sys.exit(main())
