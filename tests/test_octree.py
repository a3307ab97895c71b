"""mapping.OcTree against liboctomap (octomap-python wheel and Debian graph2tree).

Equality is checked on whole .ot files: the .ot payload holds every node's float32 log-odds in
liboctomap's pre-order, so byte equality means the same nodes, leaves and values.
"""
from __future__ import annotations

import bz2
import contextlib
import subprocess
import warnings
from pathlib import Path

import numpy as np
import octomap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import OcTree, fuse, logodds
from mapping.octree import OctreeError, probability

pytestmark = pytest.mark.reference


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session")
def scan_points(shared_data) -> np.ndarray:
    """scan.dat as float32 (OctoMap reads it as floats)."""
    text = bz2.decompress((shared_data / "octomap" / "scan.dat.bz2").read_bytes())
    return np.loadtxt(text.decode().splitlines(), dtype=np.float64).astype(np.float32)


@pytest.fixture(scope="session")
def scan_graph(shared_data, tmp_path_factory) -> Path:
    """scan.dat as a one-node .graph at the origin (log2graph, as the data README says)."""
    d = tmp_path_factory.mktemp("scangraph")
    log = d / "scan.log"
    text = bz2.decompress((shared_data / "octomap" / "scan.dat.bz2").read_bytes())
    log.write_bytes(b"NODE 0 0 0 0 0 0\n" + text)
    subprocess.run(["log2graph", str(log), str(d / "scan.graph")], check=True,
                   capture_output=True)
    return d / "scan.graph"


_G2T_CACHE: dict = {}


@pytest.fixture(scope="session")
def graph2tree(tmp_path_factory):
    """graph2tree outputs (bt bytes, ot bytes) for (graph, res, max_range), cached."""
    out_dir = tmp_path_factory.mktemp("graph2tree")

    def run(graph: Path, res: float, max_range: float = -1.0) -> tuple[bytes, bytes]:
        key = (str(graph), res, max_range)
        if key not in _G2T_CACHE:
            out = out_dir / f"{Path(graph).stem}_{res}_{max_range}.bt"
            cmd = ["graph2tree", "-i", str(graph), "-o", str(out), "-res", str(res)]
            if max_range >= 0:
                cmd += ["-m", str(max_range)]
            subprocess.run(cmd, check=True, capture_output=True)
            _G2T_CACHE[key] = (out.read_bytes(), Path(str(out) + ".ot").read_bytes())
        return _G2T_CACHE[key]

    return run


def _octomap_scan(points: np.ndarray, res: float, max_range: float, discretize=False):
    ref = octomap.OcTree(res)
    ref.insertPointCloud(points.astype(np.float64), np.zeros(3), maxrange=max_range,
                         discretize=discretize)
    return ref


def _k3(key) -> tuple[int, int, int]:
    # OcTreeKey has __getitem__ without bounds: never iterate it (it would run off the end)
    return int(key[0]), int(key[1]), int(key[2])


# --------------------------------------------------------------------------- defaults, keys


def test_default_parameters_are_liboctomaps_float32_values():
    tree = OcTree(0.1)
    ref = octomap.OcTree(0.1)
    assert tree.prob_hit_log == np.float32(ref.getProbHitLog())
    assert tree.prob_miss_log == np.float32(ref.getProbMissLog())
    assert tree.clamp_min_log == np.float32(ref.getClampingThresMinLog())
    assert tree.clamp_max_log == np.float32(ref.getClampingThresMaxLog())
    assert tree.occupancy_thres_log == np.float32(0.0)
    # hex values of OCTOMAP.md section 4
    assert float(tree.prob_hit_log) == float.fromhex("0x1.b1d106p-1")
    assert float(tree.prob_miss_log) == float.fromhex("-0x1.9f323ep-2")
    assert float(tree.clamp_min_log) == float.fromhex("-0x1.0000eap+1")
    assert float(tree.clamp_max_log) == float.fromhex("0x1.c16974p+1")
    assert logodds(0.5) == 0.0
    assert probability(0.0) == 0.5


