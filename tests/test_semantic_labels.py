"""Labelled clouds as other tools write them: integer label columns of every PLY type (Open3D
skips ``char``, ``short``, ``ushort`` and ``uint``: ScanNet's ``ushort label``), float label
columns, 8-bit colours, sparse label values, and two clouds put on one class list."""
from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest
from test_registration import make_pair

from estimation.errors import FormatError
from estimation.registration import write_transform
from perception.errors import PerceptionError
from perception.semantic_cloud import SemanticCloud, common_classes
from pipelines.cli import main

# ScanNet's label files: float x y z, uchar red green blue alpha, ushort label
SCANNET = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
           ("blue", "u1"), ("alpha", "u1"), ("label", "u2")]


def write_binary_ply(path, fields, columns, order="<", trailer=""):
    """Write a binary PLY of the vertex ``fields`` [(name, numpy kind)]; ``trailer``: header
    lines of further (empty) elements after the vertices."""
    kinds = {"f4": "float", "f8": "double", "u1": "uchar", "i1": "char", "u2": "ushort",
             "i2": "short", "u4": "uint", "i4": "int"}
    n = len(columns[fields[0][0]])
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    header = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n" + "".join(
        f"property {kinds[kind]} {name}\n" for name, kind in fields) + trailer + "end_header\n"
    rows = np.zeros(n, np.dtype([(name, order + kind) for name, kind in fields]))
    for name, _ in fields:
        rows[name] = columns[name]
    path.write_bytes(header.encode() + rows.tobytes())


def scannet_columns(points, labels, rng):
    colours = rng.integers(0, 256, (len(points), 4))
    return {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "red": colours[:, 0],
            "green": colours[:, 1], "blue": colours[:, 2], "alpha": colours[:, 3],
            "label": labels}


def test_scannet_ply_loads_its_labels_and_colours(tmp_path, rng):
    points = rng.uniform(-1, 1, (500, 3)).astype(np.float32)
    labels = rng.choice([0, 3, 39, 1163], size=500)
    columns = scannet_columns(points, labels, rng)
    write_binary_ply(tmp_path / "scene.ply", SCANNET, columns)
    cloud = SemanticCloud.read_ply(tmp_path / "scene.ply")
    np.testing.assert_array_equal(cloud.labels, labels)
    assert cloud.label_ids == (0, 3, 39, 1163) and cloud.n_classes == 4
    np.testing.assert_array_equal(cloud.probs.sum(axis=1), 1.0)
    # the one-hot columns are as many as the values, however large (not max + 1)
    columns["label"] = np.where(labels == 1163, 2_000_000_000, labels)
    write_binary_ply(tmp_path / "big.ply", SCANNET[:-1] + [("label", "i4")], columns)
    big = SemanticCloud.read_ply(tmp_path / "big.ply")
    assert big.label_ids == (0, 3, 39, 2_000_000_000) and big.probs.shape == (500, 4)
    np.testing.assert_array_equal(cloud.points, points.astype(float))
    expected = np.c_[columns["red"], columns["green"], columns["blue"]] / 255.0
    np.testing.assert_allclose(cloud.colors, expected, atol=1e-7)
    # every integer type, both byte orders, an element after the vertices
    for kind in ("i1", "u1", "i2", "u2", "i4", "u4"):
        for order in "<>":
            values = rng.choice([1, 2, 7], size=500)
            write_binary_ply(tmp_path / "k.ply", [("x", "f4"), ("y", "f4"), ("z", "f4"),
                                                  ("Label", kind)],
                             {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
                              "Label": values}, order,
                             "element face 0\nproperty list uchar int vertex_indices\n")
            np.testing.assert_array_equal(SemanticCloud.read_ply(tmp_path / "k.ply").labels,
                                          values, err_msg=f"{order}{kind}")


def test_ascii_float_labels_and_their_errors(tmp_path):
    path = tmp_path / "cc.ply"
    head = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
            "property double z\nproperty float scalar_Label\nend_header\n")
    path.write_text(head + "0 0 0 5\n1 0 0 1163\n\n0 1 0 5\n0 0 1 -1\n")
    cloud = SemanticCloud.read_ply(path)
    assert cloud.label_ids == (-1, 5, 1163)
    np.testing.assert_array_equal(cloud.labels, [5, 1163, 5, -1])
    # n_classes: the labels are the column indices, as before
    path.write_text(head + "0 0 0 2\n1 0 0 0\n0 1 0 1\n0 0 1 1\n")
    numbered = SemanticCloud.read_ply(path, n_classes=5)
    assert numbered.n_classes == 5 and numbered.label_ids is None
    with pytest.raises(FormatError, match="outside 0..n_classes-1"):
        SemanticCloud.read_ply(path, n_classes=2)
    with pytest.raises(PerceptionError, match="n_classes must be"):
        SemanticCloud.read_ply(path, n_classes=10 ** 9)  # not an allocation of that size
    for value, what in (("2.5", "2.5"), ("nan", "nan")):
        path.write_text(head + f"0 0 0 1\n1 0 0 {value}\n0 1 0 1\n0 0 1 1\n")
        with pytest.raises(FormatError, match=f"cc.ply: label column 'scalar_Label' holds "
                                              f"{what} at vertex 1"):
            SemanticCloud.read_ply(path)
    path.write_text(head + "0 0 0 1\n1 0 0 1 7\n0 1 0 1\n0 0 1 1\n")
    with pytest.raises(FormatError, match="vertex 1 has 5 values"):
        SemanticCloud.read_ply(path)


