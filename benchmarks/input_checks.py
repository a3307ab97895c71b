"""What the bad-input checks of the readers cost (issue 16).

Times, per call, medians over repeats:
* a 640x480 colour PNG and a 16-bit depth PNG read with ``perception.rgbd.read_rgb`` /
  ``read_depth`` (regular-file check, header size check, library output captured) against a
  bare ``cv2.imdecode`` of the same bytes;
* a semantic PLY of N points read with ``SemanticCloud.read_ply`` (``estimation.ply.check_ply``
  first) against ``check_ply`` alone and a bare ``open3d.t.io.read_point_cloud``.

Usage: ``.venv/bin/python benchmarks/input_checks.py [--repeats 30] [--points 70000]``
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def median_ms(call, repeats: int) -> float:
    call()  # warm-up (imports, caches)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--points", type=int, default=70000)
    args = parser.parse_args()

    import cv2
    import open3d as o3d

    from estimation.ply import check_ply
    from perception.rgbd import CameraIntrinsics, read_depth, read_rgb
    from perception.semantic_cloud import SemanticCloud

    rng = np.random.default_rng(0)
    intr = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rgb = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
        depth = rng.integers(4000, 20000, (480, 640), dtype=np.uint16)
        cv2.imwrite(str(folder / "rgb.png"), rgb)
        cv2.imwrite(str(folder / "depth.png"), depth)
        for name, reader in (("rgb.png", lambda p: read_rgb(p, intr)),
                             ("depth.png", lambda p: read_depth(p, intr))):
            path = folder / name
            data = path.read_bytes()
            checked = median_ms(lambda p=path, r=reader: r(p), args.repeats)
            bare = median_ms(lambda d=data: cv2.imdecode(np.frombuffer(d, np.uint8),
                                                         cv2.IMREAD_UNCHANGED), args.repeats)
            rows.append((f"{name} 640x480: read_{name.split('.')[0]}", checked, bare))

        points = rng.normal(size=(args.points, 3))
        cloud = SemanticCloud.from_labels(points, rng.integers(0, 8, args.points), 8)
        ply = folder / "cloud.ply"
        cloud.write_ply(ply)
        checked = median_ms(lambda: SemanticCloud.read_ply(ply), args.repeats)
        bare = median_ms(lambda: o3d.t.io.read_point_cloud(str(ply)), args.repeats)
        header = median_ms(lambda: check_ply(ply), args.repeats)
        rows.append((f"PLY {args.points} points, 8 classes: read_ply", checked, bare))
        rows.append((f"PLY {args.points} points: check_ply alone", header, bare))

    print(f"{'what':48s} {'checked ms':>11s} {'bare ms':>9s}")
    for what, checked, bare in rows:
        print(f"{what:48s} {checked:11.3f} {bare:9.3f}")


if __name__ == "__main__":
    main()
