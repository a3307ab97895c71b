"""An example octofactor plug-in: a 1-D constant-velocity Kalman filter built on filterpy.

State x = [position, velocity]; the control is an acceleration over a step of DT seconds;
the measurement is the position. ``BrokenFilter`` is deliberately incomplete: octofactor
must skip it with a warning instead of failing.
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

from estimation.plugins import FilterScenario

DT = 0.1


class ConstantVelocityFilter:
    name = "example_cv_filter"
    kind = "filter"

    def __init__(self) -> None:
        self._kf = KalmanFilter(dim_x=2, dim_z=1)
        self._kf.F = np.array([[1.0, DT], [0.0, 1.0]])
        self._kf.H = np.array([[1.0, 0.0]])
        self._B = np.array([[0.5 * DT**2], [DT]])

    @property
    def x(self) -> np.ndarray:
        return self._kf.x.reshape(-1).copy()

    @property
    def P(self) -> np.ndarray:
        return self._kf.P.copy()

    def reset(self, x0, P0) -> None:
        self._kf.x = np.asarray(x0, float).reshape(2, 1)
        self._kf.P = np.asarray(P0, float).copy()

    def predict(self, u, cov_u) -> None:
        accel = float(np.asarray(u).reshape(-1)[0])
        Q = self._B @ np.atleast_2d(cov_u) @ self._B.T
        self._kf.predict(u=np.array([[accel]]), B=self._B, Q=Q)

    def update(self, z, R) -> bool:
        self._kf.update(np.asarray(z, float).reshape(1, 1), R=np.atleast_2d(R))
        return True

    def error(self, x_true) -> np.ndarray:
        return np.asarray(x_true, float) - self.x

    def simulate(self, rng, n_steps: int = 30) -> FilterScenario:
        sigma_a, sigma_z = 0.5, 0.2
        F = self._kf.F
        B = self._B.reshape(-1)
        truth = np.array([0.0, 1.0])
        P0 = np.diag([0.1, 0.1])
        x0 = truth + rng.multivariate_normal(np.zeros(2), P0)
        controls, control_covs, measurements, measurement_covs, truths = [], [], [], [], []
        for _ in range(n_steps):
            accel = np.sin(len(truths) * 0.3)
            truth = F @ truth + B * (accel + rng.normal(0, sigma_a))
            controls.append(np.array([accel]))
            control_covs.append(np.array([[sigma_a**2]]))
            measurements.append(np.array([truth[0] + rng.normal(0, sigma_z)]))
            measurement_covs.append(np.array([[sigma_z**2]]))
            truths.append(truth.copy())
        return FilterScenario(x0, P0, controls, control_covs, measurements, measurement_covs,
                              truths, np.array([0.0, 1.0]))


class BrokenFilter:
    """Claims to be a filter but has no predict/update: must be skipped with a warning."""

    name = "example_broken"
    kind = "filter"
