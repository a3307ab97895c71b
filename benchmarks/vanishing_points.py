"""Vanishing-point accuracy and speed on the York Urban training half (../shared/data/yud_train).

Runs the seed detector, the Manhattan detector and, when importable, the peer lu-vp-detect on
every image, single-threaded, and prints forward-VP / all-three-directions angle errors
(median, share under 2 and 5 degrees; the measure defined in the data README), milliseconds
per image (median of repeats) and the ratios against the peer measured in the same run.

Usage::

    .venv/bin/python benchmarks/vanishing_points.py [--data DIR] [--repeats 3] [--no-peer]

Cite Denis, Elder, Estrada (ECCV 2008) for the data.
"""
from __future__ import annotations

import os

# single-threaded measurement: numpy's BLAS threads must be limited before numpy is imported
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 (after the thread limits)
import csv  # noqa: E402 (after the thread limits)
import sys  # noqa: E402 (after the thread limits)
import time  # noqa: E402 (after the thread limits)
from dataclasses import dataclass  # noqa: E402 (after the thread limits)
from pathlib import Path  # noqa: E402 (after the thread limits)

import numpy as np  # noqa: E402 (after the thread limits)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# README of yud_train: K in the x-right, y-down, z-forward convention (0-based pixels)
YUD_K = np.array([[674.917975, 0.0, 306.551305], [0.0, 674.917975, 250.454245], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class GroundTruth:
    """Ground truth of one YUD image: three unit directions (rows) and the image path."""

    name: str
    image: Path
    directions: np.ndarray  # (3, 3) rows = directions, x right, y down, z forward

    @property
    def forward(self) -> np.ndarray:
        return self.directions[int(np.argmax(np.abs(self.directions[:, 2])))]


def read_ground_truth(data_dir: Path) -> list[GroundTruth]:
    """Return the rows of ``ground_truth.csv`` in ``data_dir`` (sorted by image name)."""
    rows = []
    with open(data_dir / "ground_truth.csv", newline="") as handle:
        for row in csv.DictReader(handle):
            name = row["image"]
            dirs = np.array([[float(row[f"d{a}{k}"]) for a in "xyz"] for k in range(3)])
            rows.append(GroundTruth(name, data_dir / name / f"{name}.jpg", dirs))
    return sorted(rows, key=lambda r: r.name)


def errors_deg(detected: list[np.ndarray], truth: GroundTruth) -> tuple[float, np.ndarray]:
    """Return (forward error, (3,) per-GT-direction errors) in degrees, sign ignored.

    Each ground-truth direction is compared with the closest detected direction; a missing
    detection counts as 90 degrees."""
    from perception.vanishing_points import angle_between_directions

    if not detected:
        return 90.0, np.full(3, 90.0)
    det = np.asarray(detected)
    err = angle_between_directions(truth.directions[:, None, :], det[None, :, :]).min(axis=1)
    forward_k = int(np.argmax(np.abs(truth.directions[:, 2])))
    return float(err[forward_k]), err


def summary(values: np.ndarray) -> str:
    values = np.asarray(values)
    p75, p90 = np.percentile(values, [75, 90])
    return (f"median {np.median(values):6.2f} deg  <2: {100 * np.mean(values < 2):5.1f} %  "
            f"<5: {100 * np.mean(values < 5):5.1f} %  (p75 {p75:.2f}, p90 {p90:.2f}, "
            f"max {values.max():.1f})")


def run_detector(name, detect, truths, repeats):
    """Return (forward errors, all errors (N,3), wall ms per image (median of repeats), CPU ms
    per image (process time, median of repeats: less sensitive to other load), results)."""
    import cv2

    forward, every, ms, cpu_ms, results = [], [], [], [], []
    for truth in truths:
        image = cv2.imread(str(truth.image), cv2.IMREAD_GRAYSCALE)
        times, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            dirs, extra = detect(image, truth)
            times.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        f, e = errors_deg(dirs, truth)
        forward.append(f)
        every.append(e)
        ms.append(float(np.median(times)))
        cpu_ms.append(float(np.median(cpu)))
        results.append(extra)
    return np.array(forward), np.array(every), np.array(ms), np.array(cpu_ms), results


def nees_forward(results, truths) -> np.ndarray:
    """Return the 2-dof NEES of the Manhattan forward VP pixel against the ground truth."""
    values = []
    for res, truth in zip(results, truths, strict=True):
        if res is None or not res.vps:
            continue
        gt = truth.forward
        # the detected VP matching the ground-truth forward direction
        from perception.vanishing_points import angle_between_directions

        vp = min(res.vps, key=lambda v: float(angle_between_directions(v.direction, gt)))
        if vp.uv is None:
            continue
        p = YUD_K @ (gt if gt[2] >= 0 else -gt)
        err = vp.uv - p[:2] / p[2]
        values.append(float(err @ np.linalg.solve(vp.cov, err)))
    return np.array(values)


def _patch_peer_for_opencv5() -> None:
    """lu-vp-detect 1.0.4 indexes LSD output as (N, 1, 4); OpenCV 5 returns (N, 4)."""
    import cv2
    import lu_vp_detect.vp_detection as peer_module

    class _Detector:
        def __init__(self, *args):
            self._lsd = cv2.createLineSegmentDetector(*args)

        def detect(self, image):
            found = self._lsd.detect(image)
            return (found[0].reshape(-1, 1, 4),) + tuple(found[1:])

    class _Cv2:
        createLineSegmentDetector = _Detector  # noqa: N815 (OpenCV's name)

        def __getattr__(self, name):
            return getattr(cv2, name)

    peer_module.cv2 = _Cv2()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "yud_train")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-peer", action="store_true")
    args = parser.parse_args(argv)

    import cv2

    from perception.vanishing_points import detect_manhattan, detect_seed

    cv2.setNumThreads(1)
    truths = read_ground_truth(args.data)

    def seed(image, truth):
        res = detect_seed(image, K=YUD_K)
        return [vp.direction for vp in res.vps], res

    def manhattan(image, truth):
        res = detect_manhattan(image, YUD_K)
        return [vp.direction for vp in res.vps], res

    detectors = [("seed (Canny+Hough+LSQ)", seed), ("manhattan", manhattan)]
    if not args.no_peer:
        try:
            from lu_vp_detect import VPDetection  # optional peer, not a project dependency

            _patch_peer_for_opencv5()

            def peer(image, truth):
                det = VPDetection(length_thresh=30, principal_point=(YUD_K[0, 2], YUD_K[1, 2]),
                                  focal_length=YUD_K[0, 0], seed=0)
                det.find_vps(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
                # directions from its pixel VPs, so no assumption on its 3D axis convention
                pixels = np.column_stack([det.vps_2D, np.ones(len(det.vps_2D))])
                return list(pixels @ np.linalg.inv(YUD_K).T), None

            detectors.append(("lu-vp-detect (peer)", peer))
        except ImportError:
            print("lu-vp-detect not importable: peer skipped (pip install --no-deps "
                  "lu-vp-detect into the venv to compare)", file=sys.stderr)

    print(f"{len(truths)} images from {args.data}, single thread, {args.repeats} repeats")
    rows = {}
    for name, detect in detectors:
        forward, every, ms, cpu_ms, results = run_detector(name, detect, truths, args.repeats)
        rows[name] = (forward, every, ms, cpu_ms)
        print(f"\n{name}")
        print(f"  forward VP : {summary(forward)}")
        print(f"  all three  : {summary(every.ravel())}")
        print(f"  ms/image   : median {np.median(ms):6.1f}  "
              f"(min {ms.min():.1f}, max {ms.max():.1f});  CPU ms median "
              f"{np.median(cpu_ms):.1f}")
        if name == "manhattan":
            from perception.vanishing_points import angle_between_directions

            picked = np.array([
                float(angle_between_directions(res.forward().direction, truth.forward))
                if res.forward() is not None else 90.0 for res, truth in zip(results, truths,
                                                                             strict=True)])
            print(f"  forward() : {summary(picked)}  (the detector's own forward pick)")
            nees = nees_forward(results, truths)
            print(f"  forward NEES (2 dof, GT label noise included): median {np.median(nees):.2f} "
                  f"mean {np.mean(nees):.2f}  share < chi2_2(0.95)=5.99: "
                  f"{100 * np.mean(nees < 5.991):.0f} %  (n={len(nees)})")
    peer_name = "lu-vp-detect (peer)"
    if peer_name in rows:
        pf, pa, pm, pc = rows[peer_name]
        mf, ma, mm, mc = rows["manhattan"]
        print("\nratios manhattan / peer (same run):")
        print(f"  forward median error {np.median(mf) / np.median(pf):.2f}, "
              f"all-three median error {np.median(ma) / np.median(pa):.2f}, "
              f"median ms {np.median(mm) / np.median(pm):.2f} (CPU ms "
              f"{np.median(mc) / np.median(pc):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
