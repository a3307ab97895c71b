""".bt/.ot files: byte compatibility with liboctomap, round trips and bad input."""
from __future__ import annotations

import numpy as np
import octomap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import FormatError
from mapping import OcTree
from mapping.io import read_tree

pytestmark = pytest.mark.reference


@pytest.fixture(scope="module")
def geb(shared_data):
    path = shared_data / "octomap" / "geb079.bt"
    return path, path.read_bytes(), OcTree.read(path)


def test_geb079_read_then_write_is_byte_identical(geb, tmp_path):
    path, data, tree = geb
    assert (tree.size(), tree.num_leaf_nodes(), tree.memory_usage()) == (
        532566, 428144, 15204384)
    occ = tree.occupied_voxels()
    assert len(occ) == 143729
    out = tmp_path / "geb.bt"
    tree.write_bt(out)
    assert out.read_bytes() == data


def test_geb079_ot_equals_liboctomaps_and_round_trips(geb, tmp_path):
    path, data, tree = geb
    ref = octomap.OcTree(0.1)
    assert ref.readBinary(str(path).encode())
    ot = tree.to_bytes_ot()
    assert len(ot) == 2662965
    assert ot == ref.write()
    out = tmp_path / "geb.ot"
    tree.write_ot(out)
    back = OcTree.read(out)
    assert back.to_bytes_ot() == ot
    assert back.to_bytes_bt() == data


def test_ot_whose_header_claims_more_nodes_than_the_tree_has(geb, tmp_path):
    # the tree ends before the header's count: an error naming both counts and the offset
    ot = geb[2].to_bytes_ot()
    n = geb[2].size()
    bad = ot.replace(f"size {n}\n".encode(), f"size {n + 1}\n".encode(), 1) + bytes(5)
    path = tmp_path / "more.ot"
    path.write_bytes(bad)
    with pytest.raises(FormatError, match=f"header says {n + 1} nodes, the payload holds {n}"):
        OcTree.read(path)
    path.write_bytes(ot)
    assert OcTree.read(path).size() == n


def test_single_update_example_files_of_octomap_md():
    tree = OcTree(0.1)
    for _ in range(11):
        tree.update_node([[0.05, 0.05, 0.05]], True)
    tree.update_node([[0.05, 0.05, 0.05]], False)
    ot = tree.to_bytes_ot()
    payload = ot[ot.index(b"data\n") + 5:]
    assert payload[:5] == bytes.fromhex("96c1464080")
    assert payload[5:10] == bytes.fromhex("96c1464001") and payload[-5:] == bytes.fromhex(
        "96c1464000")
    bt = tree.to_bytes_bt()
    assert len(bt) == 169
    assert bt[-32:] == bytes.fromhex("00c0" + "0300" * 14 + "0200")


def test_color_octree_ot_round_trip_and_liboctomap_reads_it(tmp_path):
    ref = octomap.ColorOcTree(0.1)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, size=(300, 3))
    ref.insertPointCloud(pts, np.zeros(3))
    for p in pts[:50]:
        ref.setNodeColor(p, 10, 200, 30) if hasattr(ref, "setNodeColor") else None
    data = ref.write()
    path = tmp_path / "c.ot"
    path.write_bytes(data)
    tree = OcTree.read(path)
    assert tree.tree_type == "ColorOcTree"
    assert tree.size() == ref.size()
    assert tree.to_bytes_ot() == data
    tree.write_ot(tmp_path / "c2.ot")
    assert (tmp_path / "c2.ot").read_bytes() == data


def test_bt_of_sparse_tree_read_by_liboctomap(tmp_path, rng):
    tree = OcTree(0.05)
    tree.insert_point_cloud(rng.uniform(-3, 3, size=(500, 3)), [0.1, 0.2, 0.3])
    path = tmp_path / "t.bt"
    tree.write_bt(path)
    ref = octomap.OcTree(0.05)
    assert ref.readBinary(str(path).encode())
    assert ref.size() == tree.size()
    assert ref.writeBinary() == path.read_bytes()


