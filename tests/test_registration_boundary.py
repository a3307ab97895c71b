"""The boundary gate (``RegistrationConfig.boundary_gate``): pairs far along the target's
surface from their source point lose their weight at the final correspondence distance.

Checked here on synthetic clouds: the weight is exactly ``exp(-(t / tau)^4 / 2)`` of the
tangential distance t (computed independently from the known plane), pairs beyond the edge of
the target are dropped, nothing changes while d_max anneals, with ``None`` or on a voxel
lattice; bad values are refused. On the real room (a part registered to the map of an
overlapping part, where the gate matters): tests/test_registration_indoor.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig


def plane_with_an_edge(rng):
    """Target: 4000 random points of the unit square z = 0 (x, y in [0, 1]); source: 300
    points over it (x in [0.2, 0.8]) and 100 beyond its edge (x in [1.05, 1.25])."""
    target = np.c_[rng.uniform(0, 1, (4000, 2)), rng.normal(0, 1e-4, 4000)]
    over = np.c_[rng.uniform(0.2, 0.8, 300), rng.uniform(0.2, 0.8, 300), np.zeros(300)]
    beyond = np.c_[rng.uniform(1.05, 1.25, 100), rng.uniform(0.2, 0.8, 100), np.zeros(100)]
    return np.vstack([over, beyond]), target


def test_the_weight_follows_the_tangential_distance():
    source, target = plane_with_an_edge(np.random.default_rng(0))
    reg = Registration(source, target, RegistrationConfig(max_correspondence_distance=0.3))
    corr = reg.correspondences(np.eye(4), 0.3)
    tau = reg.config.boundary_gate * reg.boundary_radius
    along = np.linalg.norm(source[corr.source_idx, :2] - target[corr.target_idx, :2], axis=1)
    np.testing.assert_allclose(corr.weights, np.exp(-0.5 * (along / tau) ** 4), atol=1e-3)
    assert set(corr.source_idx) >= set(range(300))          # every point over the plane
    # ... most at nearly full weight: on a random sampling the nearest neighbour is farther
    # than 1.085 tau (weight 0.5) with probability exp(-20 (0.3 x 1.085)^2) = 0.12 (k = 20)
    over = corr.weights[corr.source_idx < 300]
    assert np.mean(over > 0.5) > 0.8 and over.mean() > 0.7, (np.mean(over > 0.5), over.mean())
    far = np.flatnonzero(source[:, 0] > 1.0 + 3.0 * tau)
    assert len(far) > 20 and not set(corr.source_idx) & set(far)  # beyond the edge: dropped


@pytest.mark.parametrize("case", ["annealing", "off", "lattice"])
def test_every_pair_keeps_its_weight_where_the_gate_does_not_apply(case):
    source, target = plane_with_an_edge(np.random.default_rng(1))
    config = RegistrationConfig(max_correspondence_distance=0.3,
                                boundary_gate=None if case == "off" else 0.3)
    d_max = 0.5 if case == "annealing" else 0.3
    if case == "lattice":  # voxel centres of the same plane (2 cm): no gate on a lattice
        target = (np.unique(np.floor(target / 0.02), axis=0) + 0.5) * 0.02
    reg = Registration(source, target, config)
    corr = reg.correspondences(np.eye(4), d_max)
    within = np.linalg.norm(source[:, None] - target[None], axis=2).min(axis=1) <= d_max
    assert len(corr) == within.sum()
    assert np.all(corr.weights == 1.0)


@pytest.mark.parametrize("value", [0, -0.3, float("nan"), float("inf"), "auto"])
def test_bad_boundary_gate_is_refused(value):
    with pytest.raises(EstimationError, match="boundary_gate"):
        RegistrationConfig(boundary_gate=value)
