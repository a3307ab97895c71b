"""vpslam's pose graph carries what the filter used, and the map sits where the world is.

On the small simulated corridor of tests/test_vpslam.py (320x240, 11 frames, ground truth):
* every direction the filter accepted is a direction factor of the graph, with the filter's
  covariance; the saved g2o + sidecar keeps them;
* every node carries the filter's pose covariance P[:6, :6] of its step, in memory and in the
  sidecar (fails when the node covariance is dropped);
* the saved graph, optimised, stays on the ground truth, with and without its direction
  factors (fails when the VO between factor is inverted);
* the occupied voxels of map.bt are the scans' endpoints at the ground-truth poses (fails when
  the scans are inserted at the identity, or anywhere but the node poses).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipelines.cli import main


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    from perception.rgbd import CameraIntrinsics
    from perception.simulation.corridor import CorridorConfig, simulate_corridor

    out = tmp_path_factory.mktemp("corridor")
    intr = CameraIntrinsics(262.5, 262.5, 159.5, 119.5, 320, 240, 5000.0)
    assert simulate_corridor(out, CorridorConfig(seed=1, length=5.0, intrinsics=intr)) == 11
    return out


@pytest.fixture(scope="module")
def stepped(corridor):
    """VpSlam stepped by hand: the results, the filter's P after each step, the graph."""
    from perception.rgbd import TumRgbdSequence
    from pipelines.vpslam import VpSlam, VpSlamConfig

    sequence = TumRgbdSequence(corridor)
    slam = VpSlam(sequence.intrinsics, VpSlamConfig(build_map=False))
    results, filter_P = [], []
    for index in range(len(sequence)):
        results.append(slam.step(sequence[index]))
        filter_P.append(slam.filter.P[:6, :6].copy())
    return slam, results, filter_P


@pytest.fixture(scope="module")
def run(corridor, tmp_path_factory):
    out = tmp_path_factory.mktemp("vpslam")
    assert main(["vpslam", str(corridor), "-o", str(out), "--quiet"]) == 0
    return out


def _groundtruth(corridor, stamps):
    from perception.rgbd import TumRgbdSequence

    sequence = TumRgbdSequence(corridor)
    return np.array([sequence.groundtruth_at(t).matrix() for t in stamps])


def _position_rmse(T, T_gt) -> float:
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_gt[:, :3, 3]) ** 2, axis=1))))


def test_every_accepted_direction_is_a_factor_with_the_filters_covariance(stepped):
    slam, results, _ = stepped
    factors = [r for r in slam.graph.factors if r.kind == "direction"]
    accepted = [(result.index, o) for result in results for o in result.vp_outcomes
                if o.status == "updated"]
    assert len(accepted) >= 20  # the run does use directions
    assert len(factors) == len(accepted)
    for record, (index, outcome) in zip(factors, accepted):
        assert record.nodes == (index,)
        meta = record.metadata
        np.testing.assert_allclose(meta["direction_sensor"], outcome.direction_sensor,
                                   atol=1e-12)
        np.testing.assert_allclose(meta["direction_world"], outcome.direction_world, atol=1e-12)
        np.testing.assert_array_equal(meta["cov"], 0.5 * (outcome.direction_cov
                                                          + outcome.direction_cov.T))
    # a gated or initialising direction is no factor
    assert not any(o.direction_sensor is not None for r in results for o in r.vp_outcomes
                   if o.status != "updated")


def test_direction_factors_agree_with_the_filtered_poses(stepped):
    """At the filter's poses the factors' whitened errors are of the size of noise."""
    slam, _, _ = stepped
    values = slam.graph.values()
    errors = [2 * r.factor.error(values) for r in slam.graph.factors if r.kind == "direction"]
    assert np.median(errors) < 2.0  # chi-square, 2 dof: median 1.39


def test_nodes_carry_the_filters_covariance(stepped, tmp_path):
    from estimation.io import read_g2o, write_g2o

    slam, results, filter_P = stepped
    for result, P in zip(results, filter_P):
        np.testing.assert_array_equal(result.cov_pose, 0.5 * (P + P.T))
        np.testing.assert_array_equal(slam.graph.nodes[result.index].cov, result.cov_pose)
    traces = [np.trace(P[3:, 3:]) for P in filter_P]
    assert traces[-1] > 10 * traces[0]  # not a constant: the filter's own, growing
    write_g2o(tmp_path / "g.g2o", slam.graph)
    back = read_g2o(tmp_path / "g.g2o")
    for result in results:
        np.testing.assert_array_equal(back.nodes[result.index].cov, result.cov_pose)
    assert back.factor_counts() == slam.graph.factor_counts()


