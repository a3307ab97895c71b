"""Process-wide settings: the deterministic mode and the seed.

Open3D's tensor RGB-D odometry sums its normal equations on several threads in whatever
order they finish, so two runs of the same frames differ in the last bits, and the filter and
the ATE drift apart from there (issue 15: four identical vpslam runs gave ATE 0.023479-0.023616
m). OMP_NUM_THREADS does not reach it (Open3D 0.20 runs its loops on TBB):
``open3d.utility.set_max_threads(1)`` does, and makes the odometry bit-identical from run to
run. OpenCV's RANSAC (the PnP guess) draws from ``cv::theRNG()``: seeded here and run on one
thread. numba's octree insertion gives the same map on any thread count (mapping/octree.py),
one thread is set anyway for identical timings of the threads' shares.
"""
from __future__ import annotations

import os


def set_deterministic(seed: int | None = None) -> None:
    """One thread for Open3D, OpenCV and numba, and seeded RNGs (OpenCV, numpy's global one).

    Call before the work starts; the environment variables only reach libraries that are not
    imported yet, so the CLI calls this before any heavy import.
    """
    for name in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                 "MKL_NUM_THREADS"):
        os.environ[name] = "1"
    import cv2
    import open3d as o3d

    o3d.utility.set_max_threads(1)
    cv2.setNumThreads(1)
    if seed is not None:
        set_seed(seed)


def set_seed(seed: int) -> None:
    """Seed the process-global generators a run may draw from (OpenCV's, numpy's legacy one).

    octofactor's own samplers take explicit seeds from their configs."""
    import cv2
    import numpy as np

    cv2.setRNGSeed(int(seed))
    np.random.seed(int(seed) % 2**32)
