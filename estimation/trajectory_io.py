"""Trajectory files as arrays: KITTI poses, TUM arrays, and the (N, 4, 4) pose matrices.

* KITTI odometry poses: one line per frame, 12 numbers, the row-major 3x4 upper part of
  ``T_world_camera`` (``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz``); no timestamps.
* TUM: ``t tx ty tz qx qy qz qw`` (quaternion x y z w), read by
  :func:`estimation.io.read_tum_arrays`.

Readers raise :class:`~estimation.errors.FormatError` naming ``file:line``; writers go
through :func:`~estimation.fileio.atomic_write` and print every number with ``repr``
(shortest round-trip form), so a read-write cycle is exact.
"""
from __future__ import annotations

import os

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import FormatError, OctofactorError
from .fileio import atomic_write, check_input_file
from .io import _check_translation, _parse_float_line, read_tum_arrays

PathLike = str | os.PathLike

ORTHONORMAL_TOL = 1e-3  # KITTI ground truth prints ~7 significant digits
TRAJECTORY_FORMATS = ("tum", "kitti")


def _format_numbers(values) -> str:
    return " ".join(repr(float(v)) for v in values)


# ---------------------------------------------------------------- conversions
def matrices_from_tum(poses_tum: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``T_world_camera`` from (N, 7) ``tx ty tz qx qy qz qw`` (TUM, x y z w).

    Quaternions are normalised first (as evo does).
    """
    poses_tum = np.asarray(poses_tum, dtype=np.float64).reshape(-1, 7)
    T = np.tile(np.eye(4), (len(poses_tum), 1, 1))
    if len(poses_tum):
        T[:, :3, :3] = Rotation.from_quat(poses_tum[:, 3:7]).as_matrix()
        T[:, :3, 3] = poses_tum[:, :3]
    return T


def tum_from_matrices(T_world_camera: np.ndarray) -> np.ndarray:
    """(N, 7) ``tx ty tz qx qy qz qw`` (TUM order, x y z w, qw >= 0) from (N, 4, 4) poses."""
    T = _check_pose_stack(T_world_camera, "poses")
    out = np.empty((len(T), 7))
    out[:, :3] = T[:, :3, 3]
    if len(T):
        quat = Rotation.from_matrix(T[:, :3, :3]).as_quat()
        quat[quat[:, 3] < 0] *= -1.0
        out[:, 3:] = quat
    return out


def _check_pose_stack(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
        raise OctofactorError(f"{what} must be an (N, 4, 4) or (N, 3, 4) array, got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise OctofactorError(f"{what} have NaN or inf values")
    return T


# ---------------------------------------------------------------- KITTI
def read_kitti_arrays(path: PathLike) -> np.ndarray:
    """Parse a KITTI pose file: (N, 4, 4) ``T_world_camera`` in file order (N may be 0).

    Each line holds the 12 numbers of the row-major 3x4 ``[R | t]``. Blank lines and text
    after ``#`` are skipped. A line with the wrong count, a non-number, NaN/inf, or a
    rotation that is not orthonormal with det +1 (within 1e-3) raises a
    :class:`FormatError` naming ``file:line``.
    """
    rows = []
    check_input_file(path)
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line_no, line in enumerate(handle, 1):
            tokens = line.split("#", 1)[0].split()
            if not tokens:
                continue
            values = _parse_float_line(path, line_no, tokens, 12,
                                       "KITTI pose line (row-major 3x4 [R | t])")
            R = values.reshape(3, 4)[:, :3]
            if np.max(np.abs(R)) > 1.0 + ORTHONORMAL_TOL:
                raise FormatError(path, "rotation is not orthonormal (an entry beyond 1)",
                                  line=line_no)
            _check_translation(path, line_no, values.reshape(3, 4)[:, 3], "KITTI pose")
            deviation = float(np.max(np.abs(R @ R.T - np.eye(3))))
            if deviation > ORTHONORMAL_TOL:
                raise FormatError(path, f"rotation is not orthonormal (|R R^T - I| = "
                                  f"{deviation:.3g})", line=line_no)
            if np.linalg.det(R) < 0:
                raise FormatError(path, "rotation has det -1 (a reflection)", line=line_no)
            rows.append(values)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        T[:, :3, :] = np.asarray(rows).reshape(-1, 3, 4)
    return T


def write_kitti(path: PathLike, poses: np.ndarray) -> None:
    """Write (N, 4, 4) or (N, 3, 4) ``T_world_camera`` as a KITTI pose file (exact numbers)."""
    T = _check_pose_stack(poses, "KITTI poses")
    with atomic_write(path, "w") as handle:
        for pose in T:
            handle.write(_format_numbers(pose[:3, :4].ravel()) + "\n")


# ---------------------------------------------------------------- TUM arrays
def write_tum_arrays(path: PathLike, timestamps: np.ndarray, poses_tum: np.ndarray) -> None:
    """Write a TUM trajectory from (N,) timestamps and (N, 7) ``tx ty tz qx qy qz qw``.

    The inverse of :func:`estimation.io.read_tum_arrays`: numbers in shortest round-trip
    form (as :func:`estimation.io.format_tum_line`), so a round trip is exact.
    """
    timestamps = np.asarray(timestamps, dtype=np.float64)
    poses_tum = np.asarray(poses_tum, dtype=np.float64)
    if timestamps.ndim != 1 or poses_tum.shape != (len(timestamps), 7):
        raise OctofactorError(f"TUM arrays must be (N,) timestamps and (N, 7) poses, got "
                              f"{timestamps.shape} and {poses_tum.shape}")
    if not (np.all(np.isfinite(timestamps)) and np.all(np.isfinite(poses_tum))):
        raise OctofactorError("TUM arrays have NaN or inf values")
    with atomic_write(path, "w") as handle:
        handle.write("# timestamp tx ty tz qx qy qz qw\n")
        for stamp, pose in zip(timestamps, poses_tum):
            handle.write(_format_numbers((stamp, *pose)) + "\n")


# ---------------------------------------------------------------- any format
def detect_trajectory_format(path: PathLike) -> str:
    """``'kitti'`` when the first data line has 12 numbers, ``'tum'`` when it has 8."""
    check_input_file(path)
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line_no, line in enumerate(handle, 1):
            tokens = line.split("#", 1)[0].replace(",", " ").split()
            if not tokens:
                continue
            if len(tokens) == 12:
                return "kitti"
            if len(tokens) == 8:
                return "tum"
            raise FormatError(path, f"{len(tokens)} values on the first pose line: neither "
                              "TUM (8: t tx ty tz qx qy qz qw) nor KITTI (12: 3x4 [R | t])",
                              line=line_no)
    raise FormatError(path, "no poses found (empty or only comments)")


def read_trajectory(path: PathLike, fmt: str = "auto") -> tuple[np.ndarray | None, np.ndarray]:
    """Read a TUM or KITTI trajectory: (timestamps (N,) or None for KITTI, (N, 4, 4) poses).

    ``fmt`` is ``'auto'`` (:func:`detect_trajectory_format`), ``'tum'`` or ``'kitti'``.
    An empty trajectory is a :class:`FormatError`.
    """
    if fmt == "auto":
        fmt = detect_trajectory_format(path)
    if fmt == "tum":
        stamps, poses_tum = read_tum_arrays(path)
        T = matrices_from_tum(poses_tum)
    elif fmt == "kitti":
        stamps, T = None, read_kitti_arrays(path)
    else:
        raise OctofactorError(f"unknown trajectory format {fmt!r} (use auto, tum or kitti)")
    if len(T) == 0:
        raise FormatError(path, f"no poses found in {fmt.upper()} trajectory")
    return stamps, T


__all__ = [
    "read_kitti_arrays", "write_kitti", "write_tum_arrays", "matrices_from_tum",
    "tum_from_matrices", "detect_trajectory_format", "read_trajectory", "TRAJECTORY_FORMATS",
]
