"""Vanishing-point EKF SLAM (Ji, Yamashita, Asama) on top of filterpy's ExtendedKalmanFilter.

State (eq. (5)-(7)), 9 entries, world frame:

    x = [x_S, y_S, z_S, psi_S, theta_S, phi_S | x_V, y_V, z_V]

The first six are the pose of the paper's body frame (x forward, y left, z up) in the
world, Euler angles in the convention of :mod:`estimation.geometry`
(R = Rz(phi) Ry(theta) Rx(psi)); the last three are the VP "point": the vanishing point
projected onto the environment at the known distance d. The camera (optical frame,
x right, y down, z forward) is rigidly attached: T_world_camera = T_world_body *
(R_BODY_CAMERA, 0), so ``T_world_sensor`` of the PoseGraph is T_world_camera.
P is the full 9x9 covariance with the blocks of eq. (8).

Prediction (eq. (9)-(10)) uses a visual-odometry increment T_prev_curr of the camera
with its 6x6 covariance in GTSAM order [rotation, translation] (right perturbation,
T_true = T_meas * Exp(xi)). The increment is moved to the body frame
(Ad of R_BODY_CAMERA), composed on the state (motion model g), and the covariance
becomes M = V Sigma V^T with V = dg/dxi (analytic, see :func:`motion_jacobians`).

Update (eq. (11)-(18)): the VP pixel predicted by the exact pinhole projection of the VP
point with the intrinsics K, Mahalanobis gating with a chi-square threshold, and
filterpy's update, which already uses the Joseph form
P = (I - KH) P (I - KH)^T + K R K^T (filterpy 2.0, ``ExtendedKalmanFilter.update``).

Beyond the paper: ``vp_model="manhattan"`` observes up to three Manhattan VPs as unit
directions in the camera, d_cam = R_camera_world R_world_manhattan e_i. The last three
state entries then hold the Manhattan frame's orientation instead of the VP point:
R_world_manhattan = Exp(delta) R0, delta = x[6:9], R0 fixed by the first frame with two
or more directions (so the frame is refined by every later detection, SLAM-style, instead
of inheriting the first detection's error).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from .errors import EstimationError
from .geometry import (
    R_BODY_CAMERA,
    euler_matrix_derivatives,
    euler_rate_matrix,
    euler_rate_matrix_inverse,
    euler_to_matrix,
    matrix_to_euler,
    wrap_angle,
)

STATE_DIM = 9
POS = slice(0, 3)
EULER = slice(3, 6)
VP = slice(6, 9)
POSE = slice(0, 6)

# Body-frame adjoint of the fixed camera mount (a pure rotation): xi_body = AD @ xi_camera.
_AD_BODY_CAMERA = np.block([[R_BODY_CAMERA, np.zeros((3, 3))],
                            [np.zeros((3, 3)), R_BODY_CAMERA]])


@dataclass(frozen=True)
class VpEkfConfig:
    """Parameters of :class:`VanishingPointEKF`.

    Attributes
    ----------
    vp_model : "point" (the paper, eq. (11)-(13)) or "manhattan" (up to three directions)
    vp_distance : d of eq. (12), metres from the camera along the first VP ray. Large d
        makes the VP point behave like a direction (a true VP is at infinity).
    vp_range_sigma : standard deviation (m) of d when the VP point is initialised
    vp_prior_sigma : standard deviation (m) of the VP block before initialisation
    gate_chi2 : threshold pi of eq. (15) on the squared Mahalanobis distance (2 dof)
    direction_sigma : rad, direction noise for a Manhattan VP without a pixel covariance
    manhattan_association_deg : largest angle between a predicted and a measured direction
        for them to be associated
    vo_failure_sigma : (rad, m) per-step standard deviations used when the odometry fails
    state : "error" (default): the error-state EKF on SE(3) x SO(3)
        (:class:`estimation.vp_eskf.VanishingPointESKF`), no singular pose; "euler": the
        paper's 9-D Euler state (this module), for reproducing the paper
    """

    vp_model: str = "point"
    vp_distance: float = 1000.0
    vp_range_sigma: float = 50.0
    vp_prior_sigma: float = 1.0e3
    gate_chi2: float = float(chi2.ppf(0.99, 2))
    direction_sigma: float = 0.01
    manhattan_association_deg: float = 10.0
    vo_failure_sigma: tuple[float, float] = (0.05, 0.15)
    state: str = "error"

    def __post_init__(self):
        if self.state not in ("error", "euler"):
            raise EstimationError(f"state must be 'error' or 'euler', got {self.state!r}")
        object.__setattr__(self, "vo_failure_sigma", tuple(float(v) for v in
                                                           self.vo_failure_sigma))
        if self.vp_model not in ("point", "manhattan"):
            raise EstimationError(f"vp_model must be 'point' or 'manhattan', got {self.vp_model!r}")
        if not self.vp_distance > 0:
            raise EstimationError(f"vp_distance must be positive, got {self.vp_distance}")


@dataclass(frozen=True)
class VpUpdate:
    """The outcome of one VP observation.

    status is "updated", "gated" (eq. (15) rejected it), "initialised" (the first
    detection created the VP state) or "skipped" (see reason); nis is the squared
    Mahalanobis distance of the innovation (nan when not computed).

    An accepted ("updated") observation of the error-state filter also says what it was, so
    that it can become a pose-graph direction factor: ``axis`` (the structure axis it was
    associated with), ``direction_sensor`` (unit, in the camera, signed like the axis),
    ``direction_cov`` (its 3x3 covariance in the camera, as the filter used it) and
    ``direction_world`` (the axis in the world as the filter predicted it, before this
    update). They are None otherwise.
    """

    status: str
    reason: str = ""
    nis: float = float("nan")
    innovation: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    S: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    axis: int | None = None
    direction_sensor: np.ndarray | None = None
    direction_cov: np.ndarray | None = None
    direction_world: np.ndarray | None = None


# --------------------------------------------------------------------------- models

def body_increment(R_prev_curr_cam: np.ndarray, t_prev_curr_cam: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(dR, dt) of the body frame for a camera increment T_prev_curr (camera frame)."""
    dR = R_BODY_CAMERA @ R_prev_curr_cam @ R_BODY_CAMERA.T
    dt = R_BODY_CAMERA @ np.asarray(t_prev_curr_cam, dtype=float).reshape(3)
    return dR, dt


