"""Fuzzing every file reader: mutated valid files raise only octofactor's own errors.

Each reader gets a valid seed file (tests/hostile_files.py); hypothesis mutates it (bytes
flipped, truncated, inserted or deleted; counts and floats overwritten with hostile values
such as 2^31, 2^63, NaN, inf, 1e300; text tokens replaced by NaN, 1e-320, 2^56, garbage
bytes, lines doubled or dropped) and the reader must either return or raise an
OctofactorError (FormatError, ImageError, ...). Anything else -- an IndexError, a numpy
RuntimeWarning (NaN made silently), a MemoryError, a struct.error -- fails the test.
Derandomized, so a run is reproducible; ~1 minute on 2 cores.
"""
from __future__ import annotations

import struct
import warnings
from pathlib import Path

import hostile_files as hf
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimation.errors import OctofactorError

FUZZ = settings(max_examples=250, derandomize=True, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))

HOSTILE_INTS = [0, 1, 2, 255, 2**16, 2**31 - 1, 2**31, 2**32 - 1, 2**40, 2**56, 2**63,
                2**64 - 1]
HOSTILE_FLOATS = [float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e-45, 1e-320,
                  3.5e38, 1e300, -1e300]
HOSTILE_TOKENS = ["nan", "inf", "-inf", "1e308", "1e999", "1e-320", "-1", "0", "-0",
                  "4294967296", "72057594037927936", "18446744073709551616", "9" * 400,
                  "0x10", "1,2", "", "\x00", "\xff\xfe", "\u00e9", "#", "EDGE_SE3:QUAT",
                  "VERTEX_SE3:QUAT", "0.5", "1e-9", "3"]


@st.composite
def mutations(draw, seed: bytes, text: bool) -> bytes:
    """``seed`` with 1-4 random mutations (token-level ones too for text files)."""
    data = bytearray(seed)
    ops = ["flip", "truncate", "insert", "delete", "int", "float", "append", "token", "line_dup"]
    if text:  # binary formats have text headers (PLY, .bt, .ot): token ops for them too
        ops += ["token", "token", "line_drop"]
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(ops))
        pos = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[pos] = draw(st.integers(0, 255))
        elif op == "truncate":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del data[pos:pos + draw(st.integers(1, 16))]
        elif op == "int":
            value = draw(st.sampled_from(HOSTILE_INTS))
            fmt = draw(st.sampled_from(["<I", "<Q", "<i", "<q"]))
            try:
                data[pos:pos + struct.calcsize(fmt)] = struct.pack(fmt, value)
            except struct.error:
                data[pos:pos + 8] = struct.pack("<Q", value % 2**64)
        elif op == "float":
            fmt = draw(st.sampled_from(["<f", "<d"]))
            value = draw(st.sampled_from(HOSTILE_FLOATS))
            if fmt == "<f" and abs(value) > 3.4e38:
                value = float(np.sign(value) * np.inf)  # float32 overflows to inf
            data[pos:pos + struct.calcsize(fmt)] = struct.pack(fmt, value)
        elif op == "append":
            data += draw(st.binary(min_size=1, max_size=64))
        elif op == "token":
            tokens = bytes(data).split(b" ")
            k = draw(st.integers(0, len(tokens) - 1))
            tokens[k] = draw(st.sampled_from(HOSTILE_TOKENS)).encode("utf-8", "surrogateescape")
            data = bytearray(b" ".join(tokens))
        elif op in ("line_dup", "line_drop"):
            lines = bytes(data).split(b"\n")
            k = draw(st.integers(0, len(lines) - 1))
            if op == "line_dup":
                lines.insert(k, lines[k])
            else:
                del lines[k]
            data = bytearray(b"\n".join(lines))
    return bytes(data)


def _expect_clean(read, path: Path) -> object:
    """Call ``read(path)``: it returns or raises an OctofactorError, with no RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            return read(path)
        except OctofactorError:
            return None


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def _read_pose_graph(path):
    from estimation.io import read_pose_graph

    return read_pose_graph(path)


def _read_scan_graph_mapped(path):
    """What ``octofactor map G.graph`` reads: the mapped records, then each node's points."""
    from estimation.scan_graph import map_scan_graph_records

    records, edges = map_scan_graph_records(path)
    points = [record.points() for record in records]
    assert all(np.all(np.isfinite(p)) for p in points)
    return len(points), len(edges)


def _read_tree(path):
    from mapping import OcTree

    tree = OcTree.read(path)
    tree.leaves()  # walk what was read, and what export and info compute from it
    voxels = tree.occupied_voxels()
    assert np.all(np.isfinite(voxels.log_odds))
    if hasattr(voxels, "probs"):
        assert np.all(np.isfinite(voxels.probs))
    tree.metric_bounds()
    return tree


def _read_ply(path):
    from perception.semantic_cloud import SemanticCloud

    cloud = SemanticCloud.read_ply(path)
    assert np.all(np.isfinite(cloud.points)) and np.all(np.isfinite(cloud.probs))
    return cloud


def _read_transform(path):
    from estimation.registration import read_transform

    return read_transform(path)


def _read_camera(path):
    from perception.rgbd import read_camera_file

    return read_camera_file(path)


def _read_list(path):
    from perception.rgbd import read_timestamp_list

    return read_timestamp_list(path)


def _read_trajectory(path):
    from estimation.trajectory_io import read_trajectory

    return read_trajectory(path)


def _camera():
    from perception.rgbd import CameraIntrinsics

    return CameraIntrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)


