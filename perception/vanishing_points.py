"""Vanishing points: the seed paper's detector and a Manhattan-frame detector with covariances.

Two detectors share one result type:

* :func:`detect_seed` -- the seed paper's method (Canny, probabilistic Hough, removal of lines
  parallel to the image u / v axes, least-squares intersection with the Moore-Penrose
  pseudo-inverse; eq. (1)-(4)). One VP, fast, fragile on cluttered real images.
* :func:`detect_manhattan` -- up to three Manhattan VPs from LSD segments and the camera
  intrinsics: RANSAC over minimal 3-segment Manhattan frames (two segments -> VP1, a third ->
  VP2 orthogonal to VP1, VP3 = VP1 x VP2) scored by the length-weighted angular consistency of
  all segments; a weighted Gauss-Newton fit of the rotation to its inlier segments with a
  first-order noise model of the segment endpoints (re-assigning inliers between rounds); a
  final MAP fit of the three directions with a soft orthogonality prior. The 2x2 pixel
  covariance of each VP is the propagated inverse information of that fit, with the noise
  level estimated from the residuals (so it grows when the segments disagree) and a variance
  inflation calibrated on real images (``ManhattanConfig.cov_scale``).

Conventions: pixels are 0-based (x right, y down); directions are unit vectors in the camera
frame (x right, y down, z forward) with ``z >= 0``; ``K`` is the 3x3 camera matrix.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from perception.errors import PerceptionError
from perception.lines import hough_segments, lsd_segments, to_gray_u8

__all__ = [
    "VanishingPoint", "VPResult", "SeedConfig", "ManhattanConfig",
    "detect_seed", "detect_manhattan", "manhattan_from_segments", "angle_between_directions",
]


@dataclass(frozen=True)
class VanishingPoint:
    """One vanishing point.

    Attributes
    ----------
    uv : (2,) float array or None
        Pixel position (0-based), None when the VP is at infinity (direction parallel to the
        image plane).
    direction : (3,) float array
        Unit direction in the camera frame (x right, y down, z forward), ``direction[2] >= 0``.
    cov : (2, 2) float array
        Pixel covariance of ``uv`` (the EKF's measurement noise Q); all ``inf`` when ``uv`` is
        None.
    inliers : (n,) int array
        Indices into :attr:`VPResult.segments` of the segments that support this VP.
    score : float
        Support: the summed length in pixels of the inlier segments.
    """

    uv: np.ndarray | None
    direction: np.ndarray
    cov: np.ndarray
    inliers: np.ndarray
    score: float


@dataclass(frozen=True)
class VPResult:
    """Vanishing points found in one image.

    Attributes
    ----------
    vps : list of VanishingPoint
        Best (largest score) first; empty when nothing was found.
    segments : (M, 4) float array
        The line segments ``x1, y1, x2, y2`` the detector used (pixels).
    ms : float
        Wall-clock milliseconds spent in the detector.
    """

    vps: list[VanishingPoint]
    segments: np.ndarray
    ms: float

    def forward(self, min_abs_dz: float = 0.5) -> VanishingPoint | None:
        """Return the VP closest to the optical axis (largest |dz|), None if there is none
        with ``|dz| >= min_abs_dz``.

        In a full Manhattan frame the largest |dz| is at least 1/sqrt(3) = 0.58, so the
        default only rejects lone VPs far from the viewing direction (e.g. the vertical VP of
        a camera facing the end wall of a corridor), which must not be used as "forward"."""
        if not self.vps:
            return None
        best = max(self.vps, key=lambda vp: abs(float(vp.direction[2])))
        return best if abs(float(best.direction[2])) >= min_abs_dz else None


@dataclass(frozen=True)
class SeedConfig:
    """Parameters of the seed paper's detector (Canny, HoughLinesP, axis removal, eq. (1)-(4)).

    Attributes
    ----------
    canny_low, canny_high : float
        Canny hysteresis thresholds.
    hough_rho, hough_theta_deg, hough_threshold, min_line_length, max_line_gap :
        ``cv2.HoughLinesP`` parameters (pixels, degrees, votes, pixels, pixels).
    axis_tolerance_deg : float
        Lines within this angle of the image u or v axis are dropped (doors, posters: lines
        that do not converge to the corridor's VP).
    min_lines : int
        Fewer remaining lines than this -> no VP.
    """

    canny_low: float = 50.0
    canny_high: float = 150.0
    hough_rho: float = 1.0
    hough_theta_deg: float = 1.0
    hough_threshold: int = 50
    min_line_length: float = 30.0
    max_line_gap: float = 5.0
    axis_tolerance_deg: float = 10.0
    min_lines: int = 2


@dataclass(frozen=True)
class ManhattanConfig:
    """Parameters of :func:`detect_manhattan`.

    Attributes
    ----------
    lsd_scale : float
        LSD's internal image scale (0.5: about 3x faster than OpenCV's default 0.8).
    min_length : float
        Segments shorter than this (pixels) are ignored.
    max_segments : int
        Keep at most this many (longest) segments: bounds the scoring cost.
    n_hypotheses : int
        RANSAC hypotheses (minimal 3-segment Manhattan frames).
    seed : int
        Seed of the hypothesis sampler (results are deterministic).
    score_angle_deg : float
        Angle (segment vs. line from its midpoint to the VP) at which a segment stops
        contributing to a hypothesis score (weight 1 - sin^2 / sin^2(score_angle_deg)).
    inlier_angle_deg : float
        Inlier threshold of the same angle for the refinement.
    refine_iterations : int
        Re-assignment + Gauss-Newton rounds of the refinement.
    vp_gap_px : float
        A segment supports a VP only if the VP lies beyond its ends by at least this many
        pixels (the image of a finite 3D segment never reaches its VP; segments meeting at a
        junction would otherwise vote for the junction).
    min_inliers : int
        A VP needs this many inlier segments, on at least two distinct image lines, to count
        as observed. With two observed VPs the third is implied by the orthogonality prior and
        reported too (no inliers, score 0, its own larger covariance).
    orthogonality_deg : float
        Standard deviation (degrees) of a soft prior on the deviation of each VP pair from
        90 degrees in the final MAP fit: real scenes and calibrations are not exactly
        orthogonal (the yud ground truth deviates by 0.6 degrees median, and a few-degree
        calibration error bends the measured angles further). 0 = exact orthogonality (the
        three VPs are the columns of one fitted rotation). With two observed VPs the third
        is fixed by this prior. On yud_train the accuracy is flat between 3 and 10 degrees.
    cov_scale : float
        Variance inflation of the least-squares noise for errors the endpoint-noise model
        cannot see (segments cut from one edge are correlated, lens distortion, imperfect
        Manhattan structure). 20 calibrates the forward-VP NEES against the yud_train ground
        truth (mean 2.7, median 0.9, 88 % under the 95 % chi-square(2) quantile; nominal 2,
        1.39, 95 %); 1.0 gives the bare least-squares covariance, which is consistent for
        independent endpoint noise (synthetic Monte Carlo test) and on rendered images such as
        the corridor simulator's (NEES mean 2.7-3.0): use 1.0 there.
    """

    lsd_scale: float = 0.5
    min_length: float = 15.0
    max_segments: int = 300
    n_hypotheses: int = 300
    seed: int = 0
    score_angle_deg: float = 3.0
    inlier_angle_deg: float = 2.0
    refine_iterations: int = 3
    vp_gap_px: float = 10.0
    min_inliers: int = 4
    orthogonality_deg: float = 5.0
    cov_scale: float = 20.0


# ----------------------------------------------------------------------------- helpers


def angle_between_directions(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the angle in degrees (0..90) between directions ``a`` and ``b``, ignoring sign."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos = np.abs(np.sum(a * b, axis=-1)) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


#: largest focal length (pixels) the detectors accept (the vp command's --intrinsics bound)
MAX_FOCAL_PX = 1e6


def _nominal_K(shape: tuple[int, ...]) -> np.ndarray:
    h, w = shape[:2]
    f = float(max(h, w))
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3) and np.all(np.isfinite(K)) and \
            max(abs(K[0, 0]), abs(K[1, 1])) > MAX_FOCAL_PX:
        # beyond it back-projected directions underflow to (0, 0, 0)
        raise PerceptionError(f"K: focal lengths must be at most {MAX_FOCAL_PX:g} pixels, got "
                              f"fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or abs(np.linalg.det(K)) < 1e-12:
        raise PerceptionError(f"K must be a finite, invertible 3x3 camera matrix, got {K.tolist()}")
    return K


def _make_vp(direction: np.ndarray, cov_dir: np.ndarray, K: np.ndarray, inliers: np.ndarray,
             score: float) -> VanishingPoint:
    """Build a VanishingPoint from a direction and its 3x3 covariance (first-order to pixels)."""
    d = direction / np.linalg.norm(direction)
    if d[2] < 0:
        d = -d
    p = K @ d
    if abs(p[2]) < 1e-9 * np.linalg.norm(p):
        uv = None
        cov = np.full((2, 2), np.inf)
    else:
        uv = p[:2] / p[2]
        # d(uv)/d(d) = (K[:2] - uv K[2]) / p_z
        J = (K[:2] - np.outer(uv, K[2])) / p[2]
        cov = J @ cov_dir @ J.T
        cov = 0.5 * (cov + cov.T)
    return VanishingPoint(uv=uv, direction=d, cov=cov, inliers=np.asarray(inliers, dtype=np.int64),
                          score=float(score))


def _empty(segments: np.ndarray, start: float) -> VPResult:
    return VPResult(vps=[], segments=segments, ms=(time.perf_counter() - start) * 1e3)


# ----------------------------------------------------------------------------- seed method


def detect_seed(image: np.ndarray, config: SeedConfig = SeedConfig(),
                K: np.ndarray | None = None) -> VPResult:
    """Return the single VP of the seed paper's detector (Canny + Hough + least squares).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        Grayscale or BGR image.
    config : SeedConfig
    K : (3, 3) array, optional
        Camera matrix, only used to express the VP as a direction; without it a nominal
        camera (focal length = max(H, W), centred principal point) is assumed.

    Returns
    -------
    VPResult
        At most one VP; its covariance is the least-squares covariance ``s^2 (A^T A)^-1`` with
        ``s^2`` the residual variance of the line equations; inliers are all kept lines.
    """
    start = time.perf_counter()
    gray = to_gray_u8(image)
    K = _nominal_K(gray.shape) if K is None else _check_K(K)
    segments = hough_segments(gray, config.canny_low, config.canny_high, config.hough_rho,
                              np.radians(config.hough_theta_deg), config.hough_threshold,
                              config.min_line_length, config.max_line_gap)
    if len(segments) == 0:
        return _empty(segments, start)
    dx = segments[:, 2] - segments[:, 0]
    dy = segments[:, 3] - segments[:, 1]
    # angle of each line to the u axis folded into [0, 90] degrees
    folded = np.degrees(np.arctan2(np.abs(dy), np.abs(dx)))
    tol = config.axis_tolerance_deg
    keep = np.flatnonzero((folded > tol) & (folded < 90.0 - tol))
    if len(keep) < max(config.min_lines, 2):
        return _empty(segments, start)
    kept = segments[keep]
    # eq. (1): a u + b v = c with (a, b) the unit line normal, so residuals are pixel distances
    a = kept[:, 3] - kept[:, 1]
    b = kept[:, 0] - kept[:, 2]
    norm = np.hypot(a, b)
    a, b = a / norm, b / norm
    c = a * kept[:, 0] + b * kept[:, 1]
    A = np.column_stack([a, b])  # eq. (2)-(3)
    if np.linalg.matrix_rank(A) < 2:
        return _empty(segments, start)
    uv = np.linalg.pinv(A) @ c  # eq. (4): u = A^+ c, A^+ = (A^T A)^-1 A^T
    residual = A @ uv - c
    dof = max(len(kept) - 2, 1)
    cov = (residual @ residual / dof) * np.linalg.inv(A.T @ A)
    direction = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    direction /= np.linalg.norm(direction)
    if direction[2] < 0:
        direction = -direction
    vp = VanishingPoint(uv=uv, direction=direction, cov=0.5 * (cov + cov.T), inliers=keep,
                        score=float(np.sum(norm)))
    return VPResult(vps=[vp], segments=segments, ms=(time.perf_counter() - start) * 1e3)


# ----------------------------------------------------------------------------- Manhattan


@dataclass(frozen=True)
class _Segments:
    """Per-segment geometry used by the Manhattan detector (all arrays length M)."""

    xy: np.ndarray        # (M, 4) pixels
    mid: np.ndarray       # (M, 2) midpoints, pixels
    tangent: np.ndarray   # (M, 2) unit directions, pixels
    length: np.ndarray    # (M,) pixels
    h1: np.ndarray        # (M, 3) K^-1 [p1, 1]
    h2: np.ndarray        # (M, 3) K^-1 [p2, 1]
    normal: np.ndarray    # (M, 3) unit normal of the interpretation plane (camera frame)
    cross_norm: np.ndarray  # (M,) |h1 x h2|
    perp: np.ndarray      # (M, 3) K^-1 [-t_y, t_x, 0]: endpoint shift across the segment
    centre: np.ndarray    # (2,) principal point, the origin used for float32 scoring
    reach: np.ndarray     # (M,) half length + gap: a VP closer than this along the line is
                          # on the segment, which a finite 3D segment's image never reaches


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) arrays (np.cross's axis handling costs more than the
    arithmetic for the few hundred rows here)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _segment_geometry(xy: np.ndarray, K: np.ndarray, gap: float = 0.0) -> _Segments:
    Kinv = np.linalg.inv(K)
    p1, p2 = xy[:, :2], xy[:, 2:]
    delta = p2 - p1
    length = np.hypot(delta[:, 0], delta[:, 1])
    tangent = delta / length[:, None]
    ones = np.ones((len(xy), 1))
    h1 = np.hstack([p1, ones]) @ Kinv.T
    h2 = np.hstack([p2, ones]) @ Kinv.T
    cross = _cross(h1, h2)
    cross_norm = np.linalg.norm(cross, axis=1)
    perp_px = np.column_stack([-tangent[:, 1], tangent[:, 0], np.zeros(len(xy))])
    return _Segments(xy=xy, mid=0.5 * (p1 + p2), tangent=tangent, length=length, h1=h1, h2=h2,
                     normal=cross / cross_norm[:, None], cross_norm=cross_norm,
                     perp=perp_px @ Kinv.T, centre=K[:2, 2].copy(),
                     reach=np.maximum(0.5 * length + gap, 0.0))


def _sin2_to_vp(seg: _Segments, directions: np.ndarray, K: np.ndarray,
                dtype=np.float64) -> np.ndarray:
    """Return sin^2 of the image angle between each segment and the line from its midpoint to
    each VP: (..., M) for directions (..., 3). Works for VPs at infinity.

    With v = K d the homogeneous VP (pixels relative to the principal point), the numerator
    t x (v_xy - m v_z) is the segment's unit-normal line dotted with v, and the squared
    distance |v_xy - m v_z|^2 = [|v_xy|^2, v_x v_z, v_y v_z, v_z^2] . [1, -2 m_x, -2 m_y, |m|^2]:
    both are matrix products, which keeps the RANSAC scoring cheap.
    The image of a finite 3D segment never reaches its VP, so a VP on the segment or less than
    the gap beyond its ends (along-line distance from the midpoint below ``seg.reach``) gets
    sin^2 = 1: this rejects junctions of segments, which otherwise look like VPs."""
    lead = directions.shape[:-1]
    v = directions.reshape(-1, 3) @ K.T
    v[:, :2] -= seg.centre * v[:, 2:3]  # centred: float32 keeps enough digits
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    Q = np.column_stack([vx * vx + vy * vy, vx * vz, vy * vz, vz * vz]).astype(dtype)
    t, m = seg.tangent, seg.mid - seg.centre
    line = np.vstack([-t[:, 1], t[:, 0], t[:, 1] * m[:, 0] - t[:, 0] * m[:, 1]]).astype(dtype)
    mm = np.sum(m * m, axis=1)
    W = np.vstack([np.ones(len(m)), -2.0 * m[:, 0], -2.0 * m[:, 1], mm, mm - seg.reach ** 2])
    W = W.astype(dtype)
    num2 = v.astype(dtype) @ line
    np.multiply(num2, num2, out=num2)
    den2 = Q @ W[:4]
    # along-line distance^2 = den2 - num2 < (v_z reach)^2  <=>  Q . W_off < num2
    on_segment = (Q @ W[[0, 1, 2, 4]]) < num2
    np.divide(num2, np.maximum(den2, np.finfo(dtype).tiny, out=den2), out=num2)
    np.copyto(num2, dtype(1.0), where=on_segment)
    return num2.reshape(*lead, len(m))


def _hypotheses(seg: _Segments, n: int, rng: np.random.Generator) -> np.ndarray:
    """Return (H, 3, 3) candidate frames [d1, d2, d3] from length-weighted segment triples:
    two segments meet at d1, the third fixes d2 orthogonal to d1, d3 = d1 x d2."""
    m = len(seg.length)
    prob = seg.length / seg.length.sum()
    idx = rng.choice(m, size=(n, 3), p=prob)
    n_i, n_j, n_k = seg.normal[idx[:, 0]], seg.normal[idx[:, 1]], seg.normal[idx[:, 2]]
    d1 = _cross(n_i, n_j)
    d2 = _cross(d1, n_k)
    norm1 = np.linalg.norm(d1, axis=1)
    norm2 = np.linalg.norm(d2, axis=1)
    # near-parallel interpretation planes give an ill-defined intersection
    ok = (norm1 > 1e-3) & (norm2 > 1e-3 * np.maximum(norm1, 1e-300))
    ok &= (idx[:, 0] != idx[:, 1]) & (idx[:, 2] != idx[:, 0]) & (idx[:, 2] != idx[:, 1])
    d1 = d1[ok] / norm1[ok, None]
    d2 = d2[ok] / norm2[ok, None]
    d3 = _cross(d1, d2)
    return np.stack([d1, d2, d3], axis=1)


def _best_frame(seg: _Segments, K: np.ndarray, config: ManhattanConfig) -> np.ndarray | None:
    rng = np.random.default_rng(config.seed)
    frames = _hypotheses(seg, config.n_hypotheses, rng)
    if len(frames) == 0:
        return None
    sin2_score = np.float32(np.sin(np.radians(config.score_angle_deg)) ** 2)
    sin2 = _sin2_to_vp(seg, frames, K, dtype=np.float32)  # (H, 3, M)
    # soft inlier count: quadratic fall-off in the angle, zero beyond score_angle_deg
    support = np.maximum(np.float32(1.0) - sin2.min(axis=1) / sin2_score, np.float32(0.0))
    scores = support @ seg.length.astype(np.float32)
    return frames[int(np.argmax(scores))].T  # columns are directions


def _residual_scale(seg: _Segments, idx: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Return s_i, the std of n_i . d per pixel of endpoint noise across the segment.

    First order: n.d = det(h1, h2, d) / |h1 x h2|; at an inlier (n.d ~ 0) only the numerator's
    derivative matters: d/dh1 = h2 x d, d/dh2 = d x h1, each endpoint moved along ``perp``.
    """
    h1, h2, perp = seg.h1[idx], seg.h2[idx], seg.perp[idx]
    g1 = np.sum(_cross(h2, d) * perp, axis=1)
    g2 = np.sum(_cross(d, h1) * perp, axis=1)
    return np.sqrt(g1 ** 2 + g2 ** 2) / seg.cross_norm[idx]


def _variance(chi2: float, dof: int) -> float:
    """Return the residual variance, inflated by dof / (dof - 2): with the noise estimated from
    the same residuals the normalised error follows a Student-t, whose variance is larger."""
    return chi2 / max(dof - 2, 1)  # (chi2 / dof) * dof / (dof - 2)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _expmap(w: np.ndarray) -> np.ndarray:
    """Return the rotation matrix exp([w]x) (OpenCV's Rodrigues formula)."""
    import cv2

    return cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))[0]


