"""Fit and check the RGB-D odometry's covariance model against ground truth on real sequences.

For each sequence (TUM layout; default: the development set in ../shared/data/rgbd) runs
``perception.odometry.rgbd_odometry`` on frame pairs ``(k - gap, k)`` for the gaps given
(1: frame to frame; larger gaps: what odometry against a keyframe measures), takes the error
``xi = Log(T_vo^-1 T_gt)`` (right perturbation, [rotation, translation]) and prints, per
covariance model, the mean NEES (6 expected), the share inside the 95 % chi-square bound and
the mean negative log-likelihood; ``--fit`` refits :data:`perception.odometry.MOTION_COV_MODEL`
(sigma_rot = a + b |omega|, sigma_trans = c + d |t|) by maximum likelihood.

    .venv/bin/python benchmarks/vo_covariance.py [--gaps 1 2 4] [--fit] [--seq DIR FX,FY,CX,CY]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "rgbd"
DEV = [(DATA / "icl_of_kt0", (481.2, 480.0, 319.5, 239.5)),
       (DATA / "tum_fr1_rpy", (517.3, 516.5, 318.6, 255.3))]
MODELS = ("motion", "coupled", "information")


def collect(seq, intr, gaps):
    """Rows of (error xi (6,), T_vo, information) for every successful pair with ground truth."""
    import gtsam

    from perception.odometry import OdometryConfig, rgbd_odometry
    from perception.rgbd import TumRgbdSequence

    sequence = TumRgbdSequence(seq, intrinsics=intr)
    frames = [sequence[i] for i in range(len(sequence))]
    rows = []
    for gap in gaps:
        for k in range(gap, len(frames)):
            a, b = frames[k - gap], frames[k]
            if a.T_world_camera_gt is None or b.T_world_camera_gt is None:
                continue
            vo = rgbd_odometry(a, b, intr, config=OdometryConfig())
            if not vo.success:
                continue
            T_gt = a.T_world_camera_gt.between(b.T_world_camera_gt)
            xi = gtsam.Pose3.Logmap(vo.T_prev_curr.between(T_gt))
            rows.append((gap, xi, vo.T_prev_curr, vo.information))
    return rows


def covariances(rows, model, params=None):
    from perception.odometry import OdometryConfig, information_to_covariance, motion_covariance

    if model == "motion" and params is not None:
        return [motion_covariance(T, params) for _, _, T, _ in rows]
    config = replace(OdometryConfig(), cov_model=model)
    return [information_to_covariance(info, T, config) for _, _, T, info in rows]


def scores(rows, covs):
    from scipy.stats import chi2

    nees, nll = [], []
    for (_, xi, _, _), C in zip(rows, covs):
        e = float(xi @ np.linalg.solve(C, xi))
        nees.append(e)
        nll.append(0.5 * (e + np.linalg.slogdet(C)[1]))
    nees = np.array(nees)
    return float(np.mean(nees)), float(np.mean(nees < chi2.ppf(0.95, 6))), float(np.mean(nll))


def fit_motion(rows):
    from scipy.optimize import minimize

    def nll(log_params):
        return scores(rows, covariances(rows, "motion", tuple(np.exp(log_params))))[2]

    from perception.odometry import MOTION_COV_MODEL

    res = minimize(nll, np.log(MOTION_COV_MODEL), method="Nelder-Mead",
                   options=dict(maxiter=400, xatol=1e-3, fatol=1e-4))
    return tuple(float(v) for v in np.exp(res.x))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seq", nargs=2, action="append", metavar=("DIR", "FX,FY,CX,CY"))
    parser.add_argument("--gaps", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--fit", action="store_true", help="refit MOTION_COV_MODEL")
    args = parser.parse_args(argv)

    from perception.rgbd import CameraIntrinsics, listed_image_size

    sequences = ([(Path(d), tuple(float(v) for v in k.split(","))) for d, k in args.seq]
                 if args.seq else DEV)
    everything = []
    for seq, (fx, fy, cx, cy) in sequences:
        width, height = listed_image_size(seq)
        intr = CameraIntrinsics(fx, fy, cx, cy, width, height, 5000.0)
        rows = collect(seq, intr, args.gaps)
        everything += rows
        print(f"\n{seq.name}: {len(rows)} pairs (gaps {args.gaps})")
        print(f"{'model':12s} {'gap':>4s} {'mean NEES':>10s} {'in 95 %':>8s} {'mean NLL':>9s}")
        for model in MODELS:
            for gap in args.gaps:
                sub = [r for r in rows if r[0] == gap]
                m, inside, nll = scores(sub, covariances(sub, model))
                print(f"{model:12s} {gap:4d} {m:10.2f} {inside:8.2f} {nll:9.2f}")
    if args.fit:
        params = fit_motion(everything)
        print("\nMOTION_COV_MODEL fitted on all pairs: (" + ", ".join(f"{v:.3g}" for v in params)
              + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
