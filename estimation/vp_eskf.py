"""Error-state (multiplicative) EKF on SE(3) x SO(3) for vanishing-point SLAM, on filterpy.

The default filter of ``octofactor vpslam``. It estimates the same things as the paper's 9-D
Euler filter (:mod:`estimation.vp_ekf`) -- the camera pose and the structure's vanishing
directions -- but with no parametrisation singularity that an ordinary pose can reach:

* nominal state: ``T_world_camera`` (gtsam.Pose3) and ``R_world_manhattan`` (3x3, the
  structure's frame; its columns are the world directions of the vanishing points);
* error state ``x`` (15,): ``[omega, v | delta | omega_k, v_k]`` with
  ``T_world_camera = T_hat * Exp([omega, v])`` (GTSAM's right perturbation, tangent order
  [rotation, translation]), ``R_world_manhattan = R_hat * Exp(delta)`` and the same for
  ``T_world_keyframe``, a clone of the camera pose at the last keyframe (stochastic cloning,
  Roumeliotis & Burdick, ICRA 2002);
* ``P`` (15x15) is the covariance of ``x``; its top-left 6x6 block *is* the camera pose
  covariance in GTSAM's convention, no Jacobian needed.

filterpy's :class:`~filterpy.kalman.ExtendedKalmanFilter` does the algebra: ``predict``
(P = F P F^T + Q) and ``update`` (gain, Joseph-form P). ``x`` is zero between steps: after an
update the correction ``x`` is injected into the nominal state and reset to zero (the reset
Jacobian is the identity to first order, as in Sola, "Quaternion kinematics for the
error-state Kalman filter", 2017, sec. 6.3).

Prediction with a VO increment ``U = T_prev_curr`` (right-perturbation covariance
``Sigma_U``): ``T' = T U``, so ``xi' = Ad(U^-1) xi + eta`` and ``F = diag(Ad(U^-1), I3)``,
``Q = diag(Sigma_U, 0)``. The structure does not move (no process noise on ``delta``).

Prediction from the keyframe (``predict_from_keyframe``) with an increment
``U = T_keyframe_curr`` measured against the keyframe's image: ``T' = T_k U``, so
``xi' = Ad(U^-1) xi_k + eta``: the camera's rows of ``F`` take the keyframe's block, and the
camera's old error is dropped; what the updates since the keyframe taught it has already
reached the keyframe clone through their cross-covariance. Odometry against a keyframe does
not accumulate the frame-to-frame errors between keyframes (``set_keyframe`` clones the
current pose: its block and cross-covariances are copied).

Observation of Manhattan axis ``i`` as a unit direction in the camera:
``d = R_camera_world R_world_manhattan e_i``. With both right perturbations,
``d ~ d_hat + [d_hat]x omega - R_camera_manhattan [e_i]x delta``; the residual is taken in a
2-D tangent basis ``B`` of ``d_hat`` (a direction has two degrees of freedom). Each direction
is gated on its Mahalanobis distance (chi-square, 2 dof) and the gated ones are counted,
never forced in by inflating P.

Re-anchoring the world (``reanchor``: ``T_new_old`` applied on the left of both nominal
rotations) leaves ``x`` and ``P`` unchanged, because both perturbations are on the right.
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from .errors import EstimationError
from .vp_ekf import (
    VpEkfConfig,
    VpUpdate,
    associate_axis,
    checked_camera_matrix,
    checked_covariance,
    direction_covariance,
    frame_from_two_directions,
    pixel_covariance,
    pixel_ray,
    skew,
    tangent_basis,
    unit_directions,
)

STATE_DIM = 15
POSE = slice(0, 6)
ROT = slice(0, 3)
MANHATTAN = slice(6, 9)
KEYFRAME = slice(9, 15)
_DEFAULT_CONFIG = VpEkfConfig(vp_model="manhattan")


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Exp of a rotation vector (Rodrigues), (3, 3)."""
    import gtsam

    return gtsam.Rot3.Expmap(np.asarray(w, dtype=float).reshape(3)).matrix()


def as_pose3(T, what: str = "pose"):
    """A gtsam.Pose3 from a Pose3 or a (4, 4) array: :func:`estimation.pose_graph.as_pose3`
    (imported when first needed: gtsam is heavy)."""
    from .pose_graph import as_pose3 as checked_pose3

    return checked_pose3(T, what)


