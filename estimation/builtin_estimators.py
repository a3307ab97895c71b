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

    def slam_filter(self, K, T_world_camera, cov_pose, ekf_config):
        """A fresh filter for the vpslam pipeline: the error-state EKF
        (:class:`~estimation.vp_eskf.VanishingPointESKF`) or, with ``ekf_config.state ==
        "euler"``, the paper's :class:`~estimation.vp_ekf.VanishingPointEKF`."""
        if ekf_config.state == "euler":
            from .vp_ekf import VanishingPointEKF

            return VanishingPointEKF(K, T_world_camera, cov_pose, ekf_config)
        from .vp_eskf import VanishingPointESKF

        return VanishingPointESKF(K, T_world_camera, cov_pose, ekf_config)

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


def _labelled_corner_scene(rng: np.random.Generator, n_points: int = 3000
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Points on a floor, three walls and a box (one class each) with 5 mm noise."""
    n_classes = 5
    labels = rng.integers(0, n_classes, n_points)
    uv = rng.uniform(0.0, 1.0, (n_points, 2))
    points = np.zeros((n_points, 3))
    floor, wall_x, wall_y, wall_back, box = (labels == c for c in range(n_classes))
    points[floor] = np.column_stack([4 * uv[floor, 0], 3 * uv[floor, 1], np.zeros(floor.sum())])
    points[wall_x] = np.column_stack([np.zeros(wall_x.sum()), 3 * uv[wall_x, 0],
                                      2.5 * uv[wall_x, 1]])
    points[wall_y] = np.column_stack([4 * uv[wall_y, 0], np.zeros(wall_y.sum()),
                                      2.5 * uv[wall_y, 1]])
    points[wall_back] = np.column_stack([4 * uv[wall_back, 0], np.full(wall_back.sum(), 3.0),
                                         2.5 * uv[wall_back, 1]])
    points[box] = np.column_stack([1.5 + 0.6 * uv[box, 0], 1.0 + 0.6 * uv[box, 1],
                                   np.full(box.sum(), 0.8)])
    points += rng.normal(0.0, 0.005, points.shape)
    probs = np.full((n_points, n_classes), 0.1 / (n_classes - 1))
    probs[np.arange(n_points), labels] = 0.9
    return points, probs


def _registration_scenario(rng: np.random.Generator) -> RegistrationScenario:
    import gtsam

    target, target_probs = _labelled_corner_scene(rng)
    source_world, source_probs = _labelled_corner_scene(rng)
    T_target_source = gtsam.Pose3.Expmap(np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.2, 3)])
    T_source_target = T_target_source.inverse().matrix()
    source = source_world @ T_source_target[:3, :3].T + T_source_target[:3, 3]
    T_init = T_target_source.compose(
        gtsam.Pose3.Expmap(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.05, 3)]))
    return RegistrationScenario(source, target, T_target_source.matrix(), T_init.matrix(),
                                {"source_probs": source_probs, "target_probs": target_probs})


class GICPRegistration:
    """GICP-SE(3) (eq. (3)) with a Cauchy kernel: :func:`estimation.registration.gicp_se3`.

    ``options`` are :class:`estimation.registration.RegistrationConfig` fields; class
    probabilities, if passed, are ignored (geometry only).
    """

    name = "gicp"
    kind = "registration"

    def register(self, source, target, T_init, **options):
        from .registration import RegistrationConfig, gicp_se3

        options.pop("source_probs", None)
        options.pop("target_probs", None)
        return gicp_se3(source, target, T_init, RegistrationConfig(**options))

    def simulate(self, rng: np.random.Generator) -> RegistrationScenario:
        return _registration_scenario(rng)


class SemanticICPRegistration:
    """Semantic-ICP (eq. (5)-(8)): :func:`estimation.registration.semantic_icp`.

    Needs ``source_probs`` and ``target_probs`` (N x C class probabilities) in ``options``;
    the other options are :class:`estimation.registration.RegistrationConfig` fields.
    """

    name = "semantic_icp"
    kind = "registration"

    def register(self, source, target, T_init, **options):
        from .errors import EstimationError
        from .registration import RegistrationConfig, semantic_icp

        try:
            source_probs = options.pop("source_probs")
            target_probs = options.pop("target_probs")
        except KeyError:
            raise EstimationError("semantic_icp needs source_probs and target_probs") from None
        return semantic_icp(source, source_probs, target, target_probs, T_init,
                            RegistrationConfig(**options))

    def simulate(self, rng: np.random.Generator) -> RegistrationScenario:
        return _registration_scenario(rng)