def test_vertices_after_a_list_element_are_refused_with_the_reason(tmp_path):
    path = tmp_path / "faces_first.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement face 1\n"
                     b"property list uchar int vertex_indices\nelement vertex 1\n"
                     b"property float x\nproperty float y\nproperty float z\n"
                     b"property ushort label\nend_header\n" + bytes([0]) + bytes(14))
    with pytest.raises(FormatError, match="before the vertices has list properties"):
        SemanticCloud.read_ply(path)


def test_common_classes_puts_two_clouds_on_one_list(tmp_path):
    points = np.zeros((3, 3))
    a = SemanticCloud(points, np.eye(3, dtype=np.float32), label_ids=(2, 9, 40))
    b = SemanticCloud(points, np.eye(3, dtype=np.float32)[[0, 1, 1]], label_ids=(0, 9, 77))
    a2, b2 = common_classes(a, b)
    assert a2.label_ids == b2.label_ids == (0, 2, 9, 40, 77)
    np.testing.assert_array_equal(a2.labels, [2, 9, 40])
    np.testing.assert_array_equal(b2.labels, [0, 9, 9])
    np.testing.assert_array_equal(b2.probs[:, [1, 3]], 0.0)  # classes b lacks
    # a written label-only cloud reads back with its label values
    b2.write_ply(tmp_path / "b.ply")
    assert "prob_0" not in (tmp_path / "b.ply").read_bytes().split(b"end_header")[0].decode()
    np.testing.assert_array_equal(SemanticCloud.read_ply(tmp_path / "b.ply").labels, [0, 9, 9])
    # numbered classes take ids below their count only
    numbered = SemanticCloud(points, np.eye(3, dtype=np.float32))
    assert common_classes(numbered, SemanticCloud(points[:1], np.ones((1, 1)),
                                                  label_ids=(2,)))[1].n_classes == 3
    with pytest.raises(PerceptionError, match="numbered classes"):
        common_classes(numbered, a)
    with pytest.raises(PerceptionError, match="same label set"):
        common_classes(numbered, SemanticCloud(points, np.ones((3, 2))))
    with pytest.raises(PerceptionError, match="distinct label ids"):
        SemanticCloud(points, np.eye(3), label_ids=(1, 1, 2))


def test_semantic_register_reads_scannet_files_whose_classes_differ(tmp_path, rng):
    """A source that lacks one of the map's classes, labels stored as sparse ushort values:
    the same estimate as the same labels given as one class list through our own files."""
    source, labels_s, target, labels_t, T_gt = make_pair(11, 2000)
    assert set(labels_t) == {0, 1, 2}
    keep = labels_s != 1  # the source lacks class 1
    source, labels_s = source[keep], labels_s[keep]
    ids = np.array([17, 39, 1163])
    write_binary_ply(tmp_path / "src.ply", SCANNET,
                     scannet_columns(source.astype(np.float32), ids[labels_s], rng))
    write_binary_ply(tmp_path / "tgt.ply", SCANNET,
                     scannet_columns(target.astype(np.float32), ids[labels_t], rng))
    # the reference: the same points and classes, written as probabilities over 3 classes
    SemanticCloud.from_labels(source.astype(np.float32), labels_s, 3).write_ply(
        tmp_path / "src_ref.ply")
    SemanticCloud.from_labels(target.astype(np.float32), labels_t, 3).write_ply(
        tmp_path / "tgt_ref.ply")
    init = T_gt @ gtsam.Pose3(gtsam.Rot3.Yaw(0.03), np.array([0.05, 0, 0])).matrix()
    write_transform(tmp_path / "init.txt", init)
    write_transform(tmp_path / "gt.txt", T_gt)
    results = {}
    for name in ("", "_ref"):
        out = tmp_path / f"result{name}.json"
        code = main(["register", str(tmp_path / f"src{name}.ply"),
                     str(tmp_path / f"tgt{name}.ply"), "--method", "semantic", "--init",
                     str(tmp_path / "init.txt"), "--gt", str(tmp_path / "gt.txt"),
                     "--max-corr", "0.3", "-o", str(out)])
        assert code == 0
        results[name] = json.loads(out.read_text())
    assert results[""]["converged"] and results[""]["t_err_m"] < 0.01
    np.testing.assert_array_equal(results[""]["T"], results["_ref"]["T"])
    np.testing.assert_array_equal(results[""]["covariance"], results["_ref"]["covariance"])
