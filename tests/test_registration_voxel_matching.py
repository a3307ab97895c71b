"""Same-voxel correspondences on voxel-centroid maps (RegistrationConfig.voxel_matching).

Checked: the map's grid (pitch and phase) is recovered from a centroid map, ours and
Open3D's, and from nothing else (raw or jittered clouds, a source); a point's cell lookup
is the brute-force one; on the real ICL-NUIM office against its 3 cm centroid map the
estimate is several times more accurate than with the nearest centroid (switching the
stage off fails it), and on the real TUM room it is no worse; where the source does not lie
inside the map, or the map is a voxel lattice, nothing changes; bad values are refused. The
source points matched to one centroid share the mean of their covariances, and on raw halves
of the real TUM room that is more accurate than each point's own (switching it off fails).
"""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from benchmarks.registration import D_FINAL, OFFSETS, register_ours
from benchmarks.registration_indoor import SOURCE_POINTS, half_room_source
from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig, gicp, pose_error
from estimation.registration.correspondences import voxel_grid
from estimation.registration.metrics import offset_about_centroid


def thick_room(rng, n=300_000, layer=0.004):
    """Points of a box room with a table and a tilted board, surfaces 4 mm thick."""
    u = rng.uniform(size=(n, 2))
    face = rng.integers(0, 7, n)
    p = np.zeros((n, 3))
    p[face == 0] = np.c_[u[face == 0] * [4.0, 3.0], np.zeros((face == 0).sum())]   # floor
    p[face == 1] = np.c_[u[face == 1, 0] * 4.0, np.zeros((face == 1).sum()), u[face == 1, 1] * 2.5]
    p[face == 2] = np.c_[np.zeros((face == 2).sum()), u[face == 2] * [3.0, 2.5]]
    p[face == 3] = np.c_[np.full((face == 3).sum(), 4.0), u[face == 3] * [3.0, 2.5]]
    p[face == 4] = np.c_[u[face == 4, 0] * 4.0, np.full((face == 4).sum(), 3.0),
                         u[face == 4, 1] * 2.5]
    p[face == 5] = np.c_[1.0 + u[face == 5] * [1.2, 0.8], np.full((face == 5).sum(), 0.75)]
    board = face == 6  # tilted 20 deg about x
    a, b = u[board, 0] * 1.5, u[board, 1] * 1.0
    p[board] = np.c_[1.5 + a, 2.0 + b * np.cos(0.35), 0.5 + b * np.sin(0.35)]
    normals = np.zeros((n, 3))
    normals[np.isin(face, (0, 5)), 2] = 1.0
    normals[np.isin(face, (1, 4)), 1] = 1.0
    normals[np.isin(face, (2, 3)), 0] = 1.0
    normals[board] = [0.0, -np.sin(0.35), np.cos(0.35)]
    return p + rng.normal(scale=layer, size=(n, 1)) * normals


def centroids(points, pitch, origin):
    keys = np.floor((points - origin) / pitch).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    out = np.zeros((len(counts), 3))
    np.add.at(out, inverse.reshape(-1), points)
    return out / counts[:, None]


@pytest.mark.parametrize("pitch", [0.025, 0.03, 0.05])
def test_the_grid_is_recovered_from_a_centroid_map(rng, pitch):
    room = thick_room(rng)
    origin = rng.uniform(-1.0, 1.0, 3)
    grid = voxel_grid(centroids(room, pitch, origin))
    assert grid is not None
    assert grid.pitch == pytest.approx(pitch, rel=3e-4)
    phase = (grid.origin - origin) / pitch
    np.testing.assert_allclose(phase - np.round(phase), 0.0, atol=0.03)
    assert grid.shared < 0.02


def test_the_grid_of_open3ds_voxel_down_sample_is_recovered(rng):
    import open3d as o3d

    room = thick_room(rng) + rng.uniform(-1.0, 1.0, 3)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(room))
    grid = voxel_grid(np.asarray(cloud.voxel_down_sample(0.04).points))
    assert grid is not None and grid.pitch == pytest.approx(0.04, rel=3e-4)
    # Open3D's grid is anchored half a voxel below the cloud's minimum bound
    phase = (grid.origin - (room.min(axis=0) - 0.02)) / 0.04
    np.testing.assert_allclose(phase - np.round(phase), 0.0, atol=0.03)