def test_keys_match_liboctomap(rng):
    tree = OcTree(0.05)
    ref = octomap.OcTree(0.05)
    pts = rng.uniform(-50, 50, size=(200, 3)).astype(np.float32)
    pts[:5] = [[0, 0, 0], [0.05, -0.05, 0.025], [-1e-7, 1e-7, 0.1], [1638.35, -1638.4, 3],
               [0, 0, 0]]
    keys = tree.coord_to_key(pts)
    back = tree.key_to_coord(keys)
    for p, k, c in zip(pts, keys, back, strict=True):
        rk = ref.coordToKey(p.astype(np.float64))
        assert _k3(rk) == tuple(int(v) for v in k)
        assert np.allclose(ref.keyToCoord(rk), c)
    # out of the map: checked keys fail
    _, valid = tree.coord_to_key_checked([[1e6, 0, 0], [np.nan, 0, 0], [1, 2, 3]])
    assert valid.tolist() == [False, False, True]


def test_adjust_key_and_key_to_coord_at_depth():
    tree = OcTree(0.1)
    keys = np.array([[32768, 32767, 40000]])
    for depth in (1, 5, 12, 15, 16):
        adj = tree.adjust_key_at_depth(keys, depth)
        diff = 16 - depth
        expect = ((((keys - 32768) >> diff) << diff) + ((1 << (diff - 1)) if diff else 0)
                  + 32768)
        assert (adj == expect).all()
        c = tree.key_to_coord(keys, depth)
        size = tree.node_size(depth)
        assert np.allclose(c, (np.floor((keys - 32768) / 2 ** diff) + 0.5) * size)
    assert (tree.key_to_coord(keys, 0) == 0).all()


def test_compute_ray_keys_excludes_end_cell():
    tree = OcTree(0.1)
    keys = tree.compute_ray_keys([0.05, 0.05, 0.05], [0.55, 0.05, 0.05])
    assert keys[:, 0].tolist() == [32768, 32769, 32770, 32771, 32772]
    assert (keys[:, 1:] == 32768).all()
    assert len(tree.compute_ray_keys([0.01, 0.01, 0.01], [0.02, 0.03, 0.04])) == 0


def test_ray_keys_equal_single_point_insert_free_cells(rng):
    """A one-point scan: free cells = ray keys (checked against liboctomap's tree)."""
    res = 0.1
    for _ in range(20):
        o = rng.uniform(-2, 2, 3).astype(np.float32)
        e = (o + rng.normal(size=3) * 3).astype(np.float32)
        keys = OcTree(res).compute_ray_keys(o, e)
        ref = octomap.OcTree(res)
        ref.insertPointCloud(e[None].astype(np.float64), o.astype(np.float64))
        free = {_k3(lf.getKey()) for lf in ref.begin_leafs()
                if lf.getValue() < 0}
        ekey = tuple(int(v) for v in OcTree(res).coord_to_key(e)[0])
        assert free == {tuple(int(v) for v in k) for k in keys} - {ekey}


# --------------------------------------------------------------------------- whole maps


@pytest.mark.parametrize("res,nodes,leaves,bt_len,ot_len,mem", [
    (0.1, 6296, 4926, 2879, 31612, 188736),
    (0.05, 23923, 18970, 10047, 119749, 700080),
])
def test_spherical_scan_golden_and_graph2tree_bytes(shared_data, graph2tree, res, nodes, leaves,
                                                    bt_len, ot_len, mem, kernel_backend):
    from estimation.io import read_scan_graph

    path = shared_data / "octomap" / "spherical_scan.graph"
    tree = fuse(read_scan_graph(path), res)
    assert tree.size() == nodes
    assert tree.num_leaf_nodes() == leaves
    assert tree.memory_usage() == mem
    ref_bt, ref_ot = graph2tree(path, res)
    ot = tree.to_bytes_ot()
    assert len(ot) == ot_len and ot == ref_ot
    tree.to_max_likelihood()
    tree.prune()
    bt = tree.to_bytes_bt()
    assert len(bt) == bt_len and bt == ref_bt


@pytest.mark.parametrize("res,max_range,nodes,leaves,bt_len,ot_len,mem", [
    (0.1, -1.0, 407411, 327452, 160059, 2037189, 11636272),
    (0.1, 10.0, 66581, 53254, 26794, 333038, 1918544),
    pytest.param(0.05, 10.0, 1054412, 872609, 363749, 5272196, 28506304,
                 marks=pytest.mark.slow),
])
def test_scan_dat_golden_and_liboctomap_equal(scan_points, scan_graph, graph2tree, res,
                                              max_range, nodes, leaves, bt_len, ot_len, mem,
                                              kernel_backend):
    tree = OcTree(res)
    tree.insert_point_cloud(scan_points, np.zeros(3), max_range=max_range)
    assert (tree.size(), tree.num_leaf_nodes(), tree.memory_usage()) == (nodes, leaves, mem)
    ref_bt, ref_ot = graph2tree(scan_graph, res, max_range)
    ot = tree.to_bytes_ot()
    assert len(ot) == ot_len and ot == ref_ot
    tree.to_max_likelihood()
    tree.prune()
    bt = tree.to_bytes_bt()
    assert len(bt) == bt_len and bt == ref_bt