def _read_rgb(path):
    from perception.rgbd import read_rgb

    return read_rgb(path, _camera())


def _read_depth(path):
    from perception.rgbd import read_depth

    depth = read_depth(path, _camera())
    assert np.all(np.isfinite(depth))
    return depth


def _read_gray(path):
    from perception.lines import read_image

    return read_image(path)


def _read_node_cloud(path):
    from estimation.io import _read_cloud  # what load_node_clouds calls per node file

    return _read_cloud(path)


def _pcd_bytes(binary: bool) -> bytes:
    points = np.random.default_rng(5).normal(size=(20, 3)).astype("<f4")
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH 20\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 20\n"
              f"DATA {'binary' if binary else 'ascii'}\n").encode()
    if binary:
        return header + points.tobytes()
    return header + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()).encode()


def _kitti_text() -> str:
    return "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.1 0 1 0 0 0 0 1 0\n"


# name -> (seed bytes factory, file name, reader, text format?)
READERS = {
    "graph": (hf.scan_graph_bytes, "x.graph", _read_pose_graph, False),
    "graph_mapped": (hf.scan_graph_bytes, "x.graph", _read_scan_graph_mapped, False),
    "g2o": (lambda: hf.g2o_text().encode(), "x.g2o", _read_pose_graph, True),
    "tum": (lambda: hf.tum_text().encode(), "x.txt", _read_pose_graph, True),
    "kitti": (lambda: _kitti_text().encode(), "x.kitti", _read_trajectory, True),
    "bt": (lambda: hf.octree_bytes("bt"), "x.bt", _read_tree, False),
    "ot": (lambda: hf.octree_bytes("ot"), "x.ot", _read_tree, False),
    "semantic_ot": (lambda: hf.octree_bytes("sem"), "x.ot", _read_tree, False),
    "ply_binary": (hf.ply_bytes, "x.ply", _read_ply, False),
    "ply_ascii": (lambda: hf.ply_bytes(ascii=True), "x.ply", _read_ply, True),
    "ply_probs": (lambda: hf.ply_bytes(probs=True), "x.ply", _read_ply, False),
    "pcd_ascii": (lambda: _pcd_bytes(False), "1.pcd", _read_node_cloud, True),
    "pcd_binary": (lambda: _pcd_bytes(True), "1.pcd", _read_node_cloud, False),
    "ply_cloud": (hf.ply_bytes, "1.ply", _read_node_cloud, False),
    "transform": (lambda: hf.transform_text().encode(), "T.txt", _read_transform, True),
    "camera": (lambda: hf.camera_text().encode(), "camera.txt", _read_camera, True),
    "rgb_list": (lambda: b"# rgb\n1.0 rgb/1.png\n1.1 rgb/2.png\n", "rgb.txt", _read_list, True),
    "rgb_png": (lambda: hf.png_bytes(32, 24), "x.png", _read_rgb, False),
    "depth_png": (lambda: hf.png_bytes(32, 24, depth16=True), "x.png", _read_depth, False),
    "vp_image": (lambda: hf.png_bytes(32, 24), "x.png", _read_gray, False),
}


@pytest.mark.parametrize("name", sorted(READERS))
def test_reader_raises_only_octofactor_errors(name, work):
    make_seed, file_name, read, text = READERS[name]
    seed = make_seed()
    folder = work / name
    folder.mkdir()
    path = folder / file_name
    path.write_bytes(seed)
    assert _expect_clean(read, path) is not None, "the seed itself must be valid"

    @FUZZ
    @given(data=mutations(seed, text))
    def fuzz(data):
        path.write_bytes(data)
        _expect_clean(read, path)

    fuzz()


def test_g2o_sidecar_raises_only_octofactor_errors(work):
    """The JSON sidecar of a g2o file, mutated like a text file."""
    from estimation.io import g2o_sidecar_path, read_pose_graph, write_g2o

    folder = work / "sidecar"
    folder.mkdir()
    path = folder / "x.g2o"
    path.write_text(hf.g2o_text())
    graph = read_pose_graph(path)
    for node in graph.nodes.values():
        node.timestamp = 1.0 + node.id
    graph.timestamps_missing = None
    write_g2o(path, graph)
    sidecar = g2o_sidecar_path(path)
    seed = sidecar.read_bytes()

    @FUZZ
    @given(data=mutations(seed, True))
    def fuzz(data):
        sidecar.write_bytes(data)
        _expect_clean(read_pose_graph, path)

    fuzz()


def test_xyz_clouds_raise_only_octofactor_errors(work):
    """Per-node .xyz clouds (``--clouds DIR``)."""
    from estimation.io import load_node_clouds, read_pose_graph

    folder = work / "clouds"
    folder.mkdir()
    (folder / "x.g2o").write_text(hf.g2o_text())
    graph = read_pose_graph(folder / "x.g2o")
    seed = b"# x y z\n0 0 1\n1 2 3\n-1 0.5 2\n"

    @FUZZ
    @given(data=mutations(seed, True))
    def fuzz(data):
        (folder / "1.xyz").write_bytes(data)
        _expect_clean(lambda p: load_node_clouds(graph, p), folder)

    fuzz()


@pytest.mark.parametrize("name", ["graph", "bt", "ply_binary", "camera"])
def test_special_files_are_refused(name):
    """/dev/zero is endless: readers refuse non-regular files before reading them."""
    _, _, read, _ = READERS[name]
    with pytest.raises(OctofactorError, match="/dev/zero"):
        read(Path("/dev/zero"))
