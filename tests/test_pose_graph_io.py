"""Pose-graph files: TUM, g2o (through GTSAM) and OctoMap .graph, good and bad."""
from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation import FormatError, PoseGraph, Scan
from estimation.fileio import atomic_write
from estimation.io import (
    load_node_clouds,
    read_g2o,
    read_pose_graph,
    read_scan_graph,
    read_tum,
    write_g2o,
    write_scan_graph,
    write_tum,
)
from estimation.simulation import simulate_loop_graph

SPHERICAL = "octomap/spherical_scan.graph"


def _random_pose(rng) -> gtsam.Pose3:
    return gtsam.Pose3.Expmap(rng.normal(size=6) * [1, 1, 1, 5, 5, 5])


# ---------------------------------------------------------------- TUM
finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(stamps=st.lists(st.floats(0, 2e9, allow_nan=False), min_size=1, max_size=5),
       seed=st.integers(0, 2**31))
def test_tum_round_trip_keeps_full_precision(tmp_path_factory, stamps, seed):
    rng = np.random.default_rng(seed)
    pg = PoseGraph()
    for i, stamp in enumerate(stamps):
        pg.add_node(i, _random_pose(rng), timestamp=stamp)
    path = tmp_path_factory.mktemp("tum") / "traj.txt"
    write_tum(path, pg)
    back = read_tum(path)
    for i, stamp in enumerate(stamps):
        assert back.nodes[i].timestamp == stamp  # bit-exact, not 4 decimals
        assert back.nodes[i].pose.equals(pg.nodes[i].pose, 1e-12)