@pytest.mark.slow
def test_scan_dat_005_no_max_range_equals_octomap_python(scan_points):
    tree = OcTree(0.05)
    tree.insert_point_cloud(scan_points, np.zeros(3))
    ref = _octomap_scan(scan_points, 0.05, -1.0)
    assert tree.size() == ref.size()
    assert tree.to_bytes_ot() == ref.write()


@pytest.mark.parametrize("max_range", [-1.0, 3.0])
def test_discretize_and_moving_origin_equal_octomap_python(scan_points, max_range):
    pts = scan_points[::7]
    ref = octomap.OcTree(0.2)
    tree = OcTree(0.2)
    for k, origin in enumerate([(0.0, 0.0, 0.0), (0.33, -0.71, 0.2), (1.05, 0.4, -0.3)]):
        o = np.array(origin)
        ref.insertPointCloud(pts.astype(np.float64) + o, o, maxrange=max_range,
                             discretize=bool(k % 2))
        tree.insert_point_cloud((pts.astype(np.float64) + o).astype(np.float32), o,
                                max_range=max_range, discretize=bool(k % 2))
    assert tree.to_bytes_ot() == ref.write()


def test_several_scans_prune_and_expand_like_liboctomap(scan_points):
    """Many scans from one place: clamping makes 8 equal leaves collapse; later scans expand."""
    pts = scan_points[::3] * np.float32(0.2)
    ref = octomap.OcTree(0.1)
    tree = OcTree(0.1)
    rng = np.random.default_rng(3)
    for _ in range(8):
        o = rng.uniform(-0.3, 0.3, 3)
        sub = pts[rng.choice(len(pts), len(pts) // 2, replace=False)].astype(np.float64) + o
        ref.insertPointCloud(sub, o, maxrange=4.0)
        tree.insert_point_cloud(sub.astype(np.float32), o, max_range=4.0)
        assert tree.size() == ref.size()
    assert tree.to_bytes_ot() == ref.write()
    assert tree.memory_usage() == ref.memoryUsage()
    before = tree.to_bytes_ot()
    n_leaves = tree.leaves()
    tree.expand()
    assert tree.num_leaf_nodes() == int((8 ** (16 - n_leaves.depths.astype(np.int64))).sum())
    assert (tree.leaves().depths == 16).all()
    tree.prune()
    assert tree.to_bytes_ot() == before


cells = st.tuples(st.integers(0, 3), st.integers(0, 3), st.integers(0, 1))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(cells, st.sampled_from([True, False, 0.3, -1.7, 0.0])),
                min_size=1, max_size=120))
def test_update_node_sequence_equals_liboctomap(ops):
    """Per-call updateNode incl. early exit at the clamps, pruning and expansion."""
    ref = octomap.OcTree(0.5)
    tree = OcTree(0.5)
    for (i, j, k), upd in ops:
        p = np.array([i * 0.5 + 0.25, j * 0.5 + 0.25, k * 0.5 + 0.25])
        ref.updateNode(p, upd if isinstance(upd, bool) else float(upd))
        tree.update_node(p[None], upd)
    assert tree.size() == ref.size()
    assert tree.to_bytes_ot() == ref.write()


def test_lazy_eval_and_update_inner_occupancy(scan_points):
    pts = scan_points[::11].astype(np.float64)
    ref = octomap.OcTree(0.2)
    ref.insertPointCloud(pts, np.zeros(3), lazy_eval=True)
    tree = OcTree(0.2)
    tree.insert_point_cloud(pts, np.zeros(3), lazy_eval=True)
    assert tree.to_bytes_ot() == ref.write()
    ref.updateInnerOccupancy()
    tree.update_inner_occupancy()
    assert tree.to_bytes_ot() == ref.write()


