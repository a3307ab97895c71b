"""The built-in estimators wrapped in the plug-in protocols of :mod:`estimation.plugins`.

Each wrapper adds the protocol's small surface (``reset``/``predict``/``update``/``error``
or ``register``) and a ``simulate`` scenario of its own, so that the shared contract suite
can check it like any third-party plug-in.
"""
from __future__ import annotations

import numpy as np

from .plugins import FilterScenario, RegistrationScenario

# Simulation settings of the VP-EKF scenario (an Xtion-like camera walking a corridor).
_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
_COV_VO = np.diag([2e-4] * 3 + [4e-3] * 3) ** 2 * 25.0  # [rot rad^2, trans m^2] per frame
_SIGMA_PX = 1.0
_VP_DISTANCE = 1000.0  # the paper's d: far enough that the VP range stays unobservable


class VPEKFEstimator:
    """The VP-EKF of Ji et al. (:class:`estimation.vp_ekf.VanishingPointEKF`) as a filter.

    State: ``[x, y, z, psi, theta, phi, x_V, y_V, z_V]`` (docs/vp_ekf.md). The control
    ``u`` is a camera-frame VO increment as a tangent 6-vector [rotation, translation]
    (``T_prev_curr = Pose3.Expmap(u)``) with covariance ``cov_u``; the measurement is the
    VP pixel ``(u, v)`` with a 2x2 covariance.
    """

    name = "vp_ekf"
    kind = "filter"

    def __init__(self, K: np.ndarray = _K) -> None:
        from .vp_ekf import VanishingPointEKF, VpEkfConfig

        self._K = np.asarray(K, dtype=float)
        self._ekf = VanishingPointEKF(self._K, config=VpEkfConfig(vp_distance=_VP_DISTANCE,
                                                                   gate_chi2=np.inf))

    @property
    def x(self) -> np.ndarray:
        return self._ekf.x.reshape(-1).copy()

    @property
    def P(self) -> np.ndarray:
        return self._ekf.P.copy()

    def reset(self, x0, P0) -> None:
        self._ekf.x = np.asarray(x0, dtype=float).reshape(-1, 1).copy()
        self._ekf.P = np.asarray(P0, dtype=float).copy()
        self._ekf.vp_initialised = True  # x0 carries the VP point already

    def predict(self, u, cov_u) -> None:
        import gtsam

        self._ekf.predict_vo(gtsam.Pose3.Expmap(np.asarray(u, dtype=float)), cov_u)

    def update(self, z, R) -> bool:
        return self._ekf.update_vp(np.asarray(z, dtype=float).reshape(2), R).status == "updated"

    def error(self, x_true) -> np.ndarray:
        from .geometry import wrap_angle

        error = np.asarray(x_true, dtype=float) - self.x
        error[3:6] = wrap_angle(error[3:6])
        return error

    def simulate(self, rng: np.random.Generator, n_steps: int = 30) -> FilterScenario:
        """A zigzag walk along world x with VO increments and VP pixels of known noise."""
        import gtsam

        from .geometry import R_BODY_CAMERA, euler_to_matrix, matrix_to_euler

        k = np.arange(n_steps + 1)
        positions = np.column_stack([0.24 * k, 0.3 * np.sin(2 * np.pi * k / 12),
                                     1.2 + 0.03 * np.sin(2 * np.pi * k / 17)])
        eulers = np.column_stack([0.02 * np.sin(2 * np.pi * k / 9),
                                  0.03 * np.sin(2 * np.pi * k / 15),
                                  0.2 * np.cos(2 * np.pi * k / 12)])
        poses = [gtsam.Pose3(gtsam.Rot3(euler_to_matrix(e) @ R_BODY_CAMERA), p)
                 for p, e in zip(positions, eulers)]
        direction = np.array([1.0, 0.02, 0.01]) / np.linalg.norm([1.0, 0.02, 0.01])
        vp_world = positions[0] + _VP_DISTANCE * direction

        def state(pose) -> np.ndarray:
            R_wb = pose.rotation().matrix() @ R_BODY_CAMERA.T
            return np.r_[pose.translation(), matrix_to_euler(R_wb), vp_world]

        P0 = np.diag([1e-3] * 3 + [1e-3] * 3 + [2.0] * 3) ** 2
        truth0 = state(poses[0])
        x0 = truth0 + rng.multivariate_normal(np.zeros(9), P0)
        controls, control_covs, measurements, measurement_covs, truths = [], [], [], [], []
        for step in range(1, n_steps + 1):
            increment = poses[step - 1].between(poses[step]).compose(
                gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), _COV_VO)))
            controls.append(gtsam.Pose3.Logmap(increment))
            control_covs.append(_COV_VO)
            pose = poses[step]
            q = self._K @ (pose.rotation().matrix().T @ (vp_world - pose.translation()))
            measurements.append(q[:2] / q[2] + rng.normal(0.0, _SIGMA_PX, 2))
            measurement_covs.append(np.eye(2) * _SIGMA_PX ** 2)
            truths.append(state(pose))
        return FilterScenario(x0, P0, controls, control_covs, measurements, measurement_covs,
                              truths, truth0)