def test_empty_tree_files():
    tree = OcTree(0.1)
    assert tree.size() == 0
    for data in (tree.to_bytes_bt(), tree.to_bytes_ot()):
        assert b"size 0\n" in data
        back = read_tree("mem", data=data)
        assert back.size() == 0


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(-6, 6), st.integers(-6, 6), st.integers(-3, 3),
                          st.booleans()), min_size=1, max_size=60),
       st.sampled_from([0.1, 0.25, 1 / 3]))
def test_ot_and_bt_round_trips(cells, res):
    tree = OcTree(res)
    for i, j, k, hit in cells:
        tree.update_node([[(i + 0.5) * res, (j + 0.5) * res, (k + 0.5) * res]], hit)
    ot = tree.to_bytes_ot()
    assert read_tree("mem.ot", data=ot).to_bytes_ot() == ot
    assert ot == octomap.OcTree.read(ot).write()
    tree.to_max_likelihood()
    tree.prune()
    bt = tree.to_bytes_bt()
    assert read_tree("mem.bt", data=bt).to_bytes_bt() == bt


# --------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def small_files():
    tree = OcTree(0.1)
    rng = np.random.default_rng(7)
    tree.insert_point_cloud(rng.uniform(-2, 2, size=(200, 3)), np.zeros(3))
    ot = tree.to_bytes_ot()
    tree.to_max_likelihood()
    tree.prune()
    return tree.to_bytes_bt(), ot


@pytest.mark.parametrize("kind", ["bt", "ot"])
def test_truncated_files_raise_format_error_with_offset(small_files, kind):
    data = small_files[0] if kind == "bt" else small_files[1]
    start = data.index(b"data\n") + 5
    for cut in (len(data) - 1, start + 3, start, start - 3, 10):
        with pytest.raises(FormatError) as err:
            read_tree(f"x.{kind}", data=data[:cut])
        assert err.value.offset is not None and 0 <= err.value.offset <= cut
        assert "x." + kind in str(err.value)


@pytest.mark.parametrize("kind", ["bt", "ot"])
def test_header_lies_are_caught(small_files, kind):
    data = small_files[0] if kind == "bt" else small_files[1]
    size = int(data.split(b"size ")[1].split(b"\n")[0])
    for fake in (size + 1, size - 1, 10**15):
        bad = data.replace(f"size {size}\n".encode(), f"size {fake}\n".encode())
        with pytest.raises(FormatError, match="size|truncated|claims"):
            read_tree(f"x.{kind}", data=bad)


def test_unknown_id_garbage_and_bad_header():
    tree = OcTree(0.1)
    tree.update_node([[0.05, 0.05, 0.05]], True)
    ot = tree.to_bytes_ot()
    with pytest.raises(FormatError, match="unknown or unsupported tree id 'FooTree'"):
        read_tree("x.ot", data=ot.replace(b"id OcTree", b"id FooTree"))
    with pytest.raises(FormatError, match="not an OctoMap file") as err:
        read_tree("x.bt", data=b"\x00\x01garbage" * 100)
    assert err.value.offset == 0
    with pytest.raises(FormatError, match="no 'data'"):
        read_tree("x.ot", data=ot.split(b"data\n")[0])
    with pytest.raises(FormatError, match="resolution must be positive"):
        read_tree("x.ot", data=ot.replace(b"res 0.1", b"res -1"))
    with pytest.raises(FormatError, match="bad size"):
        read_tree("x.ot", data=ot.replace(b"size 17", b"size abc"))


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=0, max_size=300), st.sampled_from(["bt", "ot"]))
def test_garbage_payload_never_crashes(payload, kind):
    head = (b"# Octomap OcTree binary file\n" if kind == "bt" else b"# Octomap OcTree file\n")
    data = head + b"id OcTree\nsize 9\nres 0.1\ndata\n" + payload
    try:
        tree = read_tree("g." + kind, data=data)
    except FormatError as exc:
        assert exc.offset is not None
    else:
        assert tree.size() == 9