def test_nonfinite_and_out_of_map_points_are_skipped_and_counted(scan_points):
    pts = scan_points[:2000].copy()
    bad = pts.copy()
    bad[::10] = np.nan
    bad[5] = [np.inf, 0, 0]
    bad[7] = [1e7, 0, 0]
    clean_idx = np.ones(len(bad), bool)
    clean_idx[::10] = False
    clean_idx[[5, 7]] = False
    tree = OcTree(0.1)
    with pytest.warns(RuntimeWarning, match="skipped"):
        stats = tree.insert_point_cloud(bad, np.zeros(3))
    assert stats.n_nonfinite == 201 and stats.n_out_of_bounds == 1
    clean = OcTree(0.1)
    clean.insert_point_cloud(pts[clean_idx], np.zeros(3))
    assert tree.to_bytes_ot() == clean.to_bytes_ot()


def _scan_batch(scan_points, rng):
    """Seven scans from moving origins: one of 40k points (big enough for shares of rays),
    one with NaN and out-of-map points, one empty."""
    scans = []
    for i in range(7):
        n = 40_000 if i == 2 else int(rng.integers(500, 6000))
        pts = scan_points[rng.choice(len(scan_points), n, replace=False)] * np.float32(0.3)
        origin = rng.uniform(-0.5, 0.5, 3)
        pts = (pts + origin).astype(np.float32)
        if i == 4:
            pts[::50] = np.nan
            pts[3] = [1e7, 0, 0]
        if i == 5:
            pts = pts[:0]
        scans.append((pts, origin))
    return scans


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_insert_point_clouds_equals_scans_one_by_one_and_liboctomap(scan_points, threads,
                                                                    monkeypatch):
    """The scans marked on several threads at once and applied in order: the same tree (bytes),
    the same stats and the same warnings as one insert_point_cloud per scan, and liboctomap's
    tree."""
    import mapping.octree as octree_module

    scans = _scan_batch(scan_points, np.random.default_rng(11))
    one_by_one = OcTree(0.1)
    with warnings.catch_warnings(record=True) as caught_ref:
        warnings.simplefilter("always")
        ref_stats = [one_by_one.insert_point_cloud(p, o, max_range=3.0) for p, o in scans]
    liboctomap = octomap.OcTree(0.1)
    for p, o in scans:  # the far point still frees its first 3 m, as in liboctomap
        ok = np.isfinite(p).all(axis=1)
        liboctomap.insertPointCloud(p[ok].astype(np.float64), o.astype(np.float32).astype(float),
                                    maxrange=3.0)
    monkeypatch.setattr(octree_module, "_num_threads", lambda: threads)
    tree = OcTree(0.1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = tree.insert_point_clouds(iter(scans), max_range=3.0)
    assert tree.to_bytes_ot() == one_by_one.to_bytes_ot() == liboctomap.write()
    assert stats == ref_stats
    assert [str(w.message) for w in caught] == [str(w.message) for w in caught_ref]
    assert len(caught) == 1 and caught[0].filename == __file__


@pytest.mark.parametrize("n_scans", [1, 2])
def test_insert_point_clouds_with_fewer_scans_than_threads_shares_the_rays(scan_points, n_scans,
                                                                            monkeypatch):
    """One or two scans on three threads: the rays of each are split among the threads (as
    insert_point_cloud does), with the same tree and stats as one call per scan."""
    import mapping.octree as octree_module

    scans = _scan_batch(scan_points, np.random.default_rng(13))[2:2 + n_scans]  # 40k first
    monkeypatch.setattr(octree_module, "_num_threads", lambda: 3)
    one_by_one = OcTree(0.1)
    ref_stats = [one_by_one.insert_point_cloud(p, o, max_range=3.0) for p, o in scans]
    shares = []
    real = octree_module._scan_updates
    monkeypatch.setattr(octree_module, "_scan_updates",
                        lambda *a, **k: shares.append(k.get("max_shares")) or real(*a, **k))
    tree = OcTree(0.1)
    assert tree.insert_point_clouds(iter(scans), max_range=3.0) == ref_stats
    assert tree.to_bytes_ot() == one_by_one.to_bytes_ot()
    assert shares == [None] * n_scans  # every thread may take a share of each scan


def test_insert_point_clouds_prepares_on_the_threads_and_stops_at_a_failing_scan(
        scan_points, monkeypatch):
    """``prepare`` turns each item into its scan; a scan that fails raises in its turn, with
    the scans before it in the tree and none after it."""
    import mapping.octree as octree_module

    monkeypatch.setattr(octree_module, "_num_threads", lambda: 2)
    scans = _scan_batch(scan_points, np.random.default_rng(12))
    first_three = OcTree(0.1)
    for p, o in scans[:3]:
        first_three.insert_point_cloud(p, o)
    prepared = []

    def prepare(index):
        prepared.append(index)
        points, origin = scans[index]
        return points, (origin if index != 3 else np.array([np.nan, 0.0, 0.0]))

    tree = OcTree(0.1)
    with pytest.raises(OctreeError, match="sensor origin must be finite"):
        tree.insert_point_clouds(range(len(scans)), prepare=prepare)
    assert tree.to_bytes_ot() == first_three.to_bytes_ot()
    assert sorted(prepared)[:4] == [0, 1, 2, 3]  # every item went through prepare, in turn


# --------------------------------------------------------------------------- queries


@pytest.fixture(scope="module")
def sphere_pair(shared_data):
    from estimation.io import read_scan_graph

    g = read_scan_graph(shared_data / "octomap" / "spherical_scan.graph")
    tree = fuse(g, 0.1)
    ref = octomap.OcTree.read(tree.to_bytes_ot())
    return tree, ref


def test_search_at_every_depth_matches_liboctomap(sphere_pair, rng):
    tree, ref = sphere_pair
    pts = rng.uniform(-6, 6, size=(300, 3))
    for depth in (0, 16, 14, 10, 3):
        res = tree.search(pts, depth=depth)
        for p, known, lo in zip(pts, res.known, res.log_odds, strict=True):
            try:
                node = ref.search(p, depth=depth)
                v = node.getValue()
            except octomap.NullPointerException:
                v = None
            if v is None:
                assert not known
            else:
                assert known and np.float32(v) == lo


def test_cast_ray_matches_liboctomap(sphere_pair, rng):
    tree, ref = sphere_pair
    origins = rng.uniform(-1, 2, size=(150, 3))
    dirs = rng.normal(size=(150, 3))
    dirs[0] = [0, 0, 0]
    for ignore, max_range in [(False, -1.0), (True, -1.0), (True, 2.0)]:
        res = tree.cast_ray(origins, dirs, ignore_unknown=ignore, max_range=max_range)
        for i in range(len(origins)):
            end = np.full(3, 123.0)
            hit = ref.castRay(origins[i], dirs[i], end, ignore, max_range)
            assert bool(hit) == bool(res.hit[i])
            if res.valid[i]:
                assert np.allclose(np.float32(end), res.ends[i])
            else:
                assert not hit


def test_leaves_arrays_match_leaf_iterator(sphere_pair):
    tree, ref = sphere_pair
    lv = tree.leaves()
    # the binding's iterator object is reused: read each leaf while iterating
    it = [(_k3(n.getKey()), n.getDepth(), n.getValue(), tuple(n.getCoordinate()), n.getSize())
          for n in ref.begin_leafs()]
    assert len(lv) == len(it) == tree.num_leaf_nodes()
    for i in range(len(it)):
        key, depth, value, coord, size = it[i]
        assert key == tuple(int(v) for v in lv.keys[i])
        assert depth == lv.depths[i]
        assert np.float32(value) == lv.log_odds[i]
        assert np.allclose(coord, lv.centers[i], atol=1e-6)
        assert np.isclose(size, lv.sizes[i])
    lo, hi = tree.metric_bounds()
    assert np.allclose(lo, ref.getMetricMin()) and np.allclose(hi, ref.getMetricMax())
    assert np.isclose(tree.volume(), ref.volume())
    # bbox: every returned leaf intersects the box, and leaves fully inside are all there
    box = tree.leaves(bbox_min=[-1, -1, -1], bbox_max=[1.5, 0.5, 0.2])
    ref_box = [_k3(n.getKey()) for n in
               ref.begin_leafs_bbx(np.array([-1., -1, -1]), np.array([1.5, 0.5, 0.2]))]
    assert ref_box == [tuple(int(v) for v in k) for k in box.keys]


def test_probability_helpers(sphere_pair):
    tree, _ = sphere_pair
    lv = tree.leaves()
    assert (tree.is_occupied(lv.log_odds) == (lv.log_odds >= 0)).all()
    at = tree.is_at_threshold(np.array([3.6, 3.51103067, 0.0, -2.1], np.float32))
    assert at.tolist() == [True, True, False, True]
    assert np.allclose(probability(lv.log_odds), 1 - 1 / (1 + np.exp(lv.log_odds)))


def test_fuse_rotated_multi_node_graph_equals_graph2tree(scan_points, graph2tree, tmp_path,
                                                         kernel_backend):
    """Rotated, translated node poses: fuse() reproduces graph2tree's float32 quaternion math."""
    import gtsam

    from estimation import PoseGraph, Scan
    from estimation.io import read_scan_graph, write_scan_graph

    rng = np.random.default_rng(11)
    pg = PoseGraph()
    for i in range(3):
        rot = gtsam.Rot3.Ypr(*rng.uniform(-np.pi, np.pi, 3))
        pose = gtsam.Pose3(rot, rng.uniform(-3, 3, 3))
        pts = scan_points[rng.choice(len(scan_points), 4000, replace=False)]
        pg.add_node(i * 5 + 2, pose, scan=Scan(pts))
    path = tmp_path / "rot.graph"
    write_scan_graph(path, pg)
    ref_bt, ref_ot = graph2tree(path, 0.1, 6.0)
    tree = fuse(read_scan_graph(path), 0.1, max_range=6.0)
    assert tree.to_bytes_ot() == ref_ot
    # the in-memory graph (poses as gtsam.Pose3, no file round trip) gives the same map
    assert fuse(pg, 0.1, max_range=6.0).to_bytes_ot() == ref_ot
    tree.write_bt(tmp_path / "rot.bt")
    assert (tmp_path / "rot.bt").read_bytes() == ref_bt
    # the GTSAM-free path of `octofactor map G.graph` (the file's records, no PoseGraph)
    from estimation.scan_graph import map_scan_graph_records
    from mapping.fusion import fuse_scan_records

    nodes, _ = map_scan_graph_records(path)
    assert fuse_scan_records(nodes, 0.1, max_range=6.0).to_bytes_ot() == ref_ot


def test_mapped_scan_graph_records_equal_the_read_ones(shared_data):
    """`map G.graph` reads the file mapped and narrows each node's points later: the same ids,
    poses, points and edges as the eager reader."""
    from estimation.scan_graph import map_scan_graph_records, read_scan_graph_records

    path = shared_data / "octomap" / "spherical_scan.graph"
    nodes, edges = read_scan_graph_records(path)
    records, mapped_edges = map_scan_graph_records(path)
    assert [r.node_id for r in records] == [n.node_id for n in nodes]
    for record, node in zip(records, nodes):
        assert record.n_points == len(node.points) > 0
        assert np.array_equal(record.points(), node.points)
        assert np.array_equal(record.pose.t, node.pose.t)
        assert np.array_equal(record.pose.q_wxyz, node.pose.q_wxyz)
    assert len(mapped_edges) == len(edges)
    for mapped, edge in zip(mapped_edges, edges):
        assert (mapped.first, mapped.second, mapped.weight) == (edge.first, edge.second,
                                                                edge.weight)
        assert np.array_equal(mapped.constraint.t, edge.constraint.t)


def test_point_transform_kernel_equals_the_float32_reference(kernel_backend):
    """graph2tree's float32 quaternion transform: the kernel gives the numpy reference's bits
    (every product and sum rounded in liboctomap's order; no fused multiply-add), for random
    poses and points, signed zeros and large coordinates included."""
    from mapping.fusion import _rotate, transform_points_octomap

    f32 = np.float32

    def reference(points, t, q):  # numpy float32 arrays, one operation at a time
        p = np.asarray(points, dtype=np.float32)
        t = tuple(f32(c) for c in t)
        q = tuple(f32(c) for c in q)
        with np.errstate(all="ignore"):
            r = _rotate(q, (p[:, 0], p[:, 1], p[:, 2]))
            return np.stack([f32(r[0] + t[0]), f32(r[1] + t[1]), f32(r[2] + t[2])],
                            axis=1).astype(np.float32)

    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        t = rng.uniform(-50, 50, 3)
        pts = np.concatenate([rng.normal(scale=10, size=(2000, 3)),
                              rng.uniform(-1e4, 1e4, (200, 3)),
                              [[0.0, -0.0, 0.0], [-0.0, 0.0, -0.0], [1e-30, -1e-30, 3.0]]])
        pts = pts.astype(np.float32)
        world, _ = transform_points_octomap(pts, t, q)
        ref = reference(pts, t, q)
        assert world.dtype == np.float32 and world.shape == ref.shape
        assert world.tobytes() == ref.tobytes()
    # points in a read-only buffer run compiled too (the fixture fails on a JIT fallback)
    pts.setflags(write=False)
    assert transform_points_octomap(pts, t, q)[0].tobytes() == reference(pts, t, q).tobytes()


def test_insert_ray_equals_per_key_updates_and_cuts_at_max_range():
    o, e = np.array([0.03, -0.41, 0.2]), np.array([2.7, 1.35, -0.9])
    tree = OcTree(0.1)
    tree.insert_ray(o, e)
    ref = octomap.OcTree(0.1)
    for key in OcTree(0.1).compute_ray_keys(o, e):
        ref.updateNode(OcTree(0.1).key_to_coord(key[None])[0], False)
    ref.updateNode(e, True)
    assert tree.to_bytes_ot() == ref.write()
    cut = OcTree(0.1)
    cut.insert_ray(o, e, max_range=1.0)
    lv = cut.leaves()
    assert len(lv) > 0 and (lv.log_odds < 0).all()
    assert np.linalg.norm(lv.centers - o, axis=1).max() < 1.0 + 0.1


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.07, 0.1, 1 / 3, 0.25]),
       st.sampled_from([-1.0, 0.0, 0.5, 2.0]), st.integers(1, 4))