def test_no_grid_in_clouds_that_are_not_centroid_maps(rng):
    room = thick_room(rng)
    assert voxel_grid(room[::10]) is None  # raw points
    jittered = centroids(room, 0.03, np.zeros(3)) + rng.normal(scale=0.005, size=(1, 3))
    jittered += rng.normal(scale=0.006, size=jittered.shape)  # the cells' phase is lost
    assert voxel_grid(jittered) is None


def test_lookup_is_the_cell_a_point_lies_in(rng):
    room = thick_room(rng)
    origin = np.array([0.011, -0.007, 0.02])
    keys = np.floor((room - origin) / 0.03).astype(np.int64)
    map_points = centroids(room, 0.03, origin)
    grid = voxel_grid(map_points)
    probe = room[rng.choice(len(room), 2000)] + rng.normal(scale=0.02, size=(2000, 3))
    hit, rows = grid.lookup(probe)
    map_keys = {tuple(k): i for i, k in enumerate(
        np.floor((map_points - origin) / 0.03).astype(np.int64))}
    expected = np.array([map_keys.get(tuple(k), -1) for k in
                         np.floor((probe - origin) / 0.03).astype(np.int64)])
    assert len(keys)  # (the room has points in the grid)
    # (a point within a hair of a cell wall may fall on the other side of the recovered grid)
    assert np.mean(rows == expected) > 0.97
    np.testing.assert_array_equal(hit, rows >= 0)


def test_bad_voxel_matching_values_are_refused():
    for value in (0.0, -5.0, 91.0, float("nan"), "10"):
        with pytest.raises(EstimationError, match="voxel_matching"):
            RegistrationConfig(voxel_matching=value)


def test_nothing_changes_where_the_source_does_not_lie_inside_or_on_a_lattice(rng):
    room = thick_room(rng)
    # a map of voxel centres (a lattice) and a map of centroids with a partial source
    lattice = (np.unique(np.floor(room / 0.03), axis=0) + 0.5) * 0.03
    part = room[(room[:, 0] > 1.5)][::4] + rng.normal(scale=0.003, size=(1, 3))
    partial_map = centroids(room[room[:, 0] < 2.5], 0.03, np.zeros(3))
    init = np.eye(4)
    init[:3, 3] = [0.01, -0.02, 0.01]
    for target in (lattice, partial_map):
        # (a partial overlap is matched by cell from convergence on where the map's layers
        # are cut into sheets: partial_voxel_matching, tests/test_registration_partial_cells.py)
        cfg = dict(max_correspondence_distance=0.1, symmetric=False,
                   partial_voxel_matching=False)
        a = Registration(part, target, RegistrationConfig(**cfg)).run(init)
        b = Registration(part, target, RegistrationConfig(voxel_matching=None, **cfg)).run(init)
        np.testing.assert_array_equal(a.T, b.T)
        np.testing.assert_array_equal(a.covariance, b.covariance)
    # these thick axis-aligned walls are what the partial cells are for; never on a lattice
    cfg = dict(max_correspondence_distance=0.1, symmetric=False)
    assert Registration(part, partial_map, RegistrationConfig(**cfg)).run(
        init).diagnostic.voxel_pitch == pytest.approx(0.03, rel=1e-3)
    assert Registration(part, lattice, RegistrationConfig(**cfg)).run(
        init).diagnostic.voxel_pitch is None


def test_a_start_without_annealing_still_matches_by_cell(rng):
    # the first final-stage iteration may be too far off to see the source inside the map;
    # convergence then decides, and the iterations go on with the cells
    room = thick_room(rng)
    target = centroids(room, 0.03, np.array([0.004, 0.011, -0.008]))
    source = room[room[:, 0] < 2.0][::20] + rng.normal(scale=0.003, size=(1, 3))
    init = np.eye(4)
    init[:3, :3] = gtsam.Rot3.Rz(0.1).matrix()
    init[:3, 3] = [0.2, -0.15, 0.08]
    reg = Registration(source, target, RegistrationConfig())
    assert not gicp.source_inside_target(*reg.overlap(init, reg.cluster_size(init, None)))
    result = reg.run(init)
    assert result.converged
    assert result.diagnostic.voxel_pitch == pytest.approx(0.03, rel=1e-3)


