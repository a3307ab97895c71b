"""Registration error metrics: d_SE(3) of eq. (9), translation and rotation errors."""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..geometry import d_se3


@dataclass(frozen=True)
class PoseError:
    """Errors of an estimate against ground truth.

    Attributes
    ----------
    d_se3 : ||Logmap(T* T_GT^-1)|| (eq. (9)), mixing radians and metres as the paper does
    t_err_m : translation error of T_GT^-1 T* (m)
    r_err_rad : rotation angle of T_GT^-1 T* (rad)
    tangent : (6,) T*.localCoordinates(T_GT) = Logmap(T*^-1 T_GT), [rotation, translation]:
        the error the registration covariance describes (for NEES)
    """

    d_se3: float
    t_err_m: float
    r_err_rad: float
    tangent: np.ndarray


def pose_error(T_est: np.ndarray | gtsam.Pose3, T_gt: np.ndarray | gtsam.Pose3) -> PoseError:
    """Return the d_SE(3), translation and rotation errors of ``T_est`` against ``T_gt``."""
    est = T_est if isinstance(T_est, gtsam.Pose3) else gtsam.Pose3(np.asarray(T_est, float))
    gt = T_gt if isinstance(T_gt, gtsam.Pose3) else gtsam.Pose3(np.asarray(T_gt, float))
    # eq. (9): d_SE(3)(T*; T_GT) = ||log(T* T_GT^-1)||
    d = d_se3(est, gt)
    rel = gt.between(est)
    return PoseError(d, float(np.linalg.norm(rel.translation())),
                     float(np.linalg.norm(gtsam.Rot3.Logmap(rel.rotation()))),
                     np.asarray(est.localCoordinates(gt)))


def offset_about_centroid(rng: np.random.Generator, centroid: np.ndarray, metres: float,
                          degrees: float) -> np.ndarray:
    """A 4x4 test offset: rotate ``degrees`` about a random axis through ``centroid``, then
    shift ``metres`` in a random direction.

    ``T_gt @ offset_about_centroid(rng, source.mean(0), 1.0, 40.0)`` is the benchmarks'
    "wide" initial guess (0.2 m / 8 deg is "small").
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    shift = rng.normal(size=3)
    shift *= metres / np.linalg.norm(shift)
    D = gtsam.Pose3(gtsam.Rot3.Rodrigues(axis * np.deg2rad(degrees)), shift).matrix()
    C = np.eye(4)
    C[:3, 3] = centroid
    return C @ D @ np.linalg.inv(C)