def test_random_scans_equal_liboctomap(seed, res, max_range, n_scans):
    """Random clouds, origins off the voxel grid, odd resolutions, several max ranges."""
    rng = np.random.default_rng(seed)
    ref = octomap.OcTree(res)
    tree = OcTree(res)
    for _ in range(n_scans):
        origin = rng.uniform(-1, 1, 3)
        pts = (origin + rng.normal(scale=rng.uniform(0.2, 3), size=(rng.integers(1, 400), 3)))
        pts = pts.astype(np.float32)
        ref.insertPointCloud(pts.astype(np.float64), origin.astype(np.float32).astype(float),
                             maxrange=max_range)
        tree.insert_point_cloud(pts, origin, max_range=max_range)
    assert tree.to_bytes_ot() == ref.write()


# --------------------------------------------------------------------------- marking paths


MARK_PATHS = pytest.mark.parametrize("mark_path", [0, 1, 2],
                                     ids=["auto", "brick-grid", "hashed"])


@contextlib.contextmanager
def _forced_path(path: int):
    """Force one ray-marking path of insert_point_cloud (0 = automatic: the dense grid here)."""
    import mapping.octree as octree_module

    old = octree_module._MARK_PATH
    octree_module._MARK_PATH = path
    try:
        yield
    finally:
        octree_module._MARK_PATH = old


