"""Trajectory evaluation as evo computes it: association, Umeyama alignment, APE and RPE.

Pure numpy: no plotting, no file I/O (readers and writers are in
:mod:`estimation.trajectory_io`). Poses are ``T_world_camera`` as (N, 4, 4) arrays; the
ground truth and the estimate may live in different world frames.

Which evo command each metric reproduces (see docs/evaluation.md):

* ``ate_aligned_*``       -- ``evo_ape tum gt est -a`` (translation part, SE(3) Umeyama),
* ``ate_unaligned_rmse_m`` -- ``evo_ape tum gt est``,
* ``ate_origin_aligned_rmse_m`` -- ``evo_ape tum gt est --align_origin``,
* ``rpe_*``               -- ``evo_rpe tum gt est --delta 1 --delta_unit f`` (``-r trans_part``
  and ``-r angle_deg``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .errors import EstimationError

MIN_MATCHED_POSES = 3


# ---------------------------------------------------------------- association
def associate(t_first: np.ndarray, t_second: np.ndarray, max_diff: float = 0.02,
              offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the matched timestamp pairs ``(idx_first, idx_second)``.

    The matching of the TUM benchmark's ``associate.py``: every pair with
    ``|t_first[i] - (t_second[j] + offset)| <= max_diff`` is a candidate; candidates are
    taken closest first, and a pose already matched is never used again, so the pairs are
    unique. The result is sorted by ``t_first`` (then ``t_second``).

    For the usual case (a camera at 30 Hz against motion capture at 100 Hz) this is the
    same set of pairs as evo's ``sync.associate_trajectories``. evo matches every pose of
    the *shorter* trajectory to its nearest pose in the longer one, which can use one pose
    of the longer trajectory twice when the shorter one is sampled faster than ``max_diff``
    allows; here the second claimant takes its next-closest pose (or none).

    Parameters
    ----------
    t_first, t_second : (N,), (M,) array_like
        Timestamps in seconds, any order.
    max_diff : float
        Largest accepted time difference (s).
    offset : float
        Added to ``t_second`` before matching (s).

    Returns
    -------
    idx_first, idx_second : (K,) int arrays
        ``t_first[idx_first[k]]`` matches ``t_second[idx_second[k]]``.
    """
    t_first = _as_stamps(t_first, "t_first")
    t_second = _as_stamps(t_second, "t_second")
    if not (np.isfinite(max_diff) and max_diff >= 0):
        raise EstimationError(f"max_diff must be a finite number >= 0, got {max_diff}")
    if not np.isfinite(offset):
        raise EstimationError(f"offset must be finite, got {offset}")
    empty = np.zeros(0, dtype=np.intp)
    if len(t_first) == 0 or len(t_second) == 0:
        return empty, empty.copy()

    shifted = t_second + offset  # as associate.py: b + offset
    order_second = np.argsort(shifted, kind="stable")
    shifted_sorted = shifted[order_second]
    # Candidate ranges in the sorted second list, widened by one on each side so that the
    # exact test below (the same arithmetic as associate.py) decides the boundary cases.
    lo = np.searchsorted(shifted_sorted, t_first - max_diff, side="left") - 1
    hi = np.searchsorted(shifted_sorted, t_first + max_diff, side="right") + 1
    lo = np.clip(lo, 0, len(shifted_sorted))
    hi = np.clip(hi, 0, len(shifted_sorted))
    counts = hi - lo
    cand_first = np.repeat(np.arange(len(t_first)), counts)
    starts = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    cand_second = order_second[starts + np.arange(len(cand_first))]
    diff = np.abs(t_first[cand_first] - shifted[cand_second])
    keep = diff <= max_diff
    cand_first, cand_second, diff = cand_first[keep], cand_second[keep], diff[keep]

    # Closest first; ties by time then index, as associate.py sorts (diff, a, b) tuples.
    order = np.lexsort((cand_second, cand_first, t_second[cand_second], t_first[cand_first],
                        diff))
    used_first = np.zeros(len(t_first), dtype=bool)
    used_second = np.zeros(len(t_second), dtype=bool)
    pairs_first, pairs_second = [], []
    limit = min(len(t_first), len(t_second))
    # Greedy matching is sequential by nature; the loop runs over candidate pairs only.
    for i, j in zip(cand_first[order].tolist(), cand_second[order].tolist()):
        if used_first[i] or used_second[j]:
            continue
        used_first[i] = used_second[j] = True
        pairs_first.append(i)
        pairs_second.append(j)
        if len(pairs_first) == limit:
            break
    if not pairs_first:
        return empty, empty.copy()
    idx_first = np.asarray(pairs_first, dtype=np.intp)
    idx_second = np.asarray(pairs_second, dtype=np.intp)
    order = np.lexsort((idx_second, idx_first, t_second[idx_second], t_first[idx_first]))
    return idx_first[order], idx_second[order]


