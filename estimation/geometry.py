"""Rotation conventions of the seed papers, angle wrapping and the SE(3) distance.

Euler convention (Ji, Yamashita, Asama, eq. (6) and (13))
---------------------------------------------------------
A state holds three angles in the order ``(psi, theta, phi)``:

* ``psi``   -- roll, about the x axis,
* ``theta`` -- pitch, about the y axis,
* ``phi``   -- yaw, about the z axis,

and the rotation matrix is the product of rotations about FIXED axes

    R = Rz(phi) @ Ry(theta) @ Rx(psi)

i.e. extrinsic X-Y-Z (first roll about world x, then pitch about world y, then yaw
about world z), which equals intrinsic Z-Y'-X'' (yaw-pitch-roll, aerospace). Eq. (13)
of the paper is exactly this matrix (its printed list of sines and cosines is garbled:
it should read s_psi = sin psi, s_theta = sin theta, s_phi = sin phi, c_* likewise).
It is gtsam's ``Rot3.Ypr(phi, theta, psi)`` and scipy's ``Rotation.from_euler("ZYX",
[phi, theta, psi])``. The representation is singular at theta = +-pi/2 (gimbal lock).

``R`` maps coordinates in the rotated frame to the reference frame: for a pose
``T_world_body`` it is ``R_world_body``.

The paper's body frame (its "sensor" frame) is x forward, y left, z up; the camera
optical frame is x right, y down, z forward; :data:`R_BODY_CAMERA` converts between them.
"""
from __future__ import annotations

import numpy as np

# Columns: the camera's x (right), y (down), z (forward) axes in the paper's body frame
# (x forward, y left, z up). T_world_camera = T_world_body * (R_BODY_CAMERA, 0).
R_BODY_CAMERA = np.array([[0.0, 0.0, 1.0],
                          [-1.0, 0.0, 0.0],
                          [0.0, -1.0, 0.0]])