def _tie_heavy_cloud(rng, res: float, origin: np.ndarray, n: int) -> np.ndarray:
    """Endpoints that make computeRayKeys break ties: axis-aligned and diagonal rays, points on
    cell corners and centres, lengths that are whole multiples of the resolution."""
    parts = []
    lengths = np.where(rng.random(n) < 0.5, rng.integers(1, 30, n) * res,
                       rng.uniform(0.01, 4.0, n))
    axis = np.eye(3)[rng.integers(0, 3, n)] * rng.choice([-1.0, 1.0], (n, 1))
    parts.append(origin + axis * lengths[:, None])
    diag = rng.choice([-1.0, 0.0, 1.0], (n, 3))
    diag[np.abs(diag).sum(axis=1) == 0, 0] = 1.0
    parts.append(origin + diag * lengths[:, None])
    corners = rng.integers(-25, 25, (n, 3)) * res
    parts.append(corners + np.where(rng.random((n, 1)) < 0.5, 0.0, 0.5 * res))
    parts.append(origin + rng.normal(scale=1.5, size=(n, 3)))
    return np.concatenate(parts).astype(np.float32)


@MARK_PATHS
@settings(max_examples=12, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.1, 0.05, 1 / 3, 0.25]),
       st.sampled_from([-1.0, 1.0, 2.5]))