@pytest.mark.parametrize("method", ["lm", "isam2"])
def test_saved_graph_optimises_onto_the_groundtruth(run, corridor, tmp_path, method):
    from estimation.trajectory_io import read_trajectory

    out = tmp_path / "opt.txt"
    assert main(["graph", "optimize", str(run / "graph.g2o"), str(out), "--method",
                 method]) == 0
    stamps, T = read_trajectory(out)
    ekf_stamps, T_ekf = read_trajectory(run / "trajectory.txt")
    np.testing.assert_array_equal(stamps, ekf_stamps)
    T_gt = _groundtruth(corridor, stamps)
    smoothed, filtered = _position_rmse(T, T_gt), _position_rmse(T_ekf, T_gt)
    assert smoothed < 0.03  # 2.4 m of travel
    assert smoothed <= filtered + 0.005


def test_vo_factors_alone_reproduce_the_groundtruth_path(run, corridor, tmp_path):
    """Without its direction factors the graph is the VO chain from the first node's prior:
    it must still follow the ground truth (an inverted between factor walks away)."""
    from estimation.io import read_g2o

    graph = read_g2o(run / "graph.g2o")
    assert graph.factor_counts()["prior"] == 1
    graph.factors = [r for r in graph.factors if r.kind != "direction"]
    graph.optimize("lm")
    T_gt = _groundtruth(corridor, graph.timestamps())
    assert _position_rmse(graph.poses(), T_gt) < 0.05
    # the chain is consistent: at the optimum every VO factor is satisfied
    assert graph.error() < 1e-6


def test_map_voxels_are_the_scans_at_the_groundtruth_poses(run, corridor):
    """Occupied voxels of map.bt against the scans' endpoints put at the ground-truth poses
    with numpy (not through mapping.fuse, which the map itself uses)."""
    from scipy.spatial import cKDTree

    from estimation.io import read_scan_graph
    from mapping import OcTree

    graph = read_scan_graph(run / "graph.graph")  # node ids are frame indices
    stamps = [float(line.split()[0]) for line in (corridor / "rgb.txt").read_text().splitlines()
              if line and not line.startswith("#")]
    T_gt = _groundtruth(corridor, stamps)
    endpoints = []
    for node_id in graph.sorted_ids():
        points = np.asarray(graph.nodes[node_id].scan.points, dtype=float)
        points = points[np.linalg.norm(points, axis=1) <= 5.0]  # vpslam's max range
        endpoints.append(points @ T_gt[node_id][:3, :3].T + T_gt[node_id][:3, 3])
    endpoints = np.vstack(endpoints)
    tree = OcTree.read(run / "map.bt")
    centres = tree.occupied_voxels().centers
    assert len(centres) > 500
    distance, _ = cKDTree(endpoints).query(centres)
    assert np.mean(distance < 2 * tree.resolution) > 0.95
    distance_back, _ = cKDTree(centres).query(endpoints)
    assert np.mean(distance_back < 2 * tree.resolution) > 0.9


def test_levelling_the_world_later_moves_the_first_nodes_prior(corridor):
    """Without ground truth the world is levelled when the structure is first found; when that
    is after frame 0 the earlier nodes move, and the first node's prior must move with them
    (else the saved graph pulls them back to the old frame)."""
    from perception.rgbd import TumRgbdSequence
    from pipelines.vpslam import VpSlam, VpSlamConfig

    sequence = TumRgbdSequence(corridor)
    slam = VpSlam(sequence.intrinsics, VpSlamConfig(build_map=False, detector="normals",
                                                    world_frame="manhattan"))
    levelled_at = None
    for index in range(len(sequence)):
        frame = replace(sequence[index], T_world_camera_gt=None)
        if index < 2:  # no depth: no surface normals, the structure is found at frame 2
            frame = replace(frame, depth_m=np.zeros_like(frame.depth_m))
        slam.step(frame)
        if levelled_at is None and slam.world_frame == "manhattan":
            levelled_at = index
    assert slam.world_frame == "manhattan"
    assert levelled_at is not None and levelled_at > 0
    priors = [r for r in slam.graph.factors if r.kind == "prior"]
    assert len(priors) == 1 and priors[0].nodes == (0,)
    assert priors[0].measured.equals(slam.graph.nodes[0].pose, 1e-12)