def _assign(seg: _Segments, R: np.ndarray, K: np.ndarray, sin_inlier: float):
    sin2 = _sin2_to_vp(seg, R.T, K)  # (3, M)
    label = np.argmin(sin2, axis=0)
    inlier = sin2[label, np.arange(sin2.shape[1])] < sin_inlier ** 2
    return label, inlier


def _fit_rotation(seg: _Segments, R: np.ndarray, label: np.ndarray, inlier: np.ndarray,
                  iterations: int = 3):
    """Weighted Gauss-Newton of R (columns = VP directions) on r_i = n_i . R e_k(i).

    Returns R, the 3x3 information matrix H = J^T J (per unit pixel variance) and the
    residual variance sigma^2 (pixels^2)."""
    idx = np.flatnonzero(inlier)
    k = label[idx]
    n = seg.normal[idx]
    for _ in range(iterations):
        d = R.T[k]  # (N, 3) direction of each inlier's VP
        s = _residual_scale(seg, idx, d)
        r = np.sum(n * d, axis=1) / s
        # left perturbation R <- Exp(w) R: d r_i / d w = (d_k x n_i) / s_i
        J = _cross(d, n) / s[:, None]
        H = J.T @ J
        step = -np.linalg.solve(H, J.T @ r)
        R = _expmap(step) @ R
        if np.linalg.norm(step) < 1e-10:
            break
    d = R.T[k]
    s = _residual_scale(seg, idx, d)
    r = np.sum(n * d, axis=1) / s
    J = _cross(d, n) / s[:, None]
    H = J.T @ J
    return R, H, _variance(float(r @ r), len(idx) - 3)