def _errors(points, labels, target, trials, n=SOURCE_POINTS, **options):
    out = []
    metres, degrees, d0 = OFFSETS["small"]
    for seed in range(trials):
        rng = np.random.default_rng(seed)
        source, T_gt = half_room_source(points, labels, rng, n)
        init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
        result, _ = register_ours(source, target, init, (d0, D_FINAL), **options)
        out.append(pose_error(result.T, T_gt).t_err_m)
        pitch = result.diagnostic.voxel_pitch  # the grid whose cells matched, reported
        if options.get("voxel_matching", 10.0) is None:
            assert pitch is None
        else:
            assert pitch == pytest.approx(0.03, rel=1e-3)
    return np.array(out)


def _same_and_nearest(room, trials: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the same trials on a real room's 3 cm centroid map (``room``: points,
    labels, map), with same-voxel matching (the default) and with the nearest centroid."""
    points, labels, target = room
    return (_errors(points, labels, target, trials),
            _errors(points, labels, target, trials, voxel_matching=None))


@pytest.mark.slow
def test_same_voxel_matching_is_far_more_accurate_on_a_real_office_map(centroid_room):
    # ICL-NUIM's office against its 3 cm centroid map (measured on the benchmark's room:
    # median d_SE3 3.46 -> 1.31 mm); the same trials with the nearest centroid must lose
    same, nearest = _same_and_nearest(centroid_room("icl", 10))
    assert np.median(same / nearest) < 0.6, (same, nearest)


@pytest.mark.slow
def test_same_voxel_matching_is_no_worse_on_a_real_kinect_room(centroid_room):
    same, nearest = _same_and_nearest(centroid_room("tum", 10))
    assert np.median(same) < 1.15 * np.median(nearest), (same, nearest)


def test_the_pooled_covariance_is_the_mean_over_the_pairs_of_one_centroid(rng):
    from estimation.registration.factors import pooled_covariances

    a = rng.normal(size=(50, 3, 3))
    cov = a @ a.transpose(0, 2, 1) + np.eye(3)
    source_rows = rng.integers(0, 50, 400)
    target_rows = rng.integers(0, 30, 400)
    pooled, rows = pooled_covariances(cov, source_rows, target_rows, 30)
    assert len(pooled) == len(np.unique(target_rows))
    for t in np.unique(target_rows):
        mine = target_rows == t
        assert len(np.unique(rows[mine])) == 1
        np.testing.assert_allclose(pooled[rows[mine][0]],
                                   cov[source_rows[mine]].mean(axis=0), rtol=1e-12)
    # one pair per target: every pair keeps its own covariance
    one, rows = pooled_covariances(cov, np.arange(50), rng.permutation(60)[:50], 60)
    np.testing.assert_array_equal(one[rows], cov)


@pytest.mark.slow
def test_one_covariance_per_centroid_is_more_accurate_on_a_dense_kinect_half(centroid_room):
    # raw halves of the real TUM room (190k-330k points) against its 3 cm centroid map:
    # each point's own plane covariance weights a centroid's cell unevenly and the cells'
    # biases add up over the desk (measured, seeds 0-3: 0.39 / 0.30 / 1.59 / 3.64 mm
    # without, 0.22 / 0.14 / 0.70 / 0.64 mm with); switching the pooling off fails this
    points, labels, target = centroid_room("tum", 10)
    pooled = _errors(points, labels, target, 4, n=0)  # (raw halves)
    own = _errors(points, labels, target, 4, n=0, pooled_source_covariance=False)
    ratio = pooled / own
    assert np.median(ratio) < 0.7 and np.mean(pooled) < 0.6 * np.mean(own), (pooled, own)


@pytest.mark.parametrize("lookup", ["table", "columns", "sorted"])
def test_same_cell_matches_the_cell_lookup(rng, lookup, monkeypatch):
    """The one-pass kernel gives the pairs of the cell lookup: each flagged pair's source
    point, moved, matched to its own cell's map point (of the target's label, with labels),
    distances recomputed, others untouched; with the dense table, with the sorted cells
    searched by column (a box too large for the table) and with the sorted cells alone."""
    from dataclasses import replace

    from estimation.registration import correspondences
    from estimation.registration.correspondences import Correspondences, grid_cells

    room = thick_room(rng)
    map_points = centroids(room, 0.03, np.array([0.011, -0.007, 0.02]))
    grid = voxel_grid(map_points)
    assert grid.table is not None and grid.columns is None
    if lookup == "columns":  # the box's cells beyond the table, its columns within it
        monkeypatch.setattr(correspondences, "GRID_TABLE_CELLS", int(np.prod(grid.dims[:2])))
        grid = grid_cells(map_points, grid.pitch, grid.origin)
        assert grid.table is None and grid.columns is not None
    elif lookup == "sorted":
        grid = replace(grid, table=None)
    labels = rng.integers(0, 3, len(map_points)).astype(np.int64)
    source = room[rng.choice(len(room), 3000)] + rng.normal(scale=0.01, size=(3000, 3))
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.01, -0.02, 0.005), [0.01, 0.0, -0.01]).matrix()
    source_idx = np.arange(3000)
    target_idx = rng.integers(0, len(map_points), 3000)
    corr = Correspondences(source_idx, target_idx, rng.uniform(0, 1, 3000),
                           rng.uniform(0, 0.1, 3000), 3000)
    aligned = rng.random(3000) < 0.7
    moved = (source @ T[:3, :3].T + T[:3, 3])
    hit, rows = grid.lookup(moved)
    for with_labels in (False, True):
        out = grid.same_cell(T, source, corr, aligned, map_points,
                             labels if with_labels else None)
        move = aligned & hit
        if with_labels:
            move &= labels[np.maximum(rows, 0)] == labels[target_idx]
        expected = np.where(move, rows, target_idx)
        assert move.sum() > 200
        # (a point within a hair of a cell wall: the one-pass transform may round across it)
        assert np.mean(out.target_idx == expected) > 0.999
        same = out.target_idx == expected
        np.testing.assert_allclose(
            out.distances[same & move],
            np.linalg.norm(map_points[expected] - moved, axis=1)[same & move], rtol=1e-12)
        np.testing.assert_array_equal(out.distances[~move & same], corr.distances[~move & same])
        np.testing.assert_array_equal(out.weights, corr.weights)
        np.testing.assert_array_equal(out.source_idx, corr.source_idx)


@pytest.mark.parametrize("pairs", [3000, 2 * gicp.SPLIT_PAIRS + 1])
def test_one_whitening_per_centroid_is_each_pairs_own(rng, pairs):
    """The pairs of one centroid share its covariance and their pooled one, so their
    whitening is computed once and shared: the same numbers as each pair's own, with few
    and with many pairs (half of them on the second thread)."""
    from estimation.registration.correspondences import Correspondences
    from estimation.registration.factors import pooled_covariances, whitening_rows

    room = thick_room(rng)
    map_points = centroids(room, 0.03, np.array([0.011, -0.007, 0.02]))
    source = room[rng.choice(len(room), 5000, replace=False)]
    reg = Registration(source, map_points, RegistrationConfig())
    reg._grid = voxel_grid(map_points)
    assert reg._grid is not None
    # a few hundred centroids, each matched by many pairs, some by one
    target_idx = rng.integers(0, 400, pairs)
    source_idx = rng.integers(0, len(source), pairs)
    corr = Correspondences(source_idx, target_idx, np.ones(pairs), np.zeros(pairs), len(source))
    R = gtsam.Rot3.Rodrigues(0.3, -0.2, 0.1).matrix()
    cov_t, cov_s = reg.target_cov.all(), reg.source_cov.all()
    pooled, rows = pooled_covariances(cov_s, source_idx, target_idx, len(map_points))
    expected = whitening_rows(cov_t, target_idx, pooled, rows, R)
    np.testing.assert_array_equal(reg._whitening(corr, R), expected)
    # (not each point's own covariance: the pooling is in force)
    assert not np.allclose(expected, whitening_rows(cov_t, target_idx, cov_s, source_idx, R))


def test_the_resultants_are_those_of_each_frequency_taken_alone(rng):
    """The grid search's resultant lengths, turned from one frequency to the next in one
    kernel, are |mean of w exp(2 pi i f x)| of each frequency computed afresh (weighted
    and not)."""
    from estimation.registration.correspondences import _resultants

    x = rng.normal(scale=2.0, size=(3000, 3))
    weights = rng.uniform(0.0, 1.0, size=(3000, 3))
    frequencies = np.linspace(20.0, 45.0, 60)
    for w in (None, weights):
        share = np.full(x.shape, 1.0 / len(x)) if w is None else w / w.sum(axis=0)
        expected = np.array([np.abs((share * np.exp(2j * np.pi * f * x)).sum(axis=0))
                             for f in frequencies])
        np.testing.assert_allclose(_resultants(x, frequencies, w), expected, rtol=1e-9,
                                   atol=1e-12)