def motion_model(x: np.ndarray, dR: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """The predicted state g(x, u) of eq. (9) for a body increment u = (dR, dt); (9,)."""
    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    R = euler_to_matrix(x[EULER])
    out = x.copy()
    out[POS] = x[POS] + R @ dt
    out[EULER] = matrix_to_euler(R @ dR)
    return out


def motion_jacobians(x: np.ndarray, dR: np.ndarray, dt: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(G, V): G = dg/dx (9, 9) of eq. (10) and V = dg/dxi (9, 6) for a body-frame
    increment perturbation xi = [omega, v] (GTSAM order, u_true = u * Exp(xi)).

    With E(e) the Euler-rate matrix (R(e + de) = Exp(E de) R(e)) and e' the predicted
    angles: d e'/d e = E(e')^-1 E(e), d t'/d e_k = (dR/de_k) dt, d e'/d omega =
    E(e')^-1 R', d t'/d v = R'.
    """
    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    e = x[EULER]
    R = euler_to_matrix(e)
    R_new = R @ dR
    e_new = matrix_to_euler(R_new)
    E_new_inv = euler_rate_matrix_inverse(e_new)
    D = euler_matrix_derivatives(e)
    G = np.eye(STATE_DIM)
    G[POS, EULER] = np.einsum("kij,j->ik", D, dt)
    G[EULER, EULER] = E_new_inv @ euler_rate_matrix(e)
    V = np.zeros((STATE_DIM, 6))
    V[POS, 3:6] = R_new
    V[EULER, 0:3] = E_new_inv @ R_new
    return G, V


def camera_rotation(x: np.ndarray) -> np.ndarray:
    """R_world_camera (3, 3) of the state."""
    return euler_to_matrix(np.asarray(x, dtype=float).reshape(-1)[EULER]) @ R_BODY_CAMERA


def vp_point_camera(x: np.ndarray) -> np.ndarray:
    """The VP point in the camera frame, (3,)."""
    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    return camera_rotation(x).T @ (x[VP] - x[POS])


def vp_point_observation(x: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The predicted VP pixel h(x) = (u, v) of eq. (11)-(12), (2,).

    Eq. (12) in the paper approximates the depth by d - x_S and uses rows 2:3 of R^-1
    with axes y left / z up; we use the exact pinhole projection of the VP point into the
    camera (x right, y down, z forward), which reduces to eq. (12) for R = I
    (u = c_u + f (y_S - y_V) / (d - x_S), v = c_v - f (z_V - z_S) / (d - x_S), image v down).
    """
    q = np.asarray(K, dtype=float) @ vp_point_camera(x)
    return q[:2] / q[2]


def vp_point_jacobian(x: np.ndarray, K: np.ndarray) -> np.ndarray:
    """H = dh/dx (2, 9) of :func:`vp_point_observation` (analytic)."""
    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    K = np.asarray(K, dtype=float)
    R_wc = camera_rotation(x)
    diff = x[VP] - x[POS]
    q = K @ (R_wc.T @ diff)
    dz_dq = np.array([[1.0 / q[2], 0.0, -q[0] / q[2] ** 2],
                      [0.0, 1.0 / q[2], -q[1] / q[2] ** 2]])
    D = euler_matrix_derivatives(x[EULER])
    dp_dx = np.zeros((3, STATE_DIM))
    dp_dx[:, POS] = -R_wc.T
    # d(R_bc^T R^T diff)/de_k = R_bc^T (dR/de_k)^T diff
    dp_dx[:, EULER] = R_BODY_CAMERA.T @ np.einsum("kji,j->ik", D, diff)
    dp_dx[:, VP] = R_wc.T
    return dz_dq @ K @ dp_dx


def direction_observation(x: np.ndarray, direction_world: np.ndarray) -> np.ndarray:
    """The unit direction in the camera, R_camera_world @ w, (3,)."""
    return camera_rotation(x).T @ np.asarray(direction_world, dtype=float)


def direction_jacobian(x: np.ndarray, direction_world: np.ndarray) -> np.ndarray:
    """d(R_camera_world w)/dx (3, 9) for a fixed world direction w (Euler columns only)."""
    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    D = euler_matrix_derivatives(x[EULER])
    J = np.zeros((3, STATE_DIM))
    J[:, EULER] = R_BODY_CAMERA.T @ np.einsum("kji,j->ik", D, np.asarray(direction_world, float))
    return J


def manhattan_rotation(x: np.ndarray, R_world_manhattan0: np.ndarray) -> np.ndarray:
    """R_world_manhattan = Exp(delta) R0 with delta = x[6:9] (manhattan model)."""
    import gtsam

    delta = np.asarray(x, dtype=float).reshape(STATE_DIM)[VP]
    return gtsam.Rot3.Expmap(delta).matrix() @ R_world_manhattan0


def manhattan_observation(x: np.ndarray, R_world_manhattan0: np.ndarray, axis: int
                          ) -> np.ndarray:
    """Manhattan axis ``axis`` seen from the camera: R_camera_world Exp(delta) R0 e_axis, (3,)."""
    return direction_observation(x, manhattan_rotation(x, R_world_manhattan0)[:, axis])


def manhattan_jacobian(x: np.ndarray, R_world_manhattan0: np.ndarray, axis: int) -> np.ndarray:
    """d manhattan_observation / dx (3, 9), analytic.

    d(Exp(delta) v)/d delta = -Exp(delta) [v]x Jr(delta) (Jr: SO(3) right Jacobian).
    """
    import gtsam

    x = np.asarray(x, dtype=float).reshape(STATE_DIM)
    R_delta = gtsam.Rot3.Expmap(x[VP]).matrix()
    v = R_world_manhattan0[:, axis]
    w = R_delta @ v
    J = direction_jacobian(x, w)
    J[:, VP] = -camera_rotation(x).T @ R_delta @ skew(v) @ gtsam.Rot3.ExpmapDerivative(x[VP])
    return J


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x, the (3, 3) cross-product matrix."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def tangent_from_state_jacobian(x: np.ndarray) -> np.ndarray:
    """J (6, 6) mapping a state pose error [dpos, deuler] to the camera's GTSAM tangent
    [omega, v] (T_true = T_world_camera * Exp(xi))."""
    x = np.asarray(x, dtype=float).reshape(-1)
    R_wc = camera_rotation(x)
    J = np.zeros((6, 6))
    J[0:3, 3:6] = R_wc.T @ euler_rate_matrix(x[EULER])
    J[3:6, 0:3] = R_wc.T
    return J


def state_from_tangent_jacobian(x: np.ndarray) -> np.ndarray:
    """The inverse of :func:`tangent_from_state_jacobian`."""
    x = np.asarray(x, dtype=float).reshape(-1)
    R_wc = camera_rotation(x)
    J = np.zeros((6, 6))
    J[0:3, 3:6] = R_wc
    J[3:6, 0:3] = euler_rate_matrix_inverse(x[EULER]) @ R_wc
    return J


def pixel_ray(uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, dn_duv): the unit camera ray through pixel uv and its (3, 2) Jacobian."""
    K_inv = np.linalg.inv(np.asarray(K, dtype=float))
    r = K_inv @ np.array([uv[0], uv[1], 1.0])
    norm = np.linalg.norm(r)
    n = r / norm
    dn_duv = (np.eye(3) - np.outer(n, n)) / norm @ K_inv[:, :2]
    return n, dn_duv


def tangent_basis(d: np.ndarray) -> np.ndarray:
    """An orthonormal (3, 2) basis of the plane perpendicular to unit vector d."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(d, helper)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(d, b1)])


def unit_directions(directions) -> tuple[np.ndarray, np.ndarray]:
    """(directions normalised (k, 3), good (k,) bool): rows with a finite non-zero norm."""
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    norms = np.linalg.norm(directions, axis=1)
    good = np.isfinite(norms) & (norms > 1e-9)
    return np.where(good[:, None], directions / np.where(good, norms, 1.0)[:, None], 0.0), good


def frame_from_two_directions(directions: np.ndarray, idx: np.ndarray) -> np.ndarray | None:
    """The nearest orthonormal frame (3, 3; columns in the camera) to the first direction of
    ``idx`` and the next one at least 60 degrees from it; None without such a pair."""
    first = directions[idx[0]]
    second = next((directions[j] for j in idx[1:]
                   if abs(directions[j] @ first) < np.cos(np.deg2rad(60.0))), None)
    if second is None:
        return None
    second = second - (second @ first) * first
    second /= np.linalg.norm(second)
    return np.column_stack([first, second, np.cross(first, second)])


def associate_axis(predicted: np.ndarray, direction: np.ndarray, used: set[int],
                   max_angle_deg: float) -> tuple[int, np.ndarray] | None:
    """(axis, signed direction): the nearest predicted axis (rows of ``predicted``, camera
    frame) not yet ``used``, within ``max_angle_deg`` sign-free (VPs have no sign); None."""
    cosines = predicted @ direction
    cos_assoc = np.cos(np.deg2rad(max_angle_deg))
    axis = next((int(j) for j in np.argsort(-np.abs(cosines))
                 if int(j) not in used and abs(cosines[j]) >= cos_assoc), None)
    if axis is None:
        return None
    return axis, (direction if cosines[axis] > 0 else -direction)


def pixel_covariance(cov_uv) -> np.ndarray:
    """A VP pixel covariance as a symmetric (2, 2) array; EstimationError unless finite and
    positive definite."""
    Q = np.asarray(cov_uv, dtype=float).reshape(2, 2)
    Q = 0.5 * (Q + Q.T)
    if not np.all(np.isfinite(Q)) or np.linalg.eigvalsh(Q)[0] <= 0:
        raise EstimationError("VP pixel covariance must be finite and positive definite")
    return Q


def direction_covariance(K: np.ndarray, uv=None, cov_uv=None, direction_cov=None,
                         sigma: float = 0.01, floor: float = 1e-8) -> np.ndarray:
    """The (3, 3) covariance of a unit direction in the camera: ``direction_cov`` as given,
    else propagated from the pixel ``uv`` and its ``cov_uv``, else ``sigma`` isotropic.
    ``floor`` (rad^2) keeps it positive definite."""
    if direction_cov is not None:
        C = np.asarray(direction_cov, dtype=float).reshape(3, 3)
        if not np.all(np.isfinite(C)):
            raise EstimationError("direction covariance must be finite")
        return 0.5 * (C + C.T) + floor * np.eye(3)
    if uv is not None and cov_uv is not None and np.all(np.isfinite(uv)):
        _, dn_duv = pixel_ray(np.asarray(uv, dtype=float), K)
        return dn_duv @ pixel_covariance(cov_uv) @ dn_duv.T + floor * np.eye(3)
    return sigma ** 2 * np.eye(3)


def checked_camera_matrix(K, what: str = "K") -> np.ndarray:
    """K as a (3, 3) float array; EstimationError naming ``what`` unless it is a finite pinhole
    matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0."""
    try:
        K = np.array(K, dtype=float)
    except (TypeError, ValueError):
        raise EstimationError(f"{what} must be a 3x3 camera matrix of numbers") from None
    if K.shape != (3, 3):
        raise EstimationError(f"{what} must be a 3x3 camera matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise EstimationError(f"{what} has NaN or inf entries")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise EstimationError(f"{what} must have fx = K[0, 0] > 0, fy = K[1, 1] > 0 and last row "
                              f"[0, 0, 1], got fx={K[0, 0]}, fy={K[1, 1]}, last row "
                              f"{K[2].tolist()}")
    return K


def checked_covariance(P: np.ndarray, what: str, semidefinite: bool = False) -> np.ndarray:
    """P symmetrised; EstimationError when it is not finite or not positive definite
    (``semidefinite``: not positive semi-definite, up to round-off; a state with a cloned
    block is singular by construction)."""
    P = 0.5 * (P + P.T)
    if not np.all(np.isfinite(P)):
        raise EstimationError(f"{what} covariance has NaN or inf entries")
    if semidefinite:
        values = np.linalg.eigvalsh(P)
        if values[0] < -1e-9 * max(values[-1], 1e-300):
            raise EstimationError(f"{what} covariance lost positive semi-definiteness")
        return P
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise EstimationError(f"{what} covariance lost positive definiteness") from None
    return P


@dataclass(frozen=True)
class VpPointInit:
    """The VP point back-projected from a pixel, with its Jacobians."""

    point: np.ndarray      # (3,) world
    ray_world: np.ndarray  # (3,) unit ray in the world
    J_pose: np.ndarray     # (3, 6) d point / d [pos, euler]
    J_uv: np.ndarray       # (3, 2) d point / d (u, v)


def vp_point_from_pixel(x: np.ndarray, uv: np.ndarray, K: np.ndarray, distance: float
                        ) -> VpPointInit:
    """The VP point at range ``distance`` along the ray through ``uv`` from the camera of x."""
    x = np.asarray(x, dtype=float).reshape(-1)
    n, dn_duv = pixel_ray(uv, K)
    R_wc = camera_rotation(x)
    ray_world = R_wc @ n
    D = euler_matrix_derivatives(x[EULER])
    J_pose = np.zeros((3, 6))
    J_pose[:, 0:3] = np.eye(3)
    J_pose[:, 3:6] = distance * np.einsum("kij,j->ik", D, R_BODY_CAMERA @ n)
    return VpPointInit(x[POS] + distance * ray_world, ray_world, J_pose,
                       distance * R_wc @ dn_duv)


# --------------------------------------------------------------------------- filter

class VanishingPointEKF(ExtendedKalmanFilter):
    """The VP-EKF SLAM filter of Ji, Yamashita, Asama (filterpy ExtendedKalmanFilter).

    Parameters
    ----------
    K : (3, 3) camera intrinsics
    T_world_camera : gtsam.Pose3 or (4, 4), the initial camera pose; None puts the BODY
        frame at the identity (camera looking along world x, image up = world z)
    cov_pose : (6, 6) initial pose covariance, GTSAM tangent [rot, trans] of the camera
    config : VpEkfConfig

    Attributes
    ----------
    x : (9, 1) state, eq. (5)-(7)
    P : (9, 9) covariance, eq. (8)
    F : the last motion Jacobian G of eq. (10)
    Q : the last process noise M of eq. (10)
    R : the last measurement noise (the paper's Q, eq. (14))
    K, y, S : gain, innovation and innovation covariance of the last update
    manhattan_R0 : (3, 3) R_world_manhattan at initialisation (manhattan model), else None;
        x[6:9] then holds the rotation-vector correction delta of the Manhattan frame
    """

    def __init__(self, K: np.ndarray, T_world_camera=None, cov_pose: np.ndarray | None = None,
                 config: VpEkfConfig = VpEkfConfig()):
        super().__init__(dim_x=STATE_DIM, dim_z=2)
        self.config = config
        self.K_cam = checked_camera_matrix(K)
        if T_world_camera is None:
            # The paper's convention: the body frame at the world origin (world x forward,
            # z up), i.e. the camera looks along world x. (An identity CAMERA pose would put
            # the body's pitch at -90 deg, the gimbal lock of the Euler state.)
            M = np.eye(4)
            M[:3, :3] = R_BODY_CAMERA
        else:
            M = T_world_camera.matrix() if hasattr(T_world_camera, "matrix") else np.asarray(
                T_world_camera, dtype=float)
        R_wb = M[:3, :3] @ R_BODY_CAMERA.T
        x = np.zeros(STATE_DIM)
        x[POS] = M[:3, 3]
        x[EULER] = matrix_to_euler(R_wb)
        self.x = x.reshape(-1, 1)
        cov_pose = np.diag([1e-8] * 3 + [1e-8] * 3) if cov_pose is None else np.asarray(
            cov_pose, dtype=float)
        if cov_pose.shape != (6, 6) or not np.all(np.isfinite(cov_pose)):
            raise EstimationError(f"cov_pose must be a finite 6x6 matrix, got shape "
                                  f"{cov_pose.shape}")
        J = state_from_tangent_jacobian(x)
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[POSE, POSE] = J @ cov_pose @ J.T
        P[VP, VP] = np.eye(3) * config.vp_prior_sigma ** 2
        self.P = P
        self._finish_step()
        self.vp_initialised = False
        self.manhattan_R0: np.ndarray | None = None

    # ------------------------------------------------------------------ accessors
    @property
    def state(self) -> np.ndarray:
        """The state as a flat (9,) copy."""
        return self.x.reshape(-1).copy()

    @property
    def T_world_camera(self):
        """The camera pose as a gtsam.Pose3."""
        import gtsam

        x = self.x.reshape(-1)
        return gtsam.Pose3(gtsam.Rot3(camera_rotation(x)), x[POS].copy())

    def pose_covariance(self) -> np.ndarray:
        """The camera pose marginal (6, 6) in GTSAM tangent order [rot, trans]."""
        J = tangent_from_state_jacobian(self.x)
        cov = J @ self.P[POSE, POSE] @ J.T
        return 0.5 * (cov + cov.T)

    # ------------------------------------------------------------------ prediction
    def predict_x(self, u=0):
        """The motion model g of eq. (9); ``u`` is a body increment (dR, dt)."""
        dR, dt = u
        self.x = motion_model(self.x, dR, dt).reshape(-1, 1)

    def predict_vo(self, T_prev_curr, cov: np.ndarray) -> None:
        """Predict with a camera-frame VO increment and its (6, 6) [rot, trans] covariance."""
        M = T_prev_curr.matrix() if hasattr(T_prev_curr, "matrix") else np.asarray(
            T_prev_curr, dtype=float)
        cov = np.asarray(cov, dtype=float)
        if cov.shape != (6, 6) or not np.all(np.isfinite(cov)) or not np.all(np.isfinite(M)):
            raise EstimationError("VO increment or its covariance is not finite / not 6x6")
        dR, dt = body_increment(M[:3, :3], M[:3, 3])
        G, V = motion_jacobians(self.x, dR, dt)
        V = V @ _AD_BODY_CAMERA
        self.F = G
        self.Q = V @ cov @ V.T  # M of eq. (10)
        self.predict(u=(dR, dt))
        self._finish_step()

    def predict_lost(self, sigma: tuple[float, float] | None = None) -> None:
        """Predict without odometry (VO failed / frame missing): zero motion, inflated P."""
        s_rot, s_trans = self.config.vo_failure_sigma if sigma is None else sigma
        cov = np.diag([s_rot ** 2] * 3 + [s_trans ** 2] * 3)
        self.predict_vo(np.eye(4), cov)

    # ------------------------------------------------------------------ updates
    def update_vp(self, uv, cov_uv: np.ndarray) -> VpUpdate:
        """Paper's update (eq. (14)-(18)) from a VP pixel ``uv`` with (2, 2) covariance.

        The first detection initialises the VP point (back-projection at range d).
        """
        if uv is None or not np.all(np.isfinite(uv)):
            return VpUpdate("skipped", "vp_at_infinity")
        uv = np.asarray(uv, dtype=float).reshape(2)
        Q = self._measurement_cov(cov_uv)
        if not self.vp_initialised:
            self._initialise_vp_point(uv, Q)
            return VpUpdate("initialised")
        x = self.x.reshape(-1)
        if vp_point_camera(x)[2] <= 1e-6:
            return VpUpdate("skipped", "vp_behind_camera")
        K = self.K_cam
        return self._gated_update(uv, lambda s: vp_point_jacobian(s, K),
                                  lambda s: vp_point_observation(s, K), Q)

    def update_directions(self, directions: np.ndarray, uvs=None, covs=None) -> list[VpUpdate]:
        """Manhattan update from up to three unit directions in the camera, (k, 3).

        The Manhattan frame's orientation in the world is part of the state: x[6:9] = delta
        with R_world_manhattan = Exp(delta) R0. The first frame with at least two directions
        fixes R0 (from the estimated camera rotation) and initialises delta = 0 with the
        camera's rotation covariance (and its cross-covariances) plus the detection noise;
        later directions are associated with the nearest axis and update the filter.
        ``uvs`` / ``covs`` (optional, per direction) give the pixel and its covariance, from
        which the direction noise is propagated; otherwise ``config.direction_sigma`` is used.
        """
        directions, good = unit_directions(directions)
        k = len(directions)
        uvs = [None] * k if uvs is None else list(uvs)
        covs = [None] * k if covs is None else list(covs)
        outcomes = [VpUpdate("skipped", "bad_direction") for _ in range(k)]
        if not good.any():
            return outcomes
        if self.manhattan_R0 is None:
            return self._initialise_manhattan(directions, good, uvs, covs, outcomes)
        used: set[int] = set()
        for i in np.flatnonzero(good):
            x = self.x.reshape(-1)
            R0 = self.manhattan_R0
            predicted = (camera_rotation(x).T @ manhattan_rotation(x, R0)).T  # rows: axes in cam
            match = associate_axis(predicted, directions[i], used,
                                   self.config.manhattan_association_deg)
            if match is None:
                outcomes[i] = VpUpdate("skipped", "no_association")
                continue
            axis, d_meas = match
            used.add(axis)
            B = tangent_basis(predicted[axis])
            Q = B.T @ self._direction_cov(uvs[i], covs[i]) @ B
            outcomes[i] = self._gated_update(
                B.T @ d_meas, lambda s, a=axis, B=B, R0=R0: B.T @ manhattan_jacobian(s, R0, a),
                lambda s, a=axis, B=B, R0=R0: B.T @ manhattan_observation(s, R0, a), Q)
        return outcomes

    @property
    def world_directions(self) -> np.ndarray:
        """(3, 3) rows: the Manhattan axes in the world ((0, 3) before initialisation)."""
        if self.manhattan_R0 is None:
            return np.zeros((0, 3))
        return manhattan_rotation(self.x, self.manhattan_R0).T

    # ------------------------------------------------------------------ internals
    def _gated_update(self, z: np.ndarray, HJacobian, Hx, Q: np.ndarray) -> VpUpdate:
        H = HJacobian(self.x.reshape(-1))
        S = H @ self.P @ H.T + Q  # eq. (14)
        innovation = z - Hx(self.x.reshape(-1))
        try:
            nis = float(innovation @ np.linalg.solve(S, innovation))
        except np.linalg.LinAlgError:
            return VpUpdate("skipped", "singular_S")
        if not np.isfinite(nis):
            return VpUpdate("skipped", "non_finite_innovation")
        if nis > self.config.gate_chi2:  # eq. (15)
            return VpUpdate("gated", "mahalanobis", nis, innovation, S)
        # filterpy 2.0 needs z as a (2, 1) column: a flat (2,) broadcasts and corrupts x.
        self.update(z.reshape(2, 1), lambda s: HJacobian(s.reshape(-1)),
                    lambda s: Hx(s.reshape(-1)).reshape(2, 1), R=Q)  # eq. (16)-(18), Joseph form
        self._finish_step()
        return VpUpdate("updated", "", nis, innovation, S)

    def _initialise_vp_point(self, uv: np.ndarray, Q: np.ndarray) -> None:
        x = self.x.reshape(-1)
        init = vp_point_from_pixel(x, uv, self.K_cam, self.config.vp_distance)
        P = self.P
        P_SS = P[POSE, POSE]
        ray = init.ray_world
        P[VP, VP] = (init.J_pose @ P_SS @ init.J_pose.T + init.J_uv @ Q @ init.J_uv.T
                     + self.config.vp_range_sigma ** 2 * np.outer(ray, ray))
        P[VP, POSE] = init.J_pose @ P_SS
        P[POSE, VP] = P[VP, POSE].T
        self.P = P
        x = x.copy()
        x[VP] = init.point
        self.x = x.reshape(-1, 1)
        self.vp_initialised = True
        self._finish_step()

    def _initialise_manhattan(self, directions, good, uvs, covs, outcomes) -> list[VpUpdate]:
        idx = np.flatnonzero(good)
        if len(idx) < 2:
            outcomes[idx[0]] = VpUpdate("skipped", "manhattan_needs_two_directions")
            return outcomes
        M_camera = frame_from_two_directions(directions, idx)
        if M_camera is None:
            outcomes[idx[0]] = VpUpdate("skipped", "manhattan_needs_two_directions")
            return outcomes
        x = self.x.reshape(-1)
        self.manhattan_R0 = camera_rotation(x) @ M_camera
        # delta = 0 carries the camera's world-rotation error (E de) and the detection noise.
        E = euler_rate_matrix(x[EULER])
        noise = max(float(np.trace(self._direction_cov(uvs[j], covs[j]))) / 2 for j in idx)
        P = self.P
        P[VP, :] = 0.0
        P[:, VP] = 0.0
        P[VP, POSE] = E @ P[EULER, POSE]
        P[POSE, VP] = P[VP, POSE].T
        P[VP, VP] = E @ P[EULER, EULER] @ E.T + noise * np.eye(3)
        self.P = P
        x = x.copy()
        x[VP] = 0.0
        self.x = x.reshape(-1, 1)
        self._finish_step()
        for j in idx:
            outcomes[j] = VpUpdate("initialised")
        return outcomes

    def _measurement_cov(self, cov_uv) -> np.ndarray:
        return pixel_covariance(cov_uv)

    def _direction_cov(self, uv, cov) -> np.ndarray:
        # floor: a pixel covariance alone says nothing about the detector's model error
        return direction_covariance(self.K_cam, uv, cov, sigma=self.config.direction_sigma)

    def _finish_step(self) -> None:
        """Wrap the angles, symmetrise P and check that it is positive definite."""
        x = self.x.reshape(-1).copy()
        x[EULER] = wrap_angle(x[EULER])
        self.x = x.reshape(-1, 1)
        self.P = checked_covariance(self.P, "EKF")
