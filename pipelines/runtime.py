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


def keep_freed_memory(mmap_threshold: int = 32 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Let glibc's malloc reuse freed blocks instead of handing them back to the system.

    By default a block of 128 kB or more is its own mmap, unmapped at free, and the heap's
    free top is trimmed above 128 kB: a command that allocates and frees the same megabyte
    arrays scan after scan (``octofactor map``: the float32 points, their transform and their
    direction sort, per scan and thread) takes fresh zeroed pages each time. Measured on the
    50 x 100k-point corridor at 0.1 m: 55k -> 12k page faults, 0.09 -> 0.03 s system time,
    the map unchanged. Returns False where there is no glibc ``mallopt`` (nothing changes).
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    return bool(mallopt(m_mmap_threshold, int(mmap_threshold))
                and mallopt(m_trim_threshold, int(trim_threshold)))
