"""SemanticOcTree (class evidence fused with occupancy), PLY/PNG exports, and the CLI."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest

from estimation.errors import FormatError
from mapping import OcTree, SemanticOcTree
from mapping.export import save_height_slice, write_ply
from mapping.io import read_tree


def _room(rng, n=3000):
    """Points on a floor (class 0) and a wall (class 1), seen from (0, 0, 1)."""
    floor = np.c_[rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), np.zeros(n)]
    wall = np.c_[np.full(n, 2.05), rng.uniform(-2, 2, n), rng.uniform(0, 2, n)]
    pts = np.vstack([floor, wall]).astype(np.float32)
    labels = np.r_[np.zeros(n, np.int32), np.ones(n, np.int32)]
    return pts, labels


def test_semantic_occupancy_equals_octree_and_classes_fuse(rng):
    pts, labels = _room(rng)
    sem = SemanticOcTree(0.1, n_classes=3)
    plain = OcTree(0.1)
    for _ in range(3):
        noisy = labels.copy()
        flip = rng.random(len(noisy)) < 0.15
        noisy[flip] = 2
        sem.insert_point_cloud(pts, [0, 0, 1], labels=noisy)
        plain.insert_point_cloud(pts, [0, 0, 1])
    # occupancy part is exactly OcTree
    assert sem.size() == plain.size()
    assert (sem.leaves().log_odds == plain.leaves().log_odds).all()
    centres, probs = sem.occupied_voxels()
    vox = sem.occupied_voxels()
    assert probs.shape == (len(centres), 3)
    assert np.allclose(probs.sum(axis=1), 1, atol=1e-5)
    on_floor = (np.abs(centres[:, 2] - 0.05) < 1e-6) & (centres[:, 0] < 1.9)
    on_wall = centres[:, 0] > 2.0
    assert (vox.labels[on_floor] == 0).mean() > 0.95
    assert (vox.labels[on_wall] == 1).mean() > 0.95
    # negative control: with labels swapped the same check must fail
    swapped = SemanticOcTree(0.1, n_classes=3)
    swapped.insert_point_cloud(pts, [0, 0, 1], labels=1 - labels)
    assert (swapped.occupied_voxels().labels[on_floor[: len(swapped.occupied_voxels())]]
            == 0).mean() < 0.05


def test_semantic_probs_input_nan_and_ot_round_trip(rng, tmp_path):
    pts, labels = _room(rng, 500)
    probs = np.full((len(pts), 2), 0.1, np.float32)
    probs[np.arange(len(pts)), labels] = 0.9
    pts[::50] = np.nan
    sem = SemanticOcTree(0.2, n_classes=2)
    with pytest.warns(RuntimeWarning):
        sem.insert_point_cloud(pts, [0, 0, 1], probs=probs, max_range=3.0)
    path = tmp_path / "s.ot"
    sem.write_ot(path)
    back = read_tree(path)
    assert isinstance(back, SemanticOcTree) and back.n_classes == 2
    a, b = sem.occupied_voxels(), back.occupied_voxels()
    assert np.array_equal(a.probs, b.probs) and np.array_equal(a.centers, b.centers)
    assert back.to_bytes_ot() == path.read_bytes()
    data = path.read_bytes()
    with pytest.raises(FormatError):
        read_tree("t.ot", data=data[:-7])
    with pytest.raises(Exception, match="probs must be"):
        sem.insert_point_cloud(pts, [0, 0, 1], probs=probs[:, :1])


def test_ply_export_opens_in_open3d_with_labels(rng, tmp_path):
    import open3d as o3d

    pts, labels = _room(rng, 800)
    sem = SemanticOcTree(0.1, n_classes=2)
    sem.insert_point_cloud(pts, [0, 0, 1], labels=labels)
    path = tmp_path / "s.ply"
    n = write_ply(sem, path)
    pcd = o3d.t.io.read_point_cloud(str(path))
    assert pcd.point.positions.shape[0] == n == len(sem.occupied_voxels())
    assert pcd.point.label.dtype == o3d.core.int32
    assert pcd.point.colors.dtype == o3d.core.uint8
    assert np.array_equal(pcd.point.label.numpy().ravel(), sem.occupied_voxels().labels)
    header = path.read_bytes()[:400]
    assert b"property int label" in header and b"property uchar red" in header
    png = tmp_path / "s.png"
    save_height_slice(sem, png, height=0.05)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_map_is_byte_identical_to_graph2tree(shared_data, tmp_path, kernel_backend):
    from pipelines.cli import main

    graph = shared_data / "octomap" / "spherical_scan.graph"
    ref = tmp_path / "ref.bt"
    subprocess.run(["graph2tree", "-i", str(graph), "-o", str(ref), "-res", "0.05", "-m", "4"],
                   check=True, capture_output=True)
    for ext, ref_path in ((".bt", ref), (".ot", tmp_path / "ref.bt.ot")):
        out = tmp_path / f"ours{ext}"
        assert main(["map", str(graph), "-r", "0.05", "--max-range", "4", "-o", str(out)]) == 0
        assert out.read_bytes() == ref_path.read_bytes()
    # octree info / convert / export
    assert main(["octree", "info", str(tmp_path / "ours.bt")]) == 0
    assert main(["octree", "convert", str(tmp_path / "ours.ot"), "-o", str(tmp_path / "c.bt")]) == 0
    assert (tmp_path / "c.bt").read_bytes() == ref.read_bytes()
    assert main(["map", str(graph), "-r", "0.1", "-o", str(tmp_path / "full.bt")]) == 0
    assert main(["octree", "export", str(tmp_path / "full.bt"), "-o",
                 str(tmp_path / "x.ply")]) == 0
    assert b"element vertex 0" not in (tmp_path / "x.ply").read_bytes()[:300]
    assert main(["octree", "export", str(tmp_path / "ours.bt"), "-o",
                 str(tmp_path / "empty.ply")]) == 0
    assert b"element vertex 0" in (tmp_path / "empty.ply").read_bytes()
    assert main(["octree", "info", str(tmp_path / "x.ply")]) == 2  # not an octree: one line
    assert main(["map", str(graph), "-r", "0.05", "-o", str(tmp_path / "x.txt")]) == 2


def test_fuse_pose_graph_with_labelled_scans(rng):
    import gtsam

    from estimation import PoseGraph, Scan
    from mapping import fuse

    pts, labels = _room(rng, 600)
    pg = PoseGraph()
    for i, x in enumerate((0.0, 0.3)):
        pose = gtsam.Pose3(gtsam.Rot3(), np.array([x, 0.0, 1.0]))
        local = (pts - np.array([x, 0.0, 1.0])).astype(np.float32)
        pg.add_node(i, pose, scan=Scan(local, labels=labels))
    sem = fuse(pg, 0.1, n_classes=2)
    plain = fuse(pg, 0.1)
    assert isinstance(sem, SemanticOcTree)
    assert sem.to_bytes_bt() == plain.to_bytes_bt()
    vox = sem.occupied_voxels()
    assert (vox.labels >= 0).mean() > 0.9


def test_cli_map_from_g2o_and_node_clouds_equals_graph_input(shared_data, tmp_path):
    from estimation.io import read_scan_graph, write_g2o
    from pipelines.cli import main

    graph_path = shared_data / "octomap" / "spherical_scan.graph"
    g = read_scan_graph(graph_path)
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for node_id, node in g.nodes.items():
        np.savetxt(clouds / f"{node_id}.xyz", node.scan.points.astype(np.float64), fmt="%.9g")
    write_g2o(tmp_path / "g.g2o", g)
    assert main(["map", str(tmp_path / "g.g2o"), "-r", "0.1", "--clouds", str(clouds), "-o",
                 str(tmp_path / "a.ot")]) == 0
    assert main(["map", str(graph_path), "-r", "0.1", "-o", str(tmp_path / "b.ot")]) == 0
    assert (tmp_path / "a.ot").read_bytes() == (tmp_path / "b.ot").read_bytes()
    assert main(["map", str(tmp_path / "g.g2o"), "-r", "0.1", "-o", str(tmp_path / "c.ot")]) == 2
