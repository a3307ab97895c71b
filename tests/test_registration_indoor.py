"""Registration on a real RGB-D room against its 3 cm voxel map (issue 14's held-out setting).

The room is fused from the real TUM fr1/rpy depth frames in shared/data/rgbd
(benchmarks/registration_indoor.py builds the same case; every trial is another raw half of
the room with 5 mm noise and 10 % wrong labels, moved by a known transform, against the same
map of voxel centroids). Checked: the forward estimate is kept because the source lies inside
the map (the midpoint, forced, is far less consistent and less accurate there), and the
covariance is trusted there only with the map-representation term; the
re-matched bread is the estimator's actual response (its Newton step from the truth predicts
the error; the fixed-association one does not); Semantic-ICP's label noise keeps wrong
one-hot labels from pulling it off (with the boundary gate off: the gate removes most of that
pull itself); a part registered to the map of an overlapping part (two scans of a room) stays
off the map's edge with the boundary gate and is pulled into the overlap without it. The
covariance is consistent there (mean NEES 4.84, band [4.82, 7.30]) since the
map-representation term scales with the map's local surface thickness (thirteenth round):
this room's surfaces are thinner than the benchmark's rooms' (fused from every 10th frame,
not every 5th), and the term in pitches alone left it at 4.4, below the band (8.2 above it
without the term).
"""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.registration import D_FINAL, OFFSETS, register_ours
from benchmarks.registration_indoor import (
    half_room_source,
    labelled,
    phase_covariance,
    phase_maps,
    room_cloud,
    room_part_source,
    voxel_map,
)
from estimation.covariance import check_consistency, crossed_bootstrap_interval, nees
from estimation.registration import Registration, RegistrationConfig, gicp, pose_error
from estimation.registration.correspondences import SemanticIndex, semantic_correspondences
from estimation.registration.gicp import INSIDE_TRUSTED_COVERAGE
from estimation.registration.metrics import offset_about_centroid

N_TRIALS = 30


@pytest.fixture(scope="module")
def room(centroid_room):
    return centroid_room("tum", 10)


def trials(room, n, **options):
    points, labels, target = room
    out = []
    for seed in range(n):
        rng = np.random.default_rng(seed)
        source, T_gt = half_room_source(points, labels, rng)
        metres, degrees, d0 = OFFSETS["small"]
        init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
        result, _ = register_ours(source, target, init, (d0, D_FINAL), **options)
        out.append((result, pose_error(result.T, T_gt)))
    return out


@pytest.fixture(scope="module")
def forward(room):
    return trials(room, N_TRIALS)


@pytest.mark.slow
def test_the_forward_estimate_is_kept_when_the_source_lies_inside_the_map(forward):
    for r, _ in forward:
        assert r.converged and not r.diagnostic.symmetric
        covered, covering = r.diagnostic.overlap
        assert covered >= gicp.INSIDE_COVERAGE and covering < covered - gicp.INSIDE_MARGIN


@pytest.mark.slow
def test_inside_the_map_the_covariance_is_trusted_only_with_the_map_term(room, forward):
    # without the map-representation term (map_error) the mean NEES was 8.2 here, 7.7-9.0
    # on the benchmark's rooms, 25-31 with dense sources: such runs stay flagged; with it
    # (4.4 here, 4.9-6.7 there) a run whose source lies wholly on the map's surfaces is
    # trusted (tests/test_registration_map_error.py: a wrong basin is not)
    for r, _ in forward:
        assert r.diagnostic.map_error is not None and r.diagnostic.trusted
        assert r.diagnostic.correlation_ratio <= RegistrationConfig().trust_ratio
    assert not any(r.diagnostic.trusted for r, _ in trials(room, 3, map_error=None))