_GIMBAL_EPS = 1e-9


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Angles wrapped to the interval [-pi, pi) (elementwise; scalars stay scalars)."""
    wrapped = np.mod(np.asarray(angle, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def euler_to_matrix(euler: np.ndarray) -> np.ndarray:
    """Rotation matrices R = Rz(phi) Ry(theta) Rx(psi) for ``euler = (psi, theta, phi)``.

    ``euler`` is (3,) or (..., 3); the result is (3, 3) or (..., 3, 3). Eq. (13).
    """
    euler = np.asarray(euler, dtype=float)
    psi, theta, phi = euler[..., 0], euler[..., 1], euler[..., 2]
    cps, sps = np.cos(psi), np.sin(psi)
    cth, sth = np.cos(theta), np.sin(theta)
    cph, sph = np.cos(phi), np.sin(phi)
    R = np.empty(euler.shape[:-1] + (3, 3))
    R[..., 0, 0] = cph * cth
    R[..., 0, 1] = cph * sth * sps - sph * cps
    R[..., 0, 2] = cph * sth * cps + sph * sps
    R[..., 1, 0] = sph * cth
    R[..., 1, 1] = sph * sth * sps + cph * cps
    R[..., 1, 2] = sph * sth * cps - cph * sps
    R[..., 2, 0] = -sth
    R[..., 2, 1] = cth * sps
    R[..., 2, 2] = cth * cps
    return R


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """Euler angles ``(psi, theta, phi)`` with R = Rz(phi) Ry(theta) Rx(psi).

    ``R`` is (3, 3) or (..., 3, 3). theta is in [-pi/2, pi/2], psi and phi in [-pi, pi].
    At gimbal lock (cos theta = 0) only psi -+ phi is defined: psi is set to 0.
    """
    R = np.asarray(R, dtype=float)
    sin_theta = np.clip(-R[..., 2, 0], -1.0, 1.0)
    theta = np.arcsin(sin_theta)
    cos_theta = np.hypot(R[..., 0, 0], R[..., 1, 0])
    regular = cos_theta > _GIMBAL_EPS
    psi = np.where(regular, np.arctan2(R[..., 2, 1], R[..., 2, 2]), 0.0)
    phi = np.where(regular, np.arctan2(R[..., 1, 0], R[..., 0, 0]),
                   np.arctan2(-R[..., 0, 1], R[..., 1, 1]))
    # Recompute theta with atan2 for accuracy near +-pi/2.
    theta = np.arctan2(-R[..., 2, 0], cos_theta)
    return np.stack([psi, theta, phi], axis=-1)


def euler_matrix_derivatives(euler: np.ndarray) -> np.ndarray:
    """The three (3, 3) derivatives dR/dpsi, dR/dtheta, dR/dphi stacked as (3, 3, 3)."""
    psi, theta, phi = (float(a) for a in np.asarray(euler, dtype=float))
    Rx, Ry, Rz = _rx(psi), _ry(theta), _rz(phi)
    return np.stack([Rz @ Ry @ (_hat(np.array([1.0, 0.0, 0.0])) @ Rx),
                     Rz @ (_hat(np.array([0.0, 1.0, 0.0])) @ Ry) @ Rx,
                     (_hat(np.array([0.0, 0.0, 1.0])) @ Rz) @ Ry @ Rx])


def euler_rate_matrix(euler: np.ndarray) -> np.ndarray:
    """The (3, 3) matrix E with omega_world = E @ d(psi, theta, phi)/dt.

    Equivalently R(e + de) = Exp(E de) R(e) to first order: a small change of the
    Euler angles is a rotation E de applied on the LEFT (in the reference frame).
    """
    _, theta, phi = (float(a) for a in np.asarray(euler, dtype=float))
    cth, sth = np.cos(theta), np.sin(theta)
    cph, sph = np.cos(phi), np.sin(phi)
    return np.array([[cph * cth, -sph, 0.0],
                     [sph * cth, cph, 0.0],
                     [-sth, 0.0, 1.0]])


def euler_rate_matrix_inverse(euler: np.ndarray) -> np.ndarray:
    """The inverse of :func:`euler_rate_matrix` (raises EstimationError at gimbal lock)."""
    _, theta, phi = (float(a) for a in np.asarray(euler, dtype=float))
    cth, sth = np.cos(theta), np.sin(theta)
    if abs(cth) < 1e-6:
        from estimation.errors import EstimationError
        raise EstimationError(f"Euler angles at gimbal lock (theta = {theta:.6f} rad)")
    cph, sph = np.cos(phi), np.sin(phi)
    return np.array([[cph / cth, sph / cth, 0.0],
                     [-sph, cph, 0.0],
                     [cph * sth / cth, sph * sth / cth, 1.0]])


def d_se3(T_est, T_gt) -> float:
    """The SE(3) distance ||Logmap(T_est * T_gt^-1)|| (radians and metres mixed, GTSAM order).

    ``T_est`` and ``T_gt`` are gtsam.Pose3 (or 4x4 matrices).
    """
    import gtsam

    T_est = _as_pose3(T_est)
    T_gt = _as_pose3(T_gt)
    return float(np.linalg.norm(gtsam.Pose3.Logmap(T_est.compose(T_gt.inverse()))))


def pose3_from_euler(position: np.ndarray, euler: np.ndarray):
    """The gtsam.Pose3 with translation ``position`` and rotation ``euler_to_matrix(euler)``."""
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(euler_to_matrix(euler)),
                       np.asarray(position, dtype=float).reshape(3))


def euler_from_pose3(pose) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), euler (3,)) of a gtsam.Pose3 in this module's convention."""
    pose = _as_pose3(pose)
    return np.asarray(pose.translation(), dtype=float), matrix_to_euler(pose.rotation().matrix())


def _as_pose3(T):
    import gtsam

    if isinstance(T, gtsam.Pose3):
        return T
    return gtsam.Pose3(np.asarray(T, dtype=float))


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