def test_every_marking_path_equals_liboctomap_on_tie_heavy_rays(mark_path, seed, res,
                                                               max_range):
    """Ties in tMax (axis-aligned, diagonal rays; origins on cell corners or centres) through
    the dense grid, the brick grid and the hashed bricks; a second scan updates the first."""
    rng = np.random.default_rng(seed)
    ref = octomap.OcTree(res)
    tree = OcTree(res)
    for kind in range(2):
        k0 = rng.integers(-3, 3, 3) * res
        origin = [k0, k0 + 0.5 * res, rng.uniform(-0.5, 0.5, 3)][(seed + kind) % 3]
        origin = origin.astype(np.float32).astype(np.float64)
        pts = _tie_heavy_cloud(rng, res, origin, 150)
        ref.insertPointCloud(pts.astype(np.float64), origin, maxrange=max_range)
        with _forced_path(mark_path):
            tree.insert_point_cloud(pts, origin, max_range=max_range)
    assert tree.to_bytes_ot() == ref.write()


@MARK_PATHS
def test_rays_at_the_edge_of_the_key_space_equal_liboctomap(mark_path):
    """Rays ending next to the last keys (the DDA may step one cell past its end cell there)
    and endpoints outside the map, at 1 cm (the map ends at +-327.68 m)."""
    res = 0.01
    rng = np.random.default_rng(5)
    ref = octomap.OcTree(res)
    tree = OcTree(res)
    for origin in ([327.61, 0.003, -0.02], [-327.655, 0.0, 0.0], [0.0, 327.6, 327.6]):
        o = np.array(origin, np.float32).astype(np.float64)
        pts = o + rng.uniform(-0.09, 0.09, (400, 3))
        pts[::7] = o + rng.choice([-1.0, 1.0], (len(pts[::7]), 3)) * 0.0699
        pts = pts.astype(np.float32)
        inside = tree.coord_to_key_checked(pts)[1]
        assert 0 < (~inside).sum() < len(pts)
        ref.insertPointCloud(pts.astype(np.float64), o)
        with warnings.catch_warnings(), _forced_path(mark_path):
            warnings.simplefilter("ignore", RuntimeWarning)
            stats = tree.insert_point_cloud(pts, o)
        assert stats.n_out_of_bounds == int((~inside).sum())
    assert tree.size() == ref.size()
    assert tree.to_bytes_ot() == ref.write()