@pytest.mark.slow
def test_the_rematched_bread_is_the_estimators_response_on_the_room(room):
    # The estimate is the root of the score sum F with the correspondences re-matched at the
    # pose itself: from the truth, a Newton step with the re-matched bread D predicts where
    # the estimator ends (measured: mean Mahalanobis miss 0.5 against the error's 7.5; 1.4
    # with the fixed-association Hessian A). So the covariance's gap on this room is in the
    # meat (the score sum's spread), not in the bread.
    # (the nearest-centroid estimator: same-voxel matching, on by default on this map, is
    # much less driven by re-matching, so its bread is close to A)
    points, labels, target = room
    nearest = trials(room, 6, voxel_matching=None)
    miss_d, miss_a, size = [], [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        source, T_gt = half_room_source(points, labels, rng)
        result, err = nearest[seed]
        reg = Registration(source.points, target.points, RegistrationConfig(
            max_correspondence_distance=D_FINAL, symmetric=False, voxel_matching=None))
        reg.run(T_gt)  # (the kernel's scale at the truth)
        sol = reg.solution_terms(T_gt, D_FINAL)
        summed = gicp.cluster_sums(sol.tgt, sol.scores, reg.cluster_size(T_gt, sol.corr))
        fixed = np.linalg.solve(sol.A, np.linalg.solve(sol.A, summed.T @ summed).T)
        D = reg.reassociation_hessian(T_gt, D_FINAL, sol, fixed)
        F = sol.scores.sum(axis=0)
        moved = -err.tangent  # T = T_gt Exp(moved), to first order
        P = result.covariance
        miss_d.append(nees(moved + np.linalg.solve(D, F), P))
        miss_a.append(nees(moved + np.linalg.solve(sol.A, F), P))
        size.append(nees(moved, P))
    assert np.mean(miss_d) < 0.35 * np.mean(size), (miss_d, miss_a, size)
    assert np.mean(miss_d) < 0.5 * np.mean(miss_a), (miss_d, miss_a, size)


@pytest.mark.slow
def test_the_midpoint_would_be_far_less_consistent_there(room, monkeypatch):
    # negative control of the overlap rule: the midpoint forced where it does not apply.
    # Without the boundary gate (measured: mean NEES 33 against 7-12 for the forward
    # estimate, and less accurate) the reverse direction's pairs beyond the part's edge pull
    # it; the gate removes most of that (8.9 against 7.8), so the rule is checked without it.
    forward = trials(room, 10, boundary_gate=None)
    monkeypatch.setattr(gicp, "source_inside_target", lambda *overlap: False)
    out = trials(room, 10, boundary_gate=None)
    assert all(r.diagnostic.symmetric for r, _ in out)
    mid = np.array([nees(err.tangent, r.covariance) for r, err in out])
    fwd = np.array([nees(err.tangent, r.covariance) for r, err in forward])
    assert not check_consistency(mid, dof=6).passed
    assert mid.mean() > 2.0 * fwd.mean(), (mid.mean(), fwd.mean())
    assert np.median([a.d_se3 / b.d_se3 for (_, a), (_, b) in zip(out, forward)]) > 1.2


@pytest.mark.slow
def test_the_boundary_gate_keeps_an_overlapping_part_off_the_maps_edge(room):
    # Two scans of a room: a part (15k raw points) against the 3 cm map of a part it
    # overlaps by a 1 m slab. Without the gate the points beyond the map's edge are matched
    # to the edge and pull the estimate into the overlap (benchmark: median 25 mm; with the
    # gate 5.9 mm; Open3D GICP 109 mm; benchmarks/registration_indoor.py --setting part).
    points, labels, _ = room
    ratios = []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        source, T_gt, part = room_part_source(points, labels, rng)
        target = labelled(*voxel_map(points[part], labels[part], "centroids"))
        metres, degrees, d0 = OFFSETS["small"]
        init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
        gated, _ = register_ours(source, target, init, (d0, D_FINAL))
        plain, _ = register_ours(source, target, init, (d0, D_FINAL), boundary_gate=None)
        if gated.converged and plain.converged:
            ratios.append(pose_error(gated.T, T_gt).d_se3 / pose_error(plain.T, T_gt).d_se3)
    assert len(ratios) >= 4, ratios
    assert np.median(ratios) < 0.5, ratios


@pytest.mark.slow
def test_covariance_is_consistent_on_a_real_room_against_its_voxel_map(forward):
    # measured 4.84 (median 4.17), band [4.82, 7.30]; the map term unscaled by the map's
    # thickness gave 4.4, no map term 8.2, before same-voxel matching and the crossing term
    # 9.6 (docs/registration_notes.md)
    values = np.array([nees(err.tangent, r.covariance) for r, err in forward])
    assert not check_consistency(np.array(
        [nees(err.tangent, 0.1 * r.covariance) for r, err in forward]), dof=6).passed
    check = check_consistency(values, dof=6)
    assert check.passed, check


@pytest.mark.slow
def test_the_gap_is_where_the_voxel_grid_cuts_the_room(room, forward):
    # the diagnosis of the room gap (docs/registration_notes.md, "Where the room gap comes
    # from"): the room's own points voxelised again at other grid phases move the estimate
    # by about its error; that spread, added to the reported covariance, closes most of the
    # gap (measured on the benchmark's rooms: TUM 11.9 -> 7.3, ICL-NUIM 460 -> 12.9)
    points, labels, _ = room
    maps = phase_maps(points, labels, "centroids", 8)
    plain, with_phase, spread = [], [], []
    for seed, (r, err) in enumerate(forward[:6]):
        source, _ = half_room_source(points, labels, np.random.default_rng(seed))
        C = phase_covariance(source.points, maps, r.T)
        plain.append(nees(err.tangent, r.covariance))
        with_phase.append(nees(err.tangent, r.covariance + C))
        noise = r.covariance - r.diagnostic.model_covariance  # the point-noise sandwich
        spread.append(np.trace(C[3:, 3:]) / np.trace(noise[3:, 3:]))
        plain[-1], with_phase[-1] = nees(err.tangent, noise), nees(err.tangent, noise + C)
    assert np.median(spread) > 0.25, spread  # the phase alone moves it by half a sigma or more
    # against the point-noise sandwich (the model terms, which cover the phase in part, left
    # out), measured on these 6 trials: 8.0 -> 4.5 before the cell-crossing term, 6.8 -> 5.1
    # with it; the tenth round's kernel schedule moved it between 6.8 -> 5.1 and 7.1 -> 5.6
    assert np.mean(with_phase) < 0.85 * np.mean(plain), (plain, with_phase)


@pytest.mark.slow
def test_label_noise_keeps_wrong_labels_from_pulling_semantic_icp(room):
    # with the boundary gate off: a wrongly labelled point matched to a same-class point far
    # along the surface is also what the gate removes (with it: 0.99 instead of < 0.9)
    auto = trials(room, 10, semantic=True, boundary_gate=None)
    none = trials(room, 10, semantic=True, label_noise=0.0, boundary_gate=None)
    ratio = np.median([a.d_se3 / b.d_se3 for (_, a), (_, b) in zip(auto, none)])
    assert ratio < 0.9, ratio


def test_label_noise_gives_a_wrongly_labelled_point_its_nearest_neighbour():
    # target: class 0 at the origin, class 1 at 0.15 m; the source point sits on the class-0
    # point but is labelled 1 (wrong, one-hot)
    index = SemanticIndex(np.array([[0.0, 0, 0], [0.15, 0, 0]]), np.eye(2))
    moved = np.array([[0.001, 0, 0]])
    nearest = (np.array([0.001]), np.array([0]))
    kwargs = dict(d_max=0.2, residual_sigma=0.01, nearest=nearest, posterior=True)
    plain = semantic_correspondences(moved, np.array([[0.0, 1.0]]), index, **kwargs)
    assert list(plain.target_idx) == [1]  # the labels as given: all weight on the far point
    noisy = semantic_correspondences(moved, np.array([[0.0, 1.0]]), index, label_noise=0.1,
                                     **kwargs)
    assert noisy.target_idx[np.argmax(noisy.weights)] == 0
    assert noisy.weights.max() > 0.99


def test_label_noise_is_checked():
    from estimation.errors import EstimationError

    for bad in (-0.1, 1.0, "often"):
        with pytest.raises(EstimationError, match="label_noise"):
            RegistrationConfig(label_noise=bad)


def test_object_labels_split_the_geometric_classes_into_coherent_segments():
    """``--classes N`` (stand-in for object labels): every class used, each segment (one
    geometric class in one 0.6 m cube) one label, the geometric class recoverable mod 4."""
    from benchmarks.registration_indoor import N_GEOMETRIC, main, object_labels

    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 6.0, (20000, 3))
    labels = rng.integers(0, N_GEOMETRIC, len(points))
    out = object_labels(points, labels, 24)
    assert out.min() >= 0 and out.max() < 24 and len(np.unique(out)) == 24
    np.testing.assert_array_equal(out % N_GEOMETRIC, labels)
    cube = np.floor(points / 0.6).astype(np.int64)
    key = (cube[:, 0] * 1000 + cube[:, 1]) * 1000 + cube[:, 2]
    for k in np.unique(key)[:50]:
        for c in range(N_GEOMETRIC):
            assert len(np.unique(out[(key == k) & (labels == c)])) <= 1
    np.testing.assert_array_equal(object_labels(points, labels, N_GEOMETRIC), labels)
    with pytest.raises(SystemExit):
        main(["--classes", "2"])