def _fit_direction(seg: _Segments, d: np.ndarray, idx: np.ndarray, iterations: int = 3):
    """Weighted fit of one direction to its inliers (no orthogonality): minimise
    sum (n_i . d)^2 / s_i^2 over unit d. Returns d and its 3x3 covariance."""
    n = seg.normal[idx]
    for _ in range(iterations):
        s = _residual_scale(seg, idx, d)
        M = (n / s[:, None] ** 2).T @ n
        d_new = np.linalg.eigh(M)[1][:, 0]
        d = d_new if d_new @ d >= 0 else -d_new
    s = _residual_scale(seg, idx, d)
    r = (n @ d) / s
    sigma2 = _variance(float(r @ r), len(idx) - 2)
    # tangent-plane information B^T M B, B an orthonormal basis of d's orthogonal complement
    B = np.linalg.svd(d[None, :])[2][1:].T
    M = (n / s[:, None] ** 2).T @ n
    cov_t = sigma2 * np.linalg.inv(B.T @ M @ B)
    return d, B @ cov_t @ B.T


def _tangent_basis(d: np.ndarray) -> np.ndarray:
    """Return a 3x2 orthonormal basis of the plane orthogonal to the unit vector d."""
    # b1 = e x d with e the axis least aligned with d among x, y
    if abs(d[0]) < 0.9:
        b1 = np.array([0.0, -d[2], d[1]])
    else:
        b1 = np.array([d[2], 0.0, -d[0]])
    b1 /= np.sqrt(b1 @ b1)
    b2 = np.array([d[1] * b1[2] - d[2] * b1[1], d[2] * b1[0] - d[0] * b1[2],
                   d[0] * b1[1] - d[1] * b1[0]])
    return np.column_stack([b1, b2])