def _vo_noise(cov: np.ndarray) -> np.ndarray:
    """Q: the (6, 6) increment covariance on the camera pose rows, checked and symmetrised."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        raise EstimationError("VO covariance must be a finite 6x6 matrix")
    Q = np.zeros((STATE_DIM, STATE_DIM))
    Q[POSE, POSE] = 0.5 * (cov + cov.T)
    return Q


def axis_jacobians(R_world_camera: np.ndarray, R_world_manhattan: np.ndarray, axis: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(d_hat (3,), H (3, 9)): axis ``axis`` of the structure seen from the camera and its
    Jacobian with respect to the error state [omega, v, delta]."""
    R_cm = R_world_camera.T @ R_world_manhattan
    d = R_cm[:, axis]
    H = np.zeros((3, STATE_DIM))
    H[:, ROT] = skew(d)
    e = np.zeros(3)
    e[axis] = 1.0
    H[:, MANHATTAN] = -R_cm @ skew(e)
    return d, H


class VanishingPointESKF(ExtendedKalmanFilter):
    """Error-state EKF of the camera pose and the structure's vanishing directions.

    Parameters
    ----------
    K : (3, 3) camera intrinsics
    T_world_camera : gtsam.Pose3 or (4, 4), the initial camera pose; None: the identity
    cov_pose : (6, 6) initial pose covariance, GTSAM tangent [rotation, translation]
    config : VpEkfConfig (``vp_model``: "manhattan" observes up to three directions;
        "point" one vanishing point given as a pixel, the paper's measurement)

    Attributes
    ----------
    x : (15, 1) error state [omega, v, delta, omega_k, v_k], zero between steps
    P : (15, 15) its covariance; ``P[:6, :6]`` is the pose covariance (GTSAM order)
    F, Q : the last prediction's Jacobian and process noise
    T_world_keyframe : gtsam.Pose3, the nominal pose of the last keyframe (a clone)
    R : the last measurement noise (2x2, in the tangent basis of the predicted direction)
    K, y, S : gain, innovation and innovation covariance of the last update
    T_world_camera : gtsam.Pose3, the nominal camera pose
    R_world_manhattan : (3, 3) or None before the structure is initialised
    """

    def __init__(self, K: np.ndarray, T_world_camera=None, cov_pose: np.ndarray | None = None,
                 config: VpEkfConfig = _DEFAULT_CONFIG):
        import gtsam

        super().__init__(dim_x=STATE_DIM, dim_z=2)
        self.config = config
        self.K_cam = checked_camera_matrix(K)
        self.T_world_camera = (gtsam.Pose3() if T_world_camera is None
                               else as_pose3(T_world_camera, "T_world_camera"))
        cov_pose = np.diag([1e-8] * 6) if cov_pose is None else np.asarray(cov_pose, float)
        if cov_pose.shape != (6, 6) or not np.all(np.isfinite(cov_pose)):
            raise EstimationError(f"cov_pose must be a finite 6x6 matrix, got {cov_pose.shape}")
        self.x = np.zeros((STATE_DIM, 1))
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[POSE, POSE] = 0.5 * (cov_pose + cov_pose.T)
        P[MANHATTAN, MANHATTAN] = np.eye(3) * np.pi ** 2  # unknown until initialised
        self.P = P
        self.R_world_manhattan: np.ndarray | None = None
        self._observed_axes: set[int] = set()
        self.set_keyframe()

    # ------------------------------------------------------------------ accessors
    @property
    def vp_initialised(self) -> bool:
        return self.R_world_manhattan is not None

    @property
    def world_directions(self) -> np.ndarray:
        """(k, 3) rows: the structure's axes in the world ((0, 3) before initialisation;
        with the point model only the observed first axis)."""
        if self.R_world_manhattan is None:
            return np.zeros((0, 3))
        axes = sorted(self._observed_axes) or [0, 1, 2]
        return self.R_world_manhattan[:, axes].T.copy()

    def pose_covariance(self) -> np.ndarray:
        """The camera pose covariance (6, 6), GTSAM tangent order [rotation, translation]."""
        cov = self.P[POSE, POSE]
        return 0.5 * (cov + cov.T)

    def reanchor(self, T_new_old) -> None:
        """Express the estimate in another world frame: T_new_camera = T_new_old T_old_camera.

        P is unchanged: both perturbations act on the right (module docstring)."""
        A = as_pose3(T_new_old, "T_new_old")
        self.T_world_camera = A.compose(self.T_world_camera)
        self.T_world_keyframe = A.compose(self.T_world_keyframe)
        if self.R_world_manhattan is not None:
            self.R_world_manhattan = A.rotation().matrix() @ self.R_world_manhattan

    # ------------------------------------------------------------------ prediction
    def predict_x(self, u=0):
        """Compose the nominal pose with the increment ``u`` (a gtsam.Pose3); x stays 0."""
        self.T_world_camera = self.T_world_camera.compose(u)

    def predict_vo(self, T_prev_curr, cov: np.ndarray) -> None:
        """Predict with a camera-frame increment T_prev_curr and its (6, 6) covariance
        ([rotation, translation], right perturbation of the increment)."""
        U = as_pose3(T_prev_curr, "T_prev_curr")
        F = np.eye(STATE_DIM)
        F[POSE, POSE] = U.inverse().AdjointMap()
        self.F, self.Q = F, _vo_noise(cov)
        self.predict(u=U)
        self._finish_step()

    def set_keyframe(self) -> None:
        """Clone the current pose as the keyframe (nominal, covariance, cross-covariances)."""
        self.T_world_keyframe = self.T_world_camera
        P = self.P
        P[KEYFRAME, :] = P[POSE, :]
        P[:, KEYFRAME] = P[:, POSE]
        P[KEYFRAME, KEYFRAME] = P[POSE, POSE]
        self.P = P
        self._finish_step()

    def predict_from_keyframe(self, T_keyframe_curr, cov: np.ndarray) -> None:
        """Predict with an increment measured from the keyframe's image to the current one
        and its (6, 6) covariance ([rotation, translation], right perturbation)."""
        U = as_pose3(T_keyframe_curr, "T_keyframe_curr")
        F = np.eye(STATE_DIM)
        F[POSE, POSE] = 0.0
        F[POSE, KEYFRAME] = U.inverse().AdjointMap()
        self.F, self.Q = F, _vo_noise(cov)
        self.P = F @ self.P @ F.T + self.Q
        self.T_world_camera = self.T_world_keyframe.compose(U)
        self._finish_step()

    def predict_lost(self, sigma: tuple[float, float] | None = None) -> None:
        """Predict without odometry: zero motion, covariance grown by ``vo_failure_sigma``."""
        import gtsam

        s_rot, s_trans = self.config.vo_failure_sigma if sigma is None else sigma
        self.predict_vo(gtsam.Pose3(), np.diag([s_rot ** 2] * 3 + [s_trans ** 2] * 3))

    # ------------------------------------------------------------------ updates
    def update_vp(self, uv, cov_uv: np.ndarray) -> VpUpdate:
        """The paper's measurement: one VP pixel with its (2, 2) covariance, as the direction
        of the structure's first axis (the first detection initialises it)."""
        if uv is None or not np.all(np.isfinite(uv)):
            return VpUpdate("skipped", "vp_at_infinity")
        n, dn_duv = pixel_ray(np.asarray(uv, dtype=float).reshape(2), self.K_cam)
        cov_dir = dn_duv @ pixel_covariance(cov_uv) @ dn_duv.T + 1e-10 * np.eye(3)
        if self.R_world_manhattan is None:
            # any right-handed frame whose first axis is the VP (the others stay unobserved)
            self._initialise(np.column_stack([n, tangent_basis(n)]),
                             float(np.trace(cov_dir)) / 2)
            self._observed_axes = {0}
            return VpUpdate("initialised")
        d_hat = self.R_world_camera.T @ self.R_world_manhattan[:, 0]
        if d_hat @ n < 0:
            n = -n
        return self._update_axis(0, n, cov_dir)

    def update_directions(self, directions: np.ndarray, uvs=None, covs=None,
                          direction_covs=None) -> list[VpUpdate]:
        """Update with up to three unit directions in the camera (rows of ``directions``).

        The first call with two directions at least 60 degrees apart initialises the
        structure frame. Later directions are associated with the nearest predicted axis
        (within ``config.manhattan_association_deg``, sign-free) and applied one by one.
        ``uvs``/``covs`` give each direction's pixel and pixel covariance, from which its
        noise is propagated; ``direction_covs`` (k, 3, 3) give it directly (e.g. from depth
        normals); otherwise ``config.direction_sigma`` is used.
        """
        directions, good = unit_directions(directions)
        k = len(directions)
        uvs = [None] * k if uvs is None else list(uvs)
        covs = [None] * k if covs is None else list(covs)
        direction_covs = [None] * k if direction_covs is None else list(direction_covs)
        outcomes = [VpUpdate("skipped", "bad_direction") for _ in range(k)]
        if not good.any():
            return outcomes
        if self.R_world_manhattan is None:
            return self._initialise_from(directions, good, uvs, covs, direction_covs, outcomes)
        used: set[int] = set()
        for i in np.flatnonzero(good):
            predicted = (self.R_world_camera.T @ self.R_world_manhattan).T  # rows: axes
            match = associate_axis(predicted, directions[i], used,
                                   self.config.manhattan_association_deg)
            if match is None:
                outcomes[i] = VpUpdate("skipped", "no_association")
                continue
            axis, d = match
            used.add(axis)
            outcomes[i] = self._update_axis(
                axis, d, self._direction_cov(uvs[i], covs[i], direction_covs[i]))
        return outcomes

    @property
    def R_world_camera(self) -> np.ndarray:
        return self.T_world_camera.rotation().matrix()

    # ------------------------------------------------------------------ internals
    def _update_axis(self, axis: int, d_meas: np.ndarray, cov_dir: np.ndarray) -> VpUpdate:
        d_hat, H3 = axis_jacobians(self.R_world_camera, self.R_world_manhattan, axis)
        B = tangent_basis(d_hat)
        H = B.T @ H3
        R = B.T @ cov_dir @ B
        z = B.T @ d_meas  # the prediction is B^T d_hat = 0
        S = H @ self.P @ H.T + R
        try:
            nis = float(z @ np.linalg.solve(S, z))
        except np.linalg.LinAlgError:
            return VpUpdate("skipped", "singular_S")
        if not np.isfinite(nis):
            return VpUpdate("skipped", "non_finite_innovation")
        if nis > self.config.gate_chi2:
            return VpUpdate("gated", "mahalanobis", nis, z, S)
        d_world = self.R_world_manhattan[:, axis].copy()  # the prediction, for the graph
        # filterpy needs z as a (2, 1) column (a flat (2,) broadcasts and corrupts x)
        self.update(z.reshape(2, 1), lambda _x: H, lambda _x: np.zeros((2, 1)), R=R)
        self._inject()
        self._observed_axes.add(axis)
        return VpUpdate("updated", "", nis, z, S, axis, np.array(d_meas, dtype=float),
                        np.array(cov_dir, dtype=float), d_world)

    def _inject(self) -> None:
        """Move the error-state correction into the nominal state and reset it to zero."""
        import gtsam

        dx = self.x.reshape(-1)
        self.T_world_camera = self.T_world_camera.compose(gtsam.Pose3.Expmap(dx[POSE]))
        self.T_world_keyframe = self.T_world_keyframe.compose(gtsam.Pose3.Expmap(dx[KEYFRAME]))
        if self.R_world_manhattan is not None:
            self.R_world_manhattan = self.R_world_manhattan @ so3_exp(dx[MANHATTAN])
        self.x = np.zeros((STATE_DIM, 1))
        self._finish_step()

    def _initialise_from(self, directions, good, uvs, covs, direction_covs, outcomes
                         ) -> list[VpUpdate]:
        idx = np.flatnonzero(good)
        M_camera = frame_from_two_directions(directions, idx)
        if M_camera is None:
            outcomes[idx[0]] = VpUpdate("skipped", "manhattan_needs_two_directions")
            return outcomes
        noise = max(float(np.trace(self._direction_cov(uvs[j], covs[j], direction_covs[j]))) / 2
                    for j in idx)
        self._initialise(M_camera, noise)
        self._observed_axes = {0, 1, 2}
        for j in idx:
            outcomes[j] = VpUpdate("initialised")
        return outcomes

    def _initialise(self, R_camera_manhattan: np.ndarray, noise: float) -> None:
        """R_world_manhattan = R_world_camera M; delta = M^T omega + detection noise."""
        M = R_camera_manhattan
        self.R_world_manhattan = self.R_world_camera @ M
        P = self.P
        P[MANHATTAN, :] = M.T @ P[ROT, :]  # correlated with the pose and the keyframe
        P[:, MANHATTAN] = P[MANHATTAN, :].T
        P[MANHATTAN, MANHATTAN] = M.T @ P[ROT, ROT] @ M + noise * np.eye(3)
        self.P = P
        self._finish_step()

    def _direction_cov(self, uv, cov, direction_cov=None) -> np.ndarray:
        return direction_covariance(self.K_cam, uv, cov, direction_cov,
                                    self.config.direction_sigma, floor=1e-10)

    def _finish_step(self) -> None:
        """Symmetrise P and check that it is finite and positive definite."""
        self.P = checked_covariance(self.P, "ESKF", semidefinite=True)
