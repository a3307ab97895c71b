"""The structure's Manhattan frame from depth surface normals (after OPVO, Kim et al. 2017).

Line vanishing points fail where a Manhattan-frame tracker must work: blurred or distorted
images, clutter, textureless walls. Planar surfaces of the structure (walls, floor, ceiling,
desks) are dense in a depth image, and their normals cluster around the three Manhattan
axes. This module estimates those axes in the camera frame:

1. normals from the depth image: back-projection on a grid of every ``stride``-th pixel,
   central differences along the image axes, cross product; pixels at depth
   discontinuities (neighbour depth ratio beyond ``max_depth_jump``) are dropped;
2. without a guess, a RANSAC search over frames built from pairs of nearly orthogonal
   normals picks the frame that the most normals support (within ``inlier_deg``);
3. mean shift on the sphere, as OPVO does: per axis, the normals within ``kernel_deg`` of
   it (sign-free) are mapped to the axis' tangent plane, their (Gaussian-weighted) mean
   moves the axis, a few rounds; then the nearest rotation to the three axes;
4. per axis, a covariance of the direction: the tangent-plane scatter of its normals over
   their effective number, with ``correlation_px`` neighbouring normals counted as one
   (neighbouring normals share depth noise and the sensor's systematic errors).

An axis is reported only when at least ``min_fraction`` of the valid normals and
``min_normals`` normals support it. Directions are unit vectors in the camera frame
(x right, y down, z forward), sign-free like vanishing points.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from estimation.vp_ekf import tangent_basis
from perception.errors import PerceptionError


@dataclass(frozen=True)
class NormalsConfig:
    """Parameters of :func:`manhattan_from_depth`.

    Attributes
    ----------
    stride : int
        Use every n-th pixel row and column (4 at 640x480: 19k normals).
    smooth : int
        Box-filter half-width (pixels of the strided grid) for the depth before
        differencing (0: none); it averages out the depth quantisation.
    depth_min, depth_max : float
        Depth range used (m).
    max_depth_jump : float
        Relative depth change between grid neighbours above which a normal is dropped.
    inlier_deg : float
        A normal within this angle of an axis supports it (RANSAC score and the counts).
    kernel_deg : float
        Mean-shift window around each axis.
    iterations : int
        Mean-shift rounds.
    n_hypotheses : int
        RANSAC frames tried without a guess.
    min_fraction, min_normals : float, int
        Least support of a reported axis (fraction of valid normals, count).
    correlation_px : float
        Grid spacing (pixels of the full image) within which normals are counted as one
        independent observation in the covariance.
    cov_floor_deg : float
        Standard deviation (degrees) added to every axis direction: the structure is not
        exactly Manhattan and the depth has systematic errors.
    seed : int
        RANSAC sampler seed (results are deterministic).
    """

    stride: int = 4
    smooth: int = 1
    depth_min: float = 0.3
    depth_max: float = 6.0
    max_depth_jump: float = 0.05
    inlier_deg: float = 8.0
    kernel_deg: float = 15.0
    iterations: int = 4
    n_hypotheses: int = 200
    min_fraction: float = 0.05
    min_normals: int = 100
    correlation_px: float = 100.0
    cov_floor_deg: float = 1.5
    seed: int = 0


@dataclass(frozen=True)
class NormalsManhattan:
    """The Manhattan axes seen in one depth image.

    Attributes
    ----------
    R_camera_manhattan : (3, 3) or None
        The fitted frame (columns: axes in the camera); None when nothing was found.
    directions : (k, 3)
        The supported axes (unit, camera frame), most supported first.
    covs : (k, 3, 3)
        Their direction covariances (rad^2, in the plane perpendicular to each).
    support : (k,) int
        Normals supporting each axis.
    n_normals : int
        Valid normals in the image.
    ms : float
        Wall time of the call.
    """

    R_camera_manhattan: np.ndarray | None
    directions: np.ndarray
    covs: np.ndarray
    support: np.ndarray
    n_normals: int
    ms: float


def depth_normals(depth_m: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  config: NormalsConfig = NormalsConfig()) -> np.ndarray:
    """Unit surface normals (N, 3) in the camera frame, facing the camera."""
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise PerceptionError(f"depth must be a 2-D image, got shape {depth.shape}")
    s = max(1, int(config.stride))
    z = depth[::s, ::s].astype(np.float64)
    valid = np.isfinite(z) & (z >= config.depth_min) & (z <= config.depth_max)
    z = np.where(valid, z, 0.0)
    if config.smooth > 0:
        import cv2

        k = 2 * int(config.smooth) + 1
        weight = cv2.blur(valid.astype(np.float64), (k, k))
        total = cv2.blur(z, (k, k))
        z_s = np.where(weight > 0.5, total / np.maximum(weight, 1e-9), 0.0)
        valid = valid & (weight > 0.99)  # every pixel of the window valid
        z = np.where(valid, z_s, 0.0)
    rows, cols = np.mgrid[0:z.shape[0], 0:z.shape[1]]
    u = cols * s
    v = rows * s
    P = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    zc = z[1:-1, 1:-1]
    ok = (valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1]
          & valid[:-2, 1:-1])
    jump = config.max_depth_jump * np.maximum(zc, 1e-9)
    ok &= (np.abs(z[1:-1, 2:] - z[1:-1, :-2]) < 2 * jump) & (
        np.abs(z[2:, 1:-1] - z[:-2, 1:-1]) < 2 * jump)
    n = np.cross(du[ok], dv[ok])
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 1e-12
    n = n[keep] / norm[keep, None]
    # face the camera: n . p < 0
    p = P[1:-1, 1:-1][ok][keep]
    flip = np.einsum("ij,ij->i", n, p) > 0
    n[flip] *= -1.0
    return n


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    import gtsam

    return gtsam.Rot3.ClosestTo(np.asarray(M, dtype=float)).matrix()


def _ransac_frame(normals: np.ndarray, config: NormalsConfig) -> np.ndarray | None:
    rng = np.random.default_rng(config.seed)
    n = len(normals)
    cos_in = np.cos(np.deg2rad(config.inlier_deg))
    sample = normals if n <= 4000 else normals[rng.choice(n, 4000, replace=False)]
    best, best_score = None, -1
    tries = 0
    for _ in range(config.n_hypotheses * 5):
        if tries >= config.n_hypotheses:
            break
        i, j = rng.integers(0, n, 2)
        a, b = normals[i], normals[j]
        if abs(a @ b) > np.sin(np.deg2rad(10.0)):  # not within 10 deg of orthogonal
            continue
        tries += 1
        b = b - (a @ b) * a
        b /= np.linalg.norm(b)
        R = np.column_stack([a, b, np.cross(a, b)])
        score = int(np.count_nonzero(np.abs(sample @ R).max(axis=1) >= cos_in))
        if score > best_score:
            best, best_score = R, score
    return best


def manhattan_from_depth(depth_m: np.ndarray, K: np.ndarray,
                         R_camera_manhattan_guess: np.ndarray | None = None,
                         config: NormalsConfig = NormalsConfig(),
                         normals: np.ndarray | None = None) -> NormalsManhattan:
    """Return the Manhattan axes supported by the depth image's surface normals.

    ``R_camera_manhattan_guess`` (e.g. the filter's prediction) starts the mean shift, as in
    OPVO's tracking; without it a RANSAC search finds the frame. ``normals``: the image's
    :func:`depth_normals` (same ``config``) when they were computed already, e.g. in another
    thread before the guess was known; ``depth_m`` is then not read again.
    """
    start = time.perf_counter()
    K = np.asarray(K, dtype=float)
    if normals is None:
        normals = depth_normals(depth_m, K[0, 0], K[1, 1], K[0, 2], K[1, 2], config)
    empty = NormalsManhattan(None, np.zeros((0, 3)), np.zeros((0, 3, 3)),
                             np.zeros(0, dtype=int), len(normals),
                             (time.perf_counter() - start) * 1e3)
    if len(normals) < config.min_normals:
        return empty
    R = (_ransac_frame(normals, config) if R_camera_manhattan_guess is None
         else _nearest_rotation(np.asarray(R_camera_manhattan_guess, dtype=float)))
    if R is None:
        return empty
    cos_k = np.cos(np.deg2rad(config.kernel_deg))
    sigma_k = np.deg2rad(config.kernel_deg) / 2
    for _ in range(config.iterations):
        axes = R.copy()
        for j in range(3):
            c = normals @ R[:, j]
            sel = np.abs(c) >= cos_k
            if np.count_nonzero(sel) < 3:
                continue
            m = normals[sel] * np.sign(c[sel])[:, None]
            # tangent-plane (log map) coordinates of the normals around axis j
            B = tangent_basis(R[:, j])
            cosang = np.clip(m @ R[:, j], -1.0, 1.0)
            ang = np.arccos(cosang)
            tang = m @ B
            norm = np.linalg.norm(tang, axis=1)
            logs = tang * (ang / np.maximum(norm, 1e-12))[:, None]
            w = np.exp(-0.5 * (ang / sigma_k) ** 2)
            shift = (w[:, None] * logs).sum(axis=0) / w.sum()
            step = B @ shift
            angle = np.linalg.norm(step)
            axis = R[:, j] if angle < 1e-12 else (
                np.cos(angle) * R[:, j] + np.sin(angle) * step / angle)
            axes[:, j] = axis
        R = _nearest_rotation(axes)
    cos_in = np.cos(np.deg2rad(config.inlier_deg))
    n_total = len(normals)
    eff_per_normal = (config.stride / config.correlation_px) ** 2
    floor = np.deg2rad(config.cov_floor_deg) ** 2
    found = []
    for j in range(3):
        c = normals @ R[:, j]
        sel = np.abs(c) >= cos_in
        count = int(np.count_nonzero(sel))
        if count < config.min_normals or count < config.min_fraction * n_total:
            continue
        m = normals[sel] * np.sign(c[sel])[:, None]
        B = tangent_basis(R[:, j])
        tang = m @ B
        scatter = np.cov(tang.T) if count > 2 else np.eye(2)
        n_eff = max(1.0, count * eff_per_normal)
        cov2 = scatter / n_eff + floor * np.eye(2)
        found.append((count, R[:, j].copy(), B @ cov2 @ B.T))
    found.sort(key=lambda item: -item[0])
    if not found:
        return NormalsManhattan(R, np.zeros((0, 3)), np.zeros((0, 3, 3)),
                                np.zeros(0, dtype=int), n_total,
                                (time.perf_counter() - start) * 1e3)
    return NormalsManhattan(R, np.array([f[1] for f in found]), np.array([f[2] for f in found]),
                            np.array([f[0] for f in found]), n_total,
                            (time.perf_counter() - start) * 1e3)