def _fit_soft_orthogonal(seg: _Segments, R: np.ndarray, label: np.ndarray, inlier: np.ndarray,
                         noise_var: float, sigma_orth: float, iterations: int = 3):
    """MAP fit of three unit directions: segment residuals plus a soft orthogonality prior.

    Minimises sum_k sum_{i in k} (n_i . d_k)^2 / (s_i^2 noise_var) + sum_{a<b} (d_a . d_b)^2 /
    sigma_orth^2 by Gauss-Newton on tangent-plane steps (6 parameters). A direction without
    inliers is fixed by the prior alone. Returns (3, 3) directions (rows) and their (3, 3, 3)
    covariances (inverse Gauss-Newton information, mapped back to 3D)."""
    D = R.T.copy()
    members = [np.flatnonzero(inlier & (label == k)) for k in range(3)]
    pairs = ((0, 1), (0, 2), (1, 2))
    for it in range(iterations + 1):
        bases = [_tangent_basis(d) for d in D]
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for k, idx in enumerate(members):
            if len(idx) == 0:
                continue
            s = _residual_scale(seg, idx, D[k]) * np.sqrt(noise_var)
            n = seg.normal[idx] / s[:, None]
            J = n @ bases[k]
            H[2 * k:2 * k + 2, 2 * k:2 * k + 2] += J.T @ J
            g[2 * k:2 * k + 2] += J.T @ (n @ D[k])
        for a, b in pairs:
            J = np.zeros(6)
            J[2 * a:2 * a + 2] = D[b] @ bases[a]
            J[2 * b:2 * b + 2] = D[a] @ bases[b]
            H += np.outer(J, J) / sigma_orth ** 2
            g += J * (D[a] @ D[b]) / sigma_orth ** 2
        if it == iterations:
            break
        step = -np.linalg.solve(H, g)
        for k in range(3):
            d = D[k] + bases[k] @ step[2 * k:2 * k + 2]
            D[k] = d / np.linalg.norm(d)
    cov_t = np.linalg.inv(H)
    covs = np.array([bases[k] @ cov_t[2 * k:2 * k + 2, 2 * k:2 * k + 2] @ bases[k].T
                     for k in range(3)])
    return D, covs


