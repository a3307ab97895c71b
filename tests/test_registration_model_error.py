"""Model error in the registration covariance: a voxel map's quantisation, and the diagnostic.

The i.i.d. point-noise sandwich (tests/test_registration_covariance.py) says nothing about
errors shared by whole surfaces. A robot's octree map stores surfaces as voxel centres, off
the true surface by up to half a voxel along the normal, the same offset for a whole plane
parallel to the lattice; the registration error is then systematic and the sandwich alone
was 100-1000x over-confident on the demo room (docs/registration.md). These tests check the
quantisation term (:func:`quantisation_information`) piece by piece and in Monte Carlo runs
on the room simulator, with controls that must fail.
"""
from __future__ import annotations

import numpy as np
import pytest
from test_registration import make_pair

from estimation.covariance import check_consistency, nees
from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig, pose_error
from estimation.registration.gicp import plane_groups, quantisation_information
from estimation.registration.metrics import offset_about_centroid


# -- building blocks -------------------------------------------------------------------------
def test_plane_groups_split_planes_and_orient_normals(rng):
    pitch = 0.03
    floor = np.c_[rng.uniform(0, 2, (200, 2)), rng.normal(0.015, 0.005, 200)]
    shelf = np.c_[rng.uniform(0, 2, (100, 2)), np.full(100, 0.315)]  # parallel, 30 cm up
    wall = np.c_[np.full(150, 0.015), rng.uniform(0, 2, (150, 2))]
    points = np.vstack([floor, shelf, wall])
    normals = np.vstack([np.tile([0, 0, 1.0], (300, 1)), np.tile([-1.0, 0, 0], (150, 1))])
    normals[::2] *= -1  # eigenvector signs are arbitrary
    group, sign = plane_groups(normals, points, 3 * pitch)
    assert len(np.unique(group[:200])) == 1 and len(np.unique(group[200:300])) == 1
    assert len(np.unique(group[300:])) == 1
    assert len({group[0], group[200], group[300]}) == 3
    np.testing.assert_array_equal((normals * sign[:, None]).max(axis=1), 1.0)


def test_quantisation_information_is_the_offset_variance_of_each_group(rng):
    pitch = 0.05
    points = np.c_[rng.uniform(0, 1, (50, 2)), np.zeros(50)]
    normals = np.tile([0, 0, 1.0], (50, 1))
    sens = rng.normal(size=(50, 6))
    info = quantisation_information(normals, points, sens, pitch)
    v = sens.sum(axis=0)  # one plane: one common offset
    np.testing.assert_allclose(info, pitch ** 2 / 12 * np.outer(v, v), atol=1e-15)
    # an offset delta moves every score by delta * sensitivity: the Monte Carlo variance of
    # the summed score change equals the information
    delta = rng.uniform(-pitch / 2, pitch / 2, 20000)
    moved = delta[:, None] * v
    np.testing.assert_allclose(np.cov(moved.T), info, rtol=0.05, atol=1e-6 * np.abs(info).max())


def test_clouds_off_a_lattice_get_no_quantisation_term():
    source, _, target, _, _ = make_pair(3, 1500, 0.005)
    result = Registration(source, target, RegistrationConfig()).run()
    assert result.converged
    d = result.diagnostic
    assert d.quantisation_pitch is None and d.model_error_share == 0.0
    assert not d.model_covariance.any()


def test_bad_quantisation_option_is_rejected():
    with pytest.raises(EstimationError, match="quantisation"):
        RegistrationConfig(quantisation=-0.03)
    with pytest.raises(EstimationError, match="quantisation"):
        RegistrationConfig(quantisation="big")


def test_quantisation_can_be_given_or_switched_off():
    source, _, target, _, _ = make_pair(4, 1500, 0.005)
    given = Registration(source, target, RegistrationConfig(quantisation=0.03)).run()
    assert given.diagnostic.quantisation_pitch == 0.03
    assert given.diagnostic.model_error_share > 0.0
    plain = Registration(source, target, RegistrationConfig(quantisation=None)).run()
    np.testing.assert_allclose(given.covariance - given.diagnostic.model_covariance,
                               plain.covariance, rtol=1e-6, atol=1e-11)
