"""Same-voxel matching where the source overlaps a voxel-centroid map only in part
(``RegistrationConfig.partial_voxel_matching``, issue 14, fifteenth round).

Two scans of a room: a raw part against the 3 cm centroid map of a part it overlaps. With the
nearest centroid the map's aliasing (a surface layer that a grid plane cuts is stored as two
sheets of centroids) biases the estimate, and the covariance misses it: on the real ICL-NUIM
office the right basins' mean NEES was about 500. From the nearest-neighbour fixed point on,
the iterations go on with the cells, and the estimate is that one direction's; the direction
gap (the test for another basin) is measured at the nearest-neighbour fixed point, where both
directions match alike. Measured (docs/registration_notes.md, "Partial overlaps matched by cell").
"""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.registration import D_FINAL, OFFSETS, register_ours
from benchmarks.registration_indoor import labelled, room_part_source, voxel_map
from benchmarks.registration_real import DEFAULT_OCTOMAP, scan_setting
from estimation.covariance import nees
from estimation.errors import EstimationError
from estimation.registration import RegistrationConfig, gicp, pose_error
from estimation.registration.correspondences import (
    _resultants,
    grid_sample,
    looks_voxelised,
    sheets_possible,
)
from estimation.registration.metrics import offset_about_centroid


@pytest.fixture(scope="module", autouse=True)
def strided_coarse_subset():
    # conftest.strided_coarse_subset for the whole module (its starts are module fixtures):
    # half of the subset over the normals' directions finds start 1, 6 mm off but
    # unconverged, and loses start 0
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gicp, "NORMAL_SPACE_SAMPLING", False)
        yield


@pytest.fixture(scope="module")
def office(centroid_room):
    return centroid_room("icl", 10)


def part_trial(points, labels, seed, **options):
    """(result with the cells, result without, T_target_source) of one part-against-part
    trial of the benchmark (``--setting part``, small offset)."""
    rng = np.random.default_rng(seed)
    source, T_gt, part = room_part_source(points, labels, rng)
    target = labelled(*voxel_map(points[part], labels[part], "centroids"))
    metres, degrees, d0 = OFFSETS["small"]
    init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
    cells, _ = register_ours(source, target, init, (d0, D_FINAL), **options)
    nearest, _ = register_ours(source, target, init, (d0, D_FINAL),
                               partial_voxel_matching=False, **options)
    return cells, nearest, T_gt


@pytest.fixture(scope="module")
def right_basins(office):
    # the starts of the office's part setting that end in the right basin (the others end
    # 0.3-0.9 m off with either matching and are flagged)
    points, labels, _ = office
    return [part_trial(points, labels, seed) for seed in (0, 2, 8, 9)]


def test_a_partial_overlap_is_matched_by_cell(right_basins):
    for cells, nearest, _ in right_basins:
        d = cells.diagnostic
        assert cells.converged and d.voxel_pitch == pytest.approx(0.03, rel=1e-3)
        assert not d.symmetric and np.isfinite(d.direction_gap) and d.map_error is not None
        # the estimator before: the nearest centroid, the midpoint of both directions
        assert nearest.diagnostic.voxel_pitch is None and nearest.diagnostic.symmetric


def test_the_cells_make_the_covariance_consistent_and_the_estimate_better(right_basins):
    # measured: mean NEES 9.6 with the cells, 382 with the nearest centroid; paired error
    # ratio median 0.49 (2.7 / 4.0, 3.5 / 2.7, 1.3 / 4.3, 1.1 / 8.4 mm)
    with_cells = [nees(pose_error(c.T, T).tangent, c.covariance) for c, _, T in right_basins]
    without = [nees(pose_error(n.T, T).tangent, n.covariance) for _, n, T in right_basins]
    assert np.mean(with_cells) < 20.0, with_cells
    assert np.mean(without) > 100.0, without
    ratios = [pose_error(c.T, T).d_se3 / pose_error(n.T, T).d_se3 for c, n, T in right_basins]
    assert np.median(ratios) < 0.8, ratios
    assert all(c.diagnostic.trusted for c, _, _ in right_basins)


def test_the_gap_is_measured_where_both_directions_match_alike(right_basins):
    # at the nearest-neighbour fixed point the gap is the one the estimator had before
    # (measured 18.4 -> 20.5, 15.9 -> 16.0, 20.9 -> 27.8, 28.1 -> 26.6); between the cells'
    # estimate and a nearest-neighbour reverse it would measure the aliasing (114-509 on the
    # benchmark's office) and flag every right basin
    for cells, nearest, _ in right_basins:
        ratio = cells.diagnostic.direction_gap / nearest.diagnostic.direction_gap
        assert 0.6 < ratio < 1.6, (cells.diagnostic.direction_gap,
                                   nearest.diagnostic.direction_gap)
        assert cells.diagnostic.direction_gap < RegistrationConfig().trust_gap


def test_another_basin_is_still_flagged_by_the_gap(office):
    # start 1 ends 0.58 m off; its gap at the nearest-neighbour fixed point is 50.6
    points, labels, _ = office
    cells, _, T_gt = part_trial(points, labels, 1)
    assert pose_error(cells.T, T_gt).t_err_m > 0.1
    assert cells.diagnostic.voxel_pitch is not None
    assert cells.diagnostic.direction_gap > RegistrationConfig().trust_gap
    assert not cells.diagnostic.trusted