def _observed(seg: _Segments, label: np.ndarray, inlier: np.ndarray,
              min_inliers: int) -> np.ndarray:
    """Return a (3,) bool mask: VP k has >= min_inliers inliers on at least two distinct
    interpretation planes (pieces of one image line do not fix a VP)."""
    mask = np.zeros(3, dtype=bool)
    for k in range(3):
        n = seg.normal[inlier & (label == k)]
        if len(n) >= min_inliers:
            # eigenvalues ascending: [~0 (the VP itself), spread of the planes, ...]
            mask[k] = np.linalg.eigvalsh(n.T @ n)[1] > 1e-6 * len(n)
    return mask


def _refine(seg: _Segments, R: np.ndarray, K: np.ndarray,
            config: ManhattanConfig) -> list[VanishingPoint]:
    """Return the refined VPs of the RANSAC frame R (columns = directions)."""
    sin_inlier = np.sin(np.radians(config.inlier_angle_deg))
    for _ in range(max(config.refine_iterations, 1)):
        label, inlier = _assign(seg, R, K, sin_inlier)
        observed = _observed(seg, label, inlier, config.min_inliers)
        if np.count_nonzero(observed) < 2:
            break
        # only the observed VPs' segments enter the rigid fit (an unobservable one adds a
        # rank-deficient block)
        R, _, _ = _fit_rotation(seg, R, label, inlier & observed[label], iterations=2)
    label, inlier = _assign(seg, R, K, sin_inlier)
    observed = _observed(seg, label, inlier, config.min_inliers)
    vps: list[VanishingPoint] = []
    if np.count_nonzero(observed) >= 2:
        used = inlier & observed[label]
        R, H, sigma2 = _fit_rotation(seg, R, label, used, iterations=1)
        if config.orthogonality_deg > 0:
            # the data term carries the inflated noise (cov_scale) so that its weight against
            # the orthogonality prior is the calibrated one
            D, covs = _fit_soft_orthogonal(seg, R, label, used, config.cov_scale * sigma2,
                                           np.sin(np.radians(config.orthogonality_deg)),
                                           iterations=2)
        else:
            cov_w = config.cov_scale * sigma2 * np.linalg.inv(H)
            D = R.T
            covs = np.array([_skew(d) @ cov_w @ _skew(d).T for d in D])
        for k in range(3):
            members = np.flatnonzero(used & (label == k))
            vps.append(_make_vp(D[k], covs[k], K, members, seg.length[members].sum()))
    elif np.count_nonzero(observed) == 1:
        k = int(np.flatnonzero(observed)[0])
        members = np.flatnonzero(inlier & (label == k))
        d, cov_d = _fit_direction(seg, R[:, k], members)
        vps.append(_make_vp(d, config.cov_scale * cov_d, K, members, seg.length[members].sum()))
    if not all(np.all(np.isfinite(vp.direction)) and not np.any(np.isnan(vp.cov)) for vp in vps):
        return []
    return vps