def test_tum_quaternion_order_is_xyzw(tmp_path):
    path = tmp_path / "t.txt"
    # 90 degrees about z: qx qy qz qw = 0 0 sin45 cos45
    path.write_text("1305031102.175304 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    pose = read_tum(path).nodes[0].pose
    np.testing.assert_allclose(pose.rotation().matrix() @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert read_tum(path).nodes[0].timestamp == 1305031102.175304


@pytest.mark.parametrize("content, message", [
    ("1 2 3\n", "expected 8 numbers"),
    ("0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n", "NaN"),
    ("0 0 0 0 0 0 0 x\n", "could not convert"),
    ("0 0 0 0 0 0 0 2\n", "quaternion norm"),
    ("# only a comment\n", "no poses"),
])
def test_tum_bad_input_names_file_and_line(tmp_path, content, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(FormatError, match=message) as info:
        read_tum(path)
    assert str(path) in str(info.value)


def test_tum_error_gives_line_number(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"bad.txt:2"):
        read_tum(path)


# ---------------------------------------------------------------- g2o
def test_readg2o_defaults_to_2d_and_misses_3d_files(tmp_path):
    """The GTSAM gotcha our reader guards against: without is3D=True a 3-D file reads empty."""
    sim = simulate_loop_graph(np.random.default_rng(0), n_poses=6)
    path = tmp_path / "loop.g2o"
    write_g2o(path, sim.graph)
    graph_2d, values_2d = gtsam.readG2o(str(path))
    assert graph_2d.size() == 0 and values_2d.size() == 0
    graph_3d, values_3d = gtsam.readG2o(str(path), True)
    assert graph_3d.size() == 6 and values_3d.size() == 6
    back = read_g2o(path)
    assert len(back.nodes) == 6 and len(back.factors) == 7  # + the prior, from the sidecar


def test_g2o_round_trip_keeps_poses_and_covariances(tmp_path):
    sim = simulate_loop_graph(np.random.default_rng(1), n_poses=8)
    path = tmp_path / "loop.g2o"
    dropped = write_g2o(path, sim.graph)
    assert dropped == []  # the prior is in the sidecar
    back = read_g2o(path)
    assert back.factor_counts() == {"odometry": 7, "loop": 1, "prior": 1}
    for node_id in sim.graph.sorted_ids():
        assert back.nodes[node_id].pose.equals(sim.graph.nodes[node_id].pose, 1e-12)
    between = [r for r in sim.graph.factors if len(r.nodes) == 2]
    for original, read in zip(between, [r for r in back.factors if len(r.nodes) == 2]):
        assert original.nodes == read.nodes
        assert read.measured.equals(original.measured, 1e-12)
        np.testing.assert_allclose(read.covariance, original.covariance, rtol=1e-9)


def test_g2o_information_is_reordered_to_rotation_first(tmp_path):
    # g2o's information is [t, R]: translation info 100 (sigma 0.1 m), rotation info 1e4.
    info = np.diag([100.0] * 3 + [1e4] * 3)
    upper = " ".join(str(v) for v in info[np.triu_indices(6)])
    path = tmp_path / "two.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                    f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {upper}\n")
    cov = read_g2o(path).factors[0].covariance
    np.testing.assert_allclose(np.diag(cov), [1e-4] * 3 + [1e-2] * 3)


@pytest.mark.parametrize("content, message", [
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0\n", "expected 8 numbers"),
    ("VERTEX_SE3:QUAT 0 0 0 nan 0 0 0 1\n", "NaN"),
    ("VERTEX_SE2 0 0 0 0\n", "2-D"),
    ("# nothing\n", "not a 3-D g2o"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 7 " + "0 " * 6 + "1 "
     + " ".join(str(v) for v in np.eye(6)[np.triu_indices(6)]) + "\n", "vertex 7"),
])
def test_g2o_bad_input(tmp_path, content, message):
    path = tmp_path / "bad.g2o"
    path.write_text(content)
    with pytest.raises(FormatError, match=message):
        read_g2o(path)


# ---------------------------------------------------------------- OctoMap .graph
def test_spherical_scan_graph_reads_and_writes_byte_identical(shared_data, tmp_path):
    source = shared_data / SPHERICAL
    graph = read_scan_graph(source)
    assert len(graph.nodes) == 1 and graph.num_points() == 10201
    np.testing.assert_allclose(graph.nodes[0].pose.translation(), [1, 0, -0.5])
    out = tmp_path / "copy.graph"
    write_scan_graph(out, graph)
    assert out.read_bytes() == source.read_bytes()


def _graph_with_clouds(rng, n=3) -> PoseGraph:
    pg = PoseGraph()
    for i in range(n):
        pose = gtsam.Pose3(gtsam.Rot3.Ypr(*rng.normal(size=3) * 0.3), rng.normal(size=3))
        pg.add_node(i, pose, scan=Scan(rng.uniform(-3, 3, size=(50 + i, 3))))
    for i in range(n - 1):
        T = pg.nodes[i].pose.between(pg.nodes[i + 1].pose)
        pg.add_between(i, i + 1, T, np.eye(6))
    return pg


def test_scan_graph_round_trip(tmp_path):
    pg = _graph_with_clouds(np.random.default_rng(2))
    path = tmp_path / "g.graph"
    write_scan_graph(path, pg)
    back = read_scan_graph(path)
    for i in pg.sorted_ids():
        np.testing.assert_array_equal(back.nodes[i].scan.points, pg.nodes[i].scan.points)
        assert back.nodes[i].pose.equals(pg.nodes[i].pose, 1e-6)  # float32 in the file
    assert [r.nodes for r in back.factors] == [(0, 1), (1, 2)]
    # Second round trip is byte-identical.
    again = tmp_path / "g2.graph"
    write_scan_graph(again, back)
    assert again.read_bytes() == path.read_bytes()


@pytest.mark.reference
def test_graph_from_g2o_and_clouds_is_accepted_by_graph2tree(tmp_path):
    if shutil.which("graph2tree") is None:
        pytest.fail("graph2tree (Debian octomap-tools) is not installed: run make setup")
    rng = np.random.default_rng(4)
    pg = _graph_with_clouds(rng)
    write_g2o(tmp_path / "g.g2o", pg)
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for i in pg.sorted_ids():
        np.savetxt(clouds / f"{i}.xyz", pg.nodes[i].scan.points)
    from_g2o = read_pose_graph(tmp_path / "g.g2o")
    assert load_node_clouds(from_g2o, clouds) == 3
    write_scan_graph(tmp_path / "g.graph", from_g2o)
    result = subprocess.run(["graph2tree", "-i", str(tmp_path / "g.graph"), "-o",
                             str(tmp_path / "g.bt"), "-res", "0.1"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "3 nodes" in result.stdout or "Inserting" in result.stdout or result.stdout
    assert (tmp_path / "g.bt").stat().st_size > 100


def _spherical_bytes(shared_data) -> bytes:
    return (shared_data / SPHERICAL).read_bytes()


@pytest.mark.parametrize("cut", [0, 3, 4, 100, 285600, 285707])
def test_truncated_graph_is_an_error_with_offset(shared_data, tmp_path, cut):
    path = tmp_path / "cut.graph"
    path.write_bytes(_spherical_bytes(shared_data)[:cut])
    with pytest.raises(FormatError, match=r"cut.graph \(byte \d+\): truncated"):
        read_scan_graph(path)


def test_graph_with_lying_point_count_does_not_allocate(shared_data, tmp_path):
    data = bytearray(_spherical_bytes(shared_data))
    data[4:8] = struct.pack("<I", 0xFFFFFFFF)  # 4e9 points = 120 GB if believed
    path = tmp_path / "lie.graph"
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="4294967295 points of node #0"):
        read_scan_graph(path)
    data[0:4] = struct.pack("<I", 10**9)
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="1000000000 nodes"):
        read_scan_graph(path)


def test_graph_with_nan_pose_is_rejected(shared_data, tmp_path):
    data = bytearray(_spherical_bytes(shared_data))
    pose_offset = 4 + 4 + 10201 * 28
    data[pose_offset + 4:pose_offset + 12] = struct.pack("<d", float("nan"))
    path = tmp_path / "nan.graph"
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=rf"\(byte {pose_offset}\): pose of node #0 has NaN"):
        read_scan_graph(path)


def test_graph_with_trailing_garbage_is_rejected(shared_data, tmp_path):
    path = tmp_path / "tail.graph"
    path.write_bytes(_spherical_bytes(shared_data) + b"junk")
    with pytest.raises(FormatError, match="4 unexpected bytes"):
        read_scan_graph(path)


def test_random_bytes_never_crash_the_reader(tmp_path):
    rng = np.random.default_rng(9)
    for k in range(50):
        path = tmp_path / f"r{k}.graph"
        path.write_bytes(rng.bytes(int(rng.integers(0, 400))))
        with pytest.raises(FormatError):
            read_scan_graph(path)


# ---------------------------------------------------------------- atomic writes
def test_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "keep.txt"
    path.write_text("good\n")
    with pytest.raises(RuntimeError):
        with atomic_write(path, "w") as handle:
            handle.write("half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "good\n"
    assert list(tmp_path.iterdir()) == [path]


def test_writers_leave_no_temporary_files(tmp_path):
    sim = simulate_loop_graph(np.random.default_rng(5), n_poses=5)
    write_tum(tmp_path / "a.txt", sim.graph)
    write_g2o(tmp_path / "a.g2o", sim.graph)
    write_scan_graph(tmp_path / "a.graph", sim.graph)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.g2o", "a.g2o.json", "a.graph",
                                                         "a.txt"]


def test_cloud_directory_errors(tmp_path):
    pg = _graph_with_clouds(np.random.default_rng(6), n=1)
    with pytest.raises(Exception, match="does not exist"):
        load_node_clouds(pg, tmp_path / "missing")
    (tmp_path / "0.xyz").write_text("1 2\n")
    with pytest.raises(FormatError, match="0.xyz"):
        load_node_clouds(pg, tmp_path)


def test_read_pose_graph_dispatches_on_extension(shared_data, tmp_path):
    assert len(read_pose_graph(shared_data / SPHERICAL).nodes) == 1
    with pytest.raises(Exception, match="unknown pose-graph format"):
        read_pose_graph(Path(tmp_path / "x.bin"))


def test_atomic_write_uses_the_umask_like_open(tmp_path):
    import os

    umask = os.umask(0o022)
    try:
        with atomic_write(tmp_path / "f.txt", "w") as handle:
            handle.write("x")
    finally:
        os.umask(umask)
    assert (tmp_path / "f.txt").stat().st_mode & 0o777 == 0o644


def test_g2o_elements_that_are_not_read_are_named(tmp_path, capsys):
    """A g2o element octofactor (and GTSAM) does not read is not dropped in silence: the
    reader warns with its tag and line, the CLI prints that as one warning line."""
    from estimation.errors import FormatWarning
    from pipelines.cli import main

    info = " ".join(["100 0 0 0 0 0", "100 0 0 0 0", "100 0 0 0", "100 0 0", "100 0", "100"])
    path = tmp_path / "prior.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                    f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info}\n"
                    f"EDGE_SE3_PRIOR 0 0 0 0 0 0 0 0 1 {info}\n")
    with pytest.warns(FormatWarning, match=r"EDGE_SE3_PRIOR x1 \(line 4\)"):
        graph = read_g2o(path)
    assert len(graph.factors) == 1
    assert main(["graph", "info", str(path)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"octofactor: warning: {path}: skipped g2o elements octofactor does not "
                   "read: EDGE_SE3_PRIOR x1 (line 4)"]