def test_source_points_zero_takes_the_whole_half():
    """``--source-points 0``: every point of the half (a raw half-room cloud); N: N of them."""
    from benchmarks.registration_indoor import main

    rng = np.random.default_rng(0)
    points = rng.uniform(-3.0, 3.0, (5000, 3))
    labels = rng.integers(0, 4, len(points))
    whole, T = half_room_source(points, labels, np.random.default_rng(1), 0)
    some, _ = half_room_source(points, labels, np.random.default_rng(1), 1000)
    assert len(some.points) == 1000 and 2000 < len(whole.points) < 3000
    # every source point, moved back by the truth, lies within the noise of a room point
    back = whole.points @ T[:3, :3].T + T[:3, 3]
    from scipy.spatial import cKDTree
    assert cKDTree(points).query(back)[0].max() < 0.05
    with pytest.raises(SystemExit):
        main(["--source-points", "-1"])


def test_noise_zero_gives_the_maps_own_points():
    """``--noise 0``: the half is the room's points themselves, moved by the truth; the
    default adds 5 mm per axis."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-3.0, 3.0, (5000, 3))
    labels = rng.integers(0, 4, len(points))
    exact, T = half_room_source(points, labels, np.random.default_rng(1), 0, noise=0.0)
    noisy, _ = half_room_source(points, labels, np.random.default_rng(1), 0)
    from scipy.spatial import cKDTree

    def back(cloud):  # into the room's frame by the truth
        return cloud.points @ T[:3, :3].T + T[:3, 3]

    assert cKDTree(points).query(back(exact))[0].max() < 1e-9
    assert 0.004 < (back(noisy) - back(exact)).std() < 0.006


def test_wrong_blocks_relabel_whole_blocks_of_the_same_half():
    """``--wrong-blocks``: the same points, truth and start as the per-point draw; about a
    tenth of the labels wrong, but whole blocks of them, each block shifted to one other
    class (a segmentation's errors come in regions)."""
    from benchmarks.registration_indoor import N_CLASSES, block_flips, main

    rng = np.random.default_rng(0)
    points = rng.uniform(-3.0, 3.0, (20000, 3))
    labels = rng.integers(0, N_CLASSES, len(points))
    each, T = half_room_source(points, labels, np.random.default_rng(1), 0)
    blocks, T_b = half_room_source(points, labels, np.random.default_rng(1), 0,
                                   wrong_blocks=0.5)
    np.testing.assert_array_equal(blocks.points, each.points)
    np.testing.assert_array_equal(T_b, T)
    # the wrong ones, found as in the benchmark: the labels unlike the room point's own
    back = blocks.points @ T[:3, :3].T + T[:3, 3]
    from scipy.spatial import cKDTree
    own = labels[cKDTree(points).query(back)[1]]
    wrong_b = blocks.probs.argmax(axis=1) != own
    wrong_e = each.probs.argmax(axis=1) != own
    assert 0.05 < wrong_b.mean() < 0.15 and 0.08 < wrong_e.mean() < 0.12
    # in blocks, a wrong label's nearest neighbour in the half is often wrong too (0.68 here:
    # blocks of about six points); point by point, about a tenth of them
    near = cKDTree(back).query(back, k=2)[1][:, 1]
    assert wrong_b[near][wrong_b].mean() > 0.5 and wrong_e[near][wrong_e].mean() < 0.2
    # block by block: a flipped block holds wrong labels only, all with one class shift
    flip, shift = block_flips(points[:5000], 0.1, 0.5, np.random.default_rng(2))
    cube = np.floor((points[:5000] + np.random.default_rng(2).uniform(0.0, 0.5, 3)) / 0.5)
    _, inverse = np.unique(cube, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    for block in np.unique(inverse[flip]):
        inside = inverse == block
        assert flip[inside].all()
        assert len(np.unique(shift[inside[flip]])) == 1
    assert np.all((shift >= 1) & (shift < N_CLASSES))
    # about a tenth of the blocks
    assert 0.02 < len(np.unique(inverse[flip])) / len(np.unique(inverse)) < 0.2
    for argv in (["--wrong-blocks", "0"], ["--wrong-blocks", "inf"]):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2


@pytest.mark.parametrize("argv", [["--map-error", "big"], ["--lattice-noise", "5 mm"],
                                  ["--rooms", "tum,kitchen"], ["--noise", "-0.001"],
                                  ["--noise", "nan"],
                                  ["--noise", "0.005", "--source-frames", "other"],
                                  ["--coarse", "random"], ["--frames", "50"],
                                  ["--frames", "50:10"], ["--frames", "0:50", "--rooms", "scan"],
                                  ["--map-phases", "0"],
                                  ["--map-phases", "2", "--map-phase", "random"],
                                  ["--map-phases", "2", "--setting", "part"],
                                  ["--first-trial", "-1"], ["--systematic-sigma", "-1"],
                                  ["--systematic-sigma", "1,2"]])
def test_benchmark_refuses_a_bad_option(argv, capsys):
    from benchmarks.registration_indoor import main

    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert argv[0] in capsys.readouterr().err


@pytest.mark.parametrize("coarse, sampling", [("strided", False), ("normals", True)])
def test_benchmark_coarse_option_sets_the_subset(coarse, sampling, monkeypatch):
    """``--coarse strided``: ours with the evenly strided coarse subset (the A/B of
    docs/registration_notes.md, "Normal-space sampling of the coarse subset")."""
    import benchmarks.registration_indoor as bench
    from estimation.registration import gicp

    monkeypatch.setattr(gicp, "NORMAL_SPACE_SAMPLING", True)  # restored after the test
    seen = []

    class ReachedError(Exception):
        pass

    def room_cloud(*args, **kwargs):  # the first thing main does with the option parsed
        seen.append(gicp.NORMAL_SPACE_SAMPLING)
        raise ReachedError

    monkeypatch.setattr(bench, "room_cloud", room_cloud)
    with pytest.raises(ReachedError):
        bench.main(["--rooms", "tum", "--coarse", coarse])
    assert seen == [sampling]


def test_frames_option_fuses_the_room_from_those_frames_only(monkeypatch):
    """``--frames START:STOP``: the room (and with ``--source-frames other`` the halves' scan)
    from frames START .. STOP - 1: another view of the room from the same sequence. Checked on
    ICL-NUIM: one frame of every 50 before 50 is frame 0 alone."""
    import benchmarks.registration_indoor as bench

    first, _ = room_cloud("icl", step=50, stop=50)
    both, _ = room_cloud("icl", step=50)
    assert 0 < len(first) < len(both)
    only_first, _ = room_cloud("icl", step=100)
    np.testing.assert_array_equal(first, only_first)
    seen = []

    class ReachedError(Exception):
        pass

    def fake_room_cloud(name, step, **kwargs):
        seen.append((step, kwargs))
        if len(seen) == 2:
            raise ReachedError
        return np.zeros((1, 3)), np.zeros(1, dtype=np.int64)

    monkeypatch.setattr(bench, "room_cloud", fake_room_cloud)
    with pytest.raises(ReachedError):
        bench.main(["--rooms", "tum", "--frames", "30:90", "--source-frames", "other"])
    assert seen == [(10, {"start": 30, "stop": 90}), (10, {"start": 35, "stop": 90})]


def test_a_shifted_grid_moves_the_cell_walls():
    """``voxel_map(..., shift=s)``: the cell walls at k pitch - s; no shift is the plain grid."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 1.0, (4000, 3))
    labels = rng.integers(0, 4, len(points))
    plain = voxel_map(points, labels, "centres")
    np.testing.assert_array_equal(voxel_map(points, labels, "centres", shift=np.zeros(3))[0],
                                  plain[0])
    shift = np.array([0.01, 0.02, 0.005])
    centres, _ = voxel_map(points, labels, "centres", shift=shift)
    np.testing.assert_allclose(np.mod(centres + shift, 0.03), 0.015, atol=1e-9)
    # a centroid lies in its own cell of the shifted grid
    centroids, _ = voxel_map(points, labels, "centroids", shift=shift)
    assert len(centroids) == len(centres)
    cells = {tuple(c) for c in np.floor((centres + shift) / 0.03).astype(int)}
    assert {tuple(c) for c in np.floor((centroids + shift) / 0.03).astype(int)} == cells


def test_first_trial_sets_the_trials_seeds(monkeypatch):
    """``--first-trial K``: every map's cell draws its trials from seeds K, K + 1, ...;
    ``--systematic-sigma`` reaches ours' config."""
    import benchmarks.registration_indoor as bench

    rng = np.random.default_rng(0)
    monkeypatch.setattr(bench, "room_cloud", lambda *a, **k: (rng.uniform(0, 2, (500, 3)),
                                                             rng.integers(0, 4, 500)))
    monkeypatch.setattr(bench, "register_ours", lambda *a, **k: None)
    seeds = []

    class StopError(Exception):
        pass

    def run_cell(*args, seed0=0, ours=None, **kwargs):
        seeds.append((seed0, ours.get("systematic_sigma")))
        raise StopError

    monkeypatch.setattr(bench, "run_cell", run_cell)
    for argv, seed in ((["--first-trial", "6"], (6, None)), ([], (0, None)),
                       (["--systematic-sigma", "0.002"], (0, 0.002)),
                       (["--systematic-sigma", "0.001,0,0.003"], (0, (0.001, 0.0, 0.003)))):
        with pytest.raises(StopError):
            bench.main(["--rooms", "tum", "--maps", "centroids", *argv])
        assert seeds.pop() == seed


def recorded_shifts(bench, monkeypatch) -> list:
    """The ``shift`` of every ``voxel_map`` call the benchmark makes from now on."""
    calls = []
    plain = bench.voxel_map

    def recording(*args, **kwargs):
        calls.append(kwargs.get("shift"))
        return plain(*args, **kwargs)

    monkeypatch.setattr(bench, "voxel_map", recording)
    return calls


def test_random_map_phase_gives_each_trial_its_own_map(room, monkeypatch, capsys):
    """``--map-phase random``: each trial's map is voxelised with its own grid phase, the
    trial's source as with one fixed map; the report splits off the trials' common error."""
    import benchmarks.registration_indoor as bench

    points, labels, _ = room
    calls = recorded_shifts(bench, monkeypatch)
    cells = {phase: bench.run_cell(points, labels, "centroids", "small", 2, ["gicp-se3"],
                                   source_points=3000, map_phase=phase)
             for phase in ("fixed", "random")}
    assert len(calls) == 3 and calls[0] is None  # one map for "fixed", one per trial
    assert calls[1] is not None and not np.allclose(calls[1], calls[2])
    fixed, random = (cells[p]["rows"]["gicp-se3"] for p in ("fixed", "random"))
    for a, b in zip(fixed, random):
        assert a["error_map"] != b["error_map"]  # another map, the same source otherwise
    for row in fixed + random:  # (--json) what the trust rules read, beside the verdict
        covered, _ = row["overlap"]
        assert np.isfinite(row["correlation_ratio"]) and 0.0 <= row["off_surface"] <= 1.0
        assert np.isnan(row["direction_gap"])  # (inside the map: one direction)
        assert row["trusted"] == (covered >= INSIDE_TRUSTED_COVERAGE
                                  and row["off_surface"] <= RegistrationConfig().trust_off_surface)
    cells["fixed"]["rows"]["open3d-gicp"] = fixed  # the report's reference column
    bench.report("tum", "centroids", "small", cells["fixed"])
    assert "about the common error of its 2 runs within 0.1 m" in capsys.readouterr().out


def test_map_phases_register_every_trial_against_each_map(room, monkeypatch, capsys):
    """``--map-phases M``: the same trials against M maps (the default grid, then random
    grid phases); each map's mean NEES, how many lie inside the band, and the mean over all."""
    import benchmarks.registration_indoor as bench

    points, labels, _ = room
    assert bench.map_shift(0) is None
    shifts = [bench.map_shift(i) for i in (1, 2)]
    assert all(np.all((0.0 <= s) & (s < 0.03)) for s in shifts)
    assert not np.allclose(*shifts) and np.array_equal(shifts[0], bench.map_shift(1))
    calls = recorded_shifts(bench, monkeypatch)
    cells = [bench.run_cell(points, labels, "centroids", "small", 2, ["gicp-se3"],
                            source_points=3000, map_index=i) for i in (0, 1)]
    assert calls[0] is None and np.array_equal(calls[1], shifts[0])
    rows = [cell["rows"]["gicp-se3"] for cell in cells]
    for a, b in zip(*rows):
        assert a["error_map"] != b["error_map"]  # another map, the same trial otherwise
    bench.report_maps(cells)
    out = capsys.readouterr().out
    values = [[r["nees"] for r in map_rows] for map_rows in rows]
    assert f"mean NEES per map {np.mean(values[0]):.2f} {np.mean(values[1]):.2f}" in out
    assert f"over every map and run {np.mean(values):.2f}" in out
    low, high = crossed_bootstrap_interval(np.array(values))
    assert "(crossed bootstrap; runs of one map share its grid phase" in out
    assert f"[{low:.2f}, {high:.2f}]: 6 " in out
    np.testing.assert_array_equal(bench.nees_by_map_and_trial(cells, "gicp-se3"), values)
    assert "gicp-se3 per trial over the maps, mean NEES" in out


def test_trial_splits_part_each_trials_error_common_to_the_maps_from_the_phases():
    """``report_maps``' per-trial split: a trial registered against every map keeps its half,
    noise and start, so its error common to the maps is that draw and its variation about it
    the grid phase's. Runs off the right basin are left out."""
    import benchmarks.registration_indoor as bench
    from estimation.covariance import nees_about_common

    rng = np.random.default_rng(5)
    shared = rng.normal(size=6)  # trial 0: the same error against every map
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)

    def row(error, t_err=0.001):
        return {"error_map": list(error * np.sqrt(np.diag(cov))), "covariance_map": cov,
                "t_err_m": t_err, "converged": True, "nees": 0.0}

    cells = [{"rows": {"gicp-se3": [row(shared), row(rng.normal(size=6)),
                                    row(rng.normal(size=6), t_err=0.5 if i == 2 else 0.001)]}}
             for i in range(4)]
    splits = bench.trial_splits(cells, "gicp-se3")
    assert [(t, n) for t, _, n in splits] == [(0, 4), (1, 4), (2, 3)]
    first = splits[0][1]
    assert first.about_common == pytest.approx(0.0, abs=1e-9)
    assert first.common_part == pytest.approx(float(shared @ shared))
    errors = np.array([c["rows"]["gicp-se3"][1]["error_map"] for c in cells])
    expected = nees_about_common(errors, np.broadcast_to(cov, (4, 6, 6)))
    assert splits[1][1].about_common == pytest.approx(expected.about_common)
    assert splits[1][1].mean == pytest.approx(float(nees(errors, np.broadcast_to(
        cov, (4, 6, 6))).mean()))