def detect_manhattan(image: np.ndarray, K: np.ndarray,
                     config: ManhattanConfig = ManhattanConfig()) -> VPResult:
    """Return up to three orthogonal (Manhattan) vanishing points with pixel covariances.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        Grayscale or BGR image.
    K : (3, 3) array
        Camera matrix (pixels).
    config : ManhattanConfig

    Returns
    -------
    VPResult
        ``vps`` best first (by inlier length), empty when fewer than ``min_inliers``
        consistent segments exist (blank image, too few segments). When two VPs are observed,
        the third (implied by orthogonality) is reported as well. ``segments`` are the LSD
        segments (longest ``max_segments`` of at least ``min_length`` pixels).
    """
    start = time.perf_counter()
    K = _check_K(K)
    gray = to_gray_u8(image)
    xy = lsd_segments(gray, scale=config.lsd_scale, min_length=config.min_length,
                      max_segments=config.max_segments)
    return _manhattan(xy, K, config, start)


def manhattan_from_segments(segments: np.ndarray, K: np.ndarray,
                            config: ManhattanConfig = ManhattanConfig()) -> VPResult:
    """Return the Manhattan VPs of given line segments (any detector); see detect_manhattan.

    ``segments`` is (M, 4) ``x1, y1, x2, y2`` in pixels; ``min_length`` and ``max_segments``
    of ``config`` are not applied here, degenerate (zero-length) segments are dropped.
    """
    start = time.perf_counter()
    K = _check_K(K)
    xy = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    return _manhattan(xy, K, config, start)


def _manhattan(xy: np.ndarray, K: np.ndarray, config: ManhattanConfig,
               start: float) -> VPResult:
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    xy = xy[np.hypot(xy[:, 2] - xy[:, 0], xy[:, 3] - xy[:, 1]) > 1e-6]
    if len(xy) < max(config.min_inliers, 3):
        return _empty(xy, start)
    seg = _segment_geometry(xy, K, config.vp_gap_px)
    R = _best_frame(seg, K, config)
    if R is None:
        return _empty(xy, start)
    try:
        vps = _refine(seg, R, K, config)
    except np.linalg.LinAlgError:
        # degenerate geometry the observability test did not catch: nothing found
        return _empty(xy, start)
    vps.sort(key=lambda vp: -vp.score)
    return VPResult(vps=vps, segments=xy, ms=(time.perf_counter() - start) * 1e3)
