"""Figures shared by the pipelines (matplotlib, Agg backend, PNG files)."""
from __future__ import annotations

import numpy as np


def use_agg():
    """Import pyplot on the non-interactive Agg backend and return it."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def covariance_ellipse(mean_xy: np.ndarray, cov_xy: np.ndarray, n_sigma: float = 2.0,
                       n_points: int = 48) -> np.ndarray:
    """(n_points, 2) outline of the n-sigma ellipse of a 2-D Gaussian."""
    values, vectors = np.linalg.eigh(0.5 * (cov_xy + cov_xy.T))
    values = np.clip(values, 0.0, None)
    angle = np.linspace(0, 2 * np.pi, n_points)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    return (mean_xy[:, None] + n_sigma * vectors @ (np.sqrt(values)[:, None] * circle)).T


def world_translation_covariance(rotation_world_sensor: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """3x3 position covariance in the world frame from a body-frame [rot, trans] 6x6.

    With ``T * Expmap(xi)`` the position moves by ``R @ xi_t`` to first order.
    """
    R = rotation_world_sensor
    return R @ cov6[3:, 3:] @ R.T


def save_figure(fig, path) -> None:
    """Save ``fig`` as a PNG through a temporary name and close it."""
    from estimation.fileio import atomic_write

    with atomic_write(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
