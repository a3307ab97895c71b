"""Local surface positions (RegistrationConfig.surface_radius) on voxel-centre clouds."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig, pose_error
from estimation.registration.correspondences import (
    LazyCovariances,
    local_means,
    neighbourhoods,
    point_covariances,
)


def test_local_means_equal_brute_force(rng):
    points = rng.uniform(0, 1, (400, 3)) * [1.0, 1.0, 0.1]
    radius, min_points = 0.15, 6
    tree = cKDTree(points)
    got = local_means(points, tree, radius, min_points, k_max=len(points))
    dist = np.linalg.norm(points[:, None] - points[None], axis=2)
    for i in range(len(points)):
        inside = dist[i] <= radius
        want = points[inside].mean(axis=0) if inside.sum() >= min_points else points[i]
        np.testing.assert_allclose(got[i], want, atol=1e-12)
    # rows and the lazy cache give the same values
    rows = rng.choice(len(points), 50, replace=False)
    np.testing.assert_allclose(local_means(points, tree, radius, min_points, rows,
                                           k_max=len(points)), got[rows])
    # one shared query: the covariances are those of point_covariances, the means those of
    # local_means over the k_max nearest; lazily row by row as well
    covs, means = neighbourhoods(points, 20, 1e-3, tree, radius=radius, min_points=min_points)
    np.testing.assert_allclose(covs, point_covariances(points, 20, 1e-3, tree))
    np.testing.assert_allclose(means, local_means(points, tree, radius, min_points))
    lazy = LazyCovariances(points, tree, 20, 1e-3, radius, min_points)
    np.testing.assert_allclose(lazy.means(rows), means[rows])
    np.testing.assert_allclose(lazy[rows], covs[rows])
    np.testing.assert_allclose(lazy.means(np.arange(len(points))), means)


def test_sparse_clouds_are_unchanged(rng):
    points = rng.uniform(0, 10, (300, 3))  # ~1.5 m apart: no neighbours within 5 cm
    np.testing.assert_array_equal(local_means(points, cKDTree(points), 0.05, 6), points)


def test_bad_surface_radius_is_rejected():
    for bad in (0.0, -1.0, "big"):
        with pytest.raises(EstimationError, match="surface_radius"):
            RegistrationConfig(surface_radius=bad)


@pytest.mark.slow
def test_surface_positions_on_the_room_map_from_the_ground_truth():
    # the robot's 3 cm voxel-centre map and the full headset cloud (the benchmark's 50k cell):
    # measured from the ground truth, d_SE(3) 0.035 with the samples, 0.0057 with the means
    from perception.simulation.room import (
        RoomConfig,
        build_room,
        headset_cloud,
        robot_semantic_map,
    )

    cfg = RoomConfig(seed=0)
    room = build_room(cfg)
    target = robot_semantic_map(room, cfg).points
    source, T_gt = headset_cloud(room, "dining", cfg)
    errors = {}
    for radius in (None, "auto"):
        reg = Registration(source.points, target, RegistrationConfig(
            max_correspondence_distance=0.2, surface_radius=radius))
        result = reg.run(T_gt)
        assert result.converged, result.reason
        errors[radius] = pose_error(result.T, T_gt).d_se3
    assert reg.surface_radius == pytest.approx(np.sqrt(3) * cfg.robot_voxel)  # found the grid
    assert errors["auto"] < 0.5 * errors[None], errors


def test_lattice_pitch_detects_voxel_centres(rng):
    from estimation.registration.correspondences import lattice_pitch

    res = 0.03
    surface = rng.uniform(-2, 2, (20000, 3)) * [1, 1, 0.02] + [0.3, -1.2, 0.7]
    centres = (np.unique(np.floor(surface / res), axis=0) + 0.5) * res
    assert lattice_pitch(centres) == pytest.approx(res, rel=1e-9)
    # stored as float32 (a PLY file), with 5 % pruned nodes (centres of 2x2x2 blocks, half a
    # voxel off the lattice): still found
    pruned = (np.unique(np.floor(surface[:300] / (2 * res)), axis=0) + 0.5) * 2 * res
    mixed = np.vstack([centres, pruned[: len(centres) // 20]]).astype(np.float32)
    assert lattice_pitch(mixed) == pytest.approx(res, rel=1e-6)
    # a thin subsample has no adjacent voxels left: not recognised (no means needed there)
    assert lattice_pitch(centres[rng.choice(len(centres), 300, replace=False)]) is None
    # measured points, or voxel means of them, are not on a lattice
    assert lattice_pitch(surface) is None
    keys, inverse = np.unique(np.floor(surface / res), axis=0, return_inverse=True)
    means = np.zeros((len(keys), 3))
    np.add.at(means, inverse.reshape(-1), surface)
    means /= np.bincount(inverse.reshape(-1))[:, None]
    assert lattice_pitch(means) is None
    assert lattice_pitch(centres[:5]) is None


def test_auto_surface_radius_follows_the_lattice(rng):
    res = 0.05
    plane = rng.uniform(0, 2, (5000, 3)) * [1, 1, 0]
    centres = (np.unique(np.floor(plane / res), axis=0) + 0.5) * res
    reg = Registration(plane[:500] + rng.normal(0, 1e-3, (500, 3)), centres)
    assert reg.surface_radius == pytest.approx(np.sqrt(3) * res)
    assert Registration(plane[:500], plane[500:]).surface_radius is None
    assert Registration(plane[:500], centres,
                        RegistrationConfig(surface_radius=None)).surface_radius is None