def test_marking_paths_give_identical_key_sets_on_scan_dat(scan_points):
    """The three marking paths and several thread splits on the real scan (0.1 m, 10 m)."""
    from mapping import _kernels as kern

    zero = np.zeros(3, np.float32)
    results = []
    for path in (0, 1, 2):
        for n_parts in (1, 3):
            parts = [kern.sorted_scan_marks(scan_points, zero, 0.1, 10.0, c, n_parts, 4096,
                                            np.zeros(0, np.uint8), path)
                     for c in range(n_parts)]
            tab_keys, tab_vals, pool, bcodes, nb = parts[0][:5]
            for p in parts[1:]:
                tab_keys, tab_vals, pool, bcodes, nb = kern.unite_marks(
                    tab_keys, tab_vals, pool, bcodes, nb, p[2], p[3], p[4])
            codes, upd, _ = kern.emit_updates(pool, bcodes, nb, np.float32(1.0), np.float32(0.0))
            results.append((codes, upd > 0.5))
            assert all(not p[6].any() for p in parts)  # dense grids come back zeroed
    for codes, is_hit in results[1:]:
        assert np.array_equal(codes, results[0][0]) and np.array_equal(is_hit, results[0][1])


@pytest.mark.parametrize("edge", [1, 2, 4])
def test_new_full_cubes_with_one_update_equal_per_key_updates(edge, rng):
    """A full aligned cube of new cells with one update ends as a single pruned leaf; partial
    cubes, mixed updates and cubes under existing nodes must not (updateNode per key)."""
    res = 0.1
    base = np.stack(np.meshgrid(*[np.arange(2 * edge)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = (base + 32768 + 8 * edge).astype(np.int64)
    upd = np.where(rng.random(len(keys)) < 0.1, True, False)
    upd[: len(keys) // 2] = False  # the first full cubes: one update
    keep = rng.random(len(keys)) > 0.02  # some cubes miss a cell
    keep[: len(keys) // 2] = True
    keys, upd = keys[keep], upd[keep]
    ref = octomap.OcTree(res)
    tree = OcTree(res)
    for rep in range(2):
        for key, u in zip(keys, upd):
            ref.updateNode(OcTree(res).key_to_coord(key[None])[0], bool(u))
        tree.update_node(keys, upd, keys=True)
        assert tree.size() == ref.size(), rep
        assert tree.to_bytes_ot() == ref.write()