def scan_split(seed, **options):
    s = scan_setting(DEFAULT_OCTOMAP, seed)
    metres, degrees, d0 = s.offsets["small"]
    init = s.T_gt @ offset_about_centroid(np.random.default_rng(seed),
                                          s.source.points.mean(axis=0), metres, degrees)
    return register_ours(s.source, s.target, init, (d0, s.d_final), **options)[0]


@pytest.mark.parametrize("seed", [100, 102, 108, 113])
def test_two_voxel_maps_are_matched_as_before(seed):
    # the scan splits (both halves voxelised by Open3D): a voxelised source (102) is not
    # matched by cell; where it looks raw (a sparse scan's cells hold one point or two) the
    # map's grid is not found (100), or it is and a third of the pairs lie on surfaces
    # parallel to it, but the laser's layers are 0.04 pitches thin (108, 113: the cells there
    # gave 0.44 / 1.30 mm against 0.41 / 0.86). Either way the same bits as without the option
    a = scan_split(seed)
    b = scan_split(seed, partial_voxel_matching=False)
    assert a.diagnostic.voxel_pitch is None and a.diagnostic.symmetric
    assert np.array_equal(a.T, b.T) and np.array_equal(a.covariance, b.covariance)


def test_thin_layers_are_what_keeps_the_scan_split_off_the_cells(monkeypatch):
    # the rule's negative control (and its loose form on the map's sample, which skips the
    # grid's search: 0.03 pitch thin here, the office's parts 0.15-0.20)
    monkeypatch.setattr(gicp, "PARTIAL_CELL_THICKNESS", 0.0)
    monkeypatch.setattr(gicp, "PARTIAL_MAP_THICKNESS", 0.0)
    a = scan_split(108)
    assert a.diagnostic.voxel_pitch is not None and not a.diagnostic.symmetric


def test_the_maps_own_sample_tells_thin_layers_from_thick_ones(office):
    points, labels, _ = office
    _, _, part = room_part_source(points, labels, np.random.default_rng(0))
    office_part = voxel_map(points[part], labels[part], "centroids")[0]
    scan_target = scan_setting(DEFAULT_OCTOMAP, 108).target.points
    args = (gicp.PARTIAL_CELL_ANGLE, gicp.PARTIAL_MAP_SHARE, gicp.PARTIAL_MAP_THICKNESS)
    assert sheets_possible(grid_sample(office_part), *args)
    assert not sheets_possible(grid_sample(scan_target), *args)
    assert sheets_possible(grid_sample(scan_target), args[0], args[1], 0.0)


def test_a_voxel_map_looks_voxelised_and_a_raw_scan_does_not(office):
    points, labels, target = office
    rng = np.random.default_rng(0)
    source, _, part = room_part_source(points, labels, rng)
    assert not looks_voxelised(source.points)  # measured 0.07 (threshold 0.12)
    assert not looks_voxelised(points)
    assert looks_voxelised(target.points)  # 0.4
    assert looks_voxelised(voxel_map(points[part], labels[part], "centroids")[0])


def test_the_resultants_turn_by_products_as_by_cosines(rng):
    x = rng.uniform(-2.0, 2.0, (500, 3))
    w = rng.uniform(0.0, 1.0, (500, 3))
    f = np.linspace(20.0, 40.0, 37)
    phase = 2.0 * np.pi * f[:, None, None] * x[None]
    wn = w / w.sum(axis=0)
    direct = np.hypot((np.cos(phase) * wn).sum(axis=1), (np.sin(phase) * wn).sum(axis=1))
    assert np.allclose(_resultants(x, f, w), direct, atol=1e-12)
    plain = np.hypot(np.cos(phase).mean(axis=1), np.sin(phase).mean(axis=1))
    assert np.allclose(_resultants(x, f), plain, atol=1e-12)


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_bad_partial_voxel_matching_values_are_refused(value):
    with pytest.raises(EstimationError, match="partial_voxel_matching"):
        RegistrationConfig(partial_voxel_matching=value)


def test_a_map_whose_surfaces_cross_its_grid_keeps_the_midpoint(centroid_room, monkeypatch):
    # the TUM room: 9-18 % of the pairs lie on surfaces within 5 deg of a grid axis, below
    # PARTIAL_CELL_SHARE; there the midpoint of both directions was the more accurate (paired
    # error 1.12x with the cells, 30-35 % within 10 deg), and nothing changes
    points, labels, _ = centroid_room("tum", 10)
    cells, nearest, _ = part_trial(points, labels, 1)
    assert cells.diagnostic.voxel_pitch is None and cells.diagnostic.symmetric
    assert np.array_equal(cells.T, nearest.T)
    assert np.array_equal(cells.covariance, nearest.covariance)
    monkeypatch.setattr(gicp, "PARTIAL_CELL_SHARE", 0.0)  # the rule's negative control
    monkeypatch.setattr(gicp, "PARTIAL_MAP_SHARE", 0.0)
    cells, _, _ = part_trial(points, labels, 1)
    assert cells.diagnostic.voxel_pitch is not None and not cells.diagnostic.symmetric