def _as_stamps(stamps: np.ndarray, name: str) -> np.ndarray:
    stamps = np.asarray(stamps, dtype=np.float64)
    if stamps.ndim != 1:
        raise EstimationError(f"{name} must be a 1-D array of timestamps, got shape "
                              f"{stamps.shape}")
    if not np.all(np.isfinite(stamps)):
        raise EstimationError(f"{name} has NaN or inf timestamps")
    return stamps


# ---------------------------------------------------------------- SE(3) helpers
def umeyama_alignment(src: np.ndarray, dst: np.ndarray,
                      with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """The similarity ``(R, t, s)`` minimising ``sum |dst_k - (s R src_k + t)|^2``.

    Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE PAMI 1991 (eq. 34-43); the same result as evo's
    ``geometry.umeyama_alignment(src.T, dst.T, with_scale)``.

    Parameters
    ----------
    src, dst : (N, 3) arrays
        Corresponding points (for a trajectory: estimated and ground-truth positions).
    with_scale : bool
        Estimate the scale ``s`` too (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns
    -------
    R : (3, 3) array
        Rotation, det(R) = +1.
    t : (3,) array
        Translation.
    s : float
        Scale (1.0 unless ``with_scale``).

    Raises
    ------
    EstimationError
        Shapes differ or are not (N, 3), values are not finite, or the points are
        degenerate (fewer than 3, all equal or collinear) so the rotation is undetermined.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise EstimationError(f"umeyama_alignment needs two (N, 3) arrays of the same shape, "
                              f"got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise EstimationError("umeyama_alignment: NaN or inf in the points")
    n = len(src)
    if n < 3:
        raise EstimationError(f"umeyama_alignment needs at least 3 points, got {n}")
    mean_src = src.mean(axis=0)
    mean_dst = dst.mean(axis=0)
    src_c = src - mean_src
    dst_c = dst - mean_dst
    var_src = float(np.sum(src_c**2)) / n                    # eq. 36
    cov = dst_c.T @ src_c / n                                # eq. 38
    U, d, Vt = np.linalg.svd(cov)
    # Rank < 2 leaves a rotation about the common line free. evo tests d > eps in absolute
    # terms; a relative test does not depend on the units of the positions.
    if d[0] <= 0.0 or d[1] <= 1e-12 * d[0]:
        raise EstimationError("umeyama_alignment: the points are degenerate (all equal or "
                              "collinear); the rotation is undetermined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:          # eq. 43, keeps det(R) = +1
        S[2, 2] = -1.0
    R = U @ S @ Vt                                           # eq. 40
    s = float(np.trace(np.diag(d) @ S) / var_src) if with_scale else 1.0   # eq. 42
    t = mean_dst - s * R @ mean_src                          # eq. 41
    return R, t, s


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4, 4) or a stack (..., 4, 4) of rigid transforms."""
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    inv = np.zeros_like(T)
    inv[..., :3, :3] = R_t
    inv[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    inv[..., 3, 3] = 1.0
    return inv


def rotation_angle(R: np.ndarray) -> np.ndarray | float:
    """Rotation angle (rad, in [0, pi]) of one (3, 3) or a stack (..., 3, 3) of rotations.

    ``atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)``: accurate near 0 and near pi,
    where ``arccos`` of the trace alone loses half the digits.
    """
    R = np.asarray(R, dtype=np.float64)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    axis = np.stack([R[..., 2, 1] - R[..., 1, 2],
                     R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    angle = np.arctan2(0.5 * np.linalg.norm(axis, axis=-1), cos)
    return float(angle) if np.ndim(angle) == 0 else angle


# ---------------------------------------------------------------- metrics
@dataclass(frozen=True)
class TrajectoryMetrics:
    """Errors of an estimated trajectory against ground truth (evo's definitions).

    Attributes
    ----------
    matched : int
        Number of associated (ground truth, estimate) pose pairs; every metric uses them.
    gt_poses, est_poses : int
        Number of poses given.
    first_matched_gt_index, first_matched_est_index : int
        Index of the first matched pose in each input. ``first_matched_est_index > 0``
        when the ground truth starts after the estimate (common in TUM recordings).
    max_matched_time_diff_s : float
        Largest ``|t_gt - t_est|`` of the matched pairs (0 when matched by index).
    ate_aligned_rmse_m, ate_aligned_mean_m, ate_aligned_median_m, ate_aligned_max_m : float
        Translation APE ``|t_gt_k - (R t_est_k + t)|`` after the SE(3) Umeyama alignment
        ``(R, t)`` of the matched estimated positions onto the ground truth
        (``evo_ape tum gt est -a``).
    ate_unaligned_rmse_m : float
        Translation APE in the frames as given (``evo_ape tum gt est``).
    ate_origin_aligned_rmse_m : float
        Translation APE after moving the estimate by ``T_gt_0 T_est_0^-1`` so that the
        first matched poses coincide (``evo_ape tum gt est --align_origin``).
    rpe_delta_frames, rpe_pairs : int
        RPE pairs ``(0, d), (d, 2d), ...`` of matched poses, ``d = rpe_delta_frames``
        (evo's consecutive pairs), and how many there are.
    rpe_trans_rmse_m, rpe_rot_rmse_deg : float
        RMSE of the translation and of the rotation angle of
        ``E_i = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``, Q ground truth, P estimate
        (``evo_rpe tum gt est --delta d --delta_unit f`` with ``-r trans_part`` and
        ``-r angle_deg``).
    rot_err_mean_deg, rot_err_max_deg : float
        Angle of ``(R_gt_0^T R_gt_k)^T (R_est_0^T R_est_k)``: the rotation error relative to
        the first matched frame, mean and max over the matched frames (frame 0 included).
    aligned_rot_err_mean_deg : float
        Mean angle of ``R_gt_k^T R R_est_k``: rotation error after the SE(3) alignment.
    T_gtworld_estworld : tuple
        The SE(3) alignment ``(R, t)`` as a 4x4 nested tuple, mapping estimate-world
        coordinates into the ground-truth world.
    """

    matched: int
    gt_poses: int
    est_poses: int
    first_matched_gt_index: int
    first_matched_est_index: int
    max_matched_time_diff_s: float
    ate_aligned_rmse_m: float
    ate_aligned_mean_m: float
    ate_aligned_median_m: float
    ate_aligned_max_m: float
    ate_unaligned_rmse_m: float
    ate_origin_aligned_rmse_m: float
    rpe_delta_frames: int
    rpe_pairs: int
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    rot_err_mean_deg: float
    rot_err_max_deg: float
    aligned_rot_err_mean_deg: float
    T_gtworld_estworld: tuple

    def to_dict(self) -> dict:
        """The fields as plain Python numbers and lists (JSON-ready)."""
        out = asdict(self)
        out["T_gtworld_estworld"] = [list(row) for row in self.T_gtworld_estworld]
        return out


def _check_poses(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise EstimationError(f"{name} must be an (N, 4, 4) array of poses, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(T), axis=(1, 2)))[0])
        raise EstimationError(f"{name}: pose {bad} has NaN or inf values")
    return T


def _rmse(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _translation_errors(T_gt: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    return np.linalg.norm(T_gt[:, :3, 3] - T_est[:, :3, 3], axis=1)


def evaluate_trajectory(t_gt: np.ndarray | None, T_gt: np.ndarray, t_est: np.ndarray | None,
                        T_est: np.ndarray, max_diff: float = 0.02,
                        rpe_delta: int = 1) -> TrajectoryMetrics:
    """ATE, RPE and rotation errors of an estimated trajectory, as evo computes them.

    Parameters
    ----------
    t_gt : (N,) array or None
        Ground-truth timestamps (s). ``None`` together with ``t_est=None`` matches the
        poses by index (KITTI files have no timestamps); the lengths must then be equal.
    T_gt : (N, 4, 4) array
        Ground-truth poses ``T_world_camera``.
    t_est : (M,) array or None
        Estimate timestamps (s), or ``None`` (see ``t_gt``).
    T_est : (M, 4, 4) array
        Estimated poses ``T_world_camera``; its world frame may differ from the ground
        truth's (the aligned metrics remove a rigid transform).
    max_diff : float
        Largest time difference of an associated pair (s), see :func:`associate`.
    rpe_delta : int
        Frame distance of the RPE pairs, counted in matched poses.

    Returns
    -------
    TrajectoryMetrics

    Raises
    ------
    EstimationError
        Wrong shapes, non-finite values, fewer than 3 matched pairs, unequal lengths
        when matching by index, or no RPE pair for ``rpe_delta``.
    """
    T_gt = _check_poses(T_gt, "ground truth poses")
    T_est = _check_poses(T_est, "estimated poses")
    if isinstance(rpe_delta, bool) or int(rpe_delta) != rpe_delta or rpe_delta < 1:
        raise EstimationError(f"rpe_delta must be an integer >= 1, got {rpe_delta}")
    rpe_delta = int(rpe_delta)

    if t_gt is None and t_est is None:
        if len(T_gt) != len(T_est):
            raise EstimationError(
                f"without timestamps poses are matched by index, but the ground truth has "
                f"{len(T_gt)} poses and the estimate {len(T_est)}")
        idx_gt = idx_est = np.arange(len(T_gt))
        time_diffs = np.zeros(len(T_gt))
    elif t_gt is None or t_est is None:
        raise EstimationError("give timestamps for both trajectories or for neither")
    else:
        t_gt = _as_stamps(t_gt, "ground truth timestamps")
        t_est = _as_stamps(t_est, "estimate timestamps")
        if len(t_gt) != len(T_gt) or len(t_est) != len(T_est):
            raise EstimationError(
                f"timestamps and poses differ in length: ground truth {len(t_gt)} vs "
                f"{len(T_gt)}, estimate {len(t_est)} vs {len(T_est)}")
        idx_gt, idx_est = associate(t_gt, t_est, max_diff=max_diff)
        time_diffs = np.abs(t_gt[idx_gt] - t_est[idx_est])
    matched = len(idx_gt)
    if matched < MIN_MATCHED_POSES:
        raise EstimationError(
            f"only {matched} pose pairs matched (need {MIN_MATCHED_POSES}); "
            f"ground truth {len(T_gt)} poses, estimate {len(T_est)}, max time difference "
            f"{max_diff} s")
    gt = T_gt[idx_gt]
    est = T_est[idx_est]

    # APE after SE(3) Umeyama alignment (evo_ape -a): T_align = [R t; 0 1] applied on the left.
    R_align, t_align, _ = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=False)
    T_align = np.eye(4)
    T_align[:3, :3] = R_align
    T_align[:3, 3] = t_align
    est_aligned = T_align @ est
    ate_aligned = _translation_errors(gt, est_aligned)

    # APE with the first matched poses made equal (evo_ape --align_origin).
    est_origin = (gt[0] @ se3_inverse(est[0])) @ est
    ate_origin = _translation_errors(gt, est_origin)

    # RPE over evo's consecutive pairs (0, d), (d, 2d), ...
    ids = np.arange(0, matched, rpe_delta)
    first, second = ids[:-1], ids[1:]
    if len(first) == 0:
        raise EstimationError(f"rpe_delta {rpe_delta} leaves no pose pair among {matched} "
                              "matched poses")
    gt_rel = se3_inverse(gt[first]) @ gt[second]
    est_rel = se3_inverse(est[first]) @ est[second]
    rpe = se3_inverse(gt_rel) @ est_rel

    R_gt = gt[:, :3, :3]
    R_est = est[:, :3, :3]
    R_gt_rel = np.swapaxes(R_gt[0], -1, -2) @ R_gt
    R_est_rel = np.swapaxes(R_est[0], -1, -2) @ R_est
    rot_err = np.degrees(rotation_angle(np.swapaxes(R_gt_rel, -1, -2) @ R_est_rel))
    aligned_rot_err = np.degrees(
        rotation_angle(np.swapaxes(R_gt, -1, -2) @ est_aligned[:, :3, :3]))

    return TrajectoryMetrics(
        matched=matched,
        gt_poses=len(T_gt),
        est_poses=len(T_est),
        first_matched_gt_index=int(idx_gt[0]),
        first_matched_est_index=int(idx_est[0]),
        max_matched_time_diff_s=float(time_diffs.max()),
        ate_aligned_rmse_m=_rmse(ate_aligned),
        ate_aligned_mean_m=float(ate_aligned.mean()),
        ate_aligned_median_m=float(np.median(ate_aligned)),
        ate_aligned_max_m=float(ate_aligned.max()),
        ate_unaligned_rmse_m=_rmse(_translation_errors(gt, est)),
        ate_origin_aligned_rmse_m=_rmse(ate_origin),
        rpe_delta_frames=rpe_delta,
        rpe_pairs=len(first),
        rpe_trans_rmse_m=_rmse(np.linalg.norm(rpe[:, :3, 3], axis=1)),
        rpe_rot_rmse_deg=_rmse(np.degrees(rotation_angle(rpe[:, :3, :3]))),
        rot_err_mean_deg=float(rot_err.mean()),
        rot_err_max_deg=float(rot_err.max()),
        aligned_rot_err_mean_deg=float(aligned_rot_err.mean()),
        T_gtworld_estworld=tuple(tuple(float(v) for v in row) for row in T_align),
    )


__all__ = [
    "associate", "umeyama_alignment", "evaluate_trajectory", "TrajectoryMetrics",
    "rotation_angle", "se3_inverse",
]
