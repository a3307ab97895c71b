"""Fuse the scans of a PoseGraph into an OcTree the way graph2tree does.

graph2tree transforms each node's points with the node pose in float32 quaternion arithmetic
(``q * (0,p) * conj(q)``, then ``+ t``), and inserts them from the origin
``T(T^-1(t))`` computed the same way (OCTOMAP.md section 3). Reproducing that float math is
what makes the fused map bit-identical to graph2tree's.
"""
from __future__ import annotations

import numpy as np

from .octree import OcTree, _k

f32 = np.float32


def _qmul(a, b):
    """Quaternion product (u, x, y, z) in float32, term order as liboctomap's operator*."""
    au, ax, ay, az = a
    bu, bx, by, bz = b
    u = f32(f32(f32(au * bu) - f32(ax * bx)) - f32(ay * by)) - f32(az * bz)
    x = f32(f32(f32(ay * bz) - f32(by * az)) + f32(au * bx)) + f32(bu * ax)
    y = f32(f32(f32(az * bx) - f32(bz * ax)) + f32(au * by)) + f32(bu * ay)
    z = f32(f32(f32(ax * by) - f32(bx * ay)) + f32(au * bz)) + f32(bu * az)
    return (f32(u), f32(x), f32(y), f32(z))


def _rotate(q, v):
    """Quaternion::rotate: q * (0, v) * q.inv() in float32 (works on arrays of points)."""
    zero = np.zeros_like(v[0])
    qv = _qmul(q, (zero, v[0], v[1], v[2]))
    qi = (q[0], -q[1], -q[2], -q[3])
    r = _qmul(qv, qi)
    return r[1], r[2], r[3]


def _normalized(q):
    n = 0.0
    for c in q:
        n += float(f32(c * c))
    ln = f32(np.sqrt(n))
    if ln > 0:
        return tuple(f32(c / ln) for c in q)
    return q


def transform_points_octomap(points, t, q_wxyz) -> tuple[np.ndarray, np.ndarray]:
    """(points_world (N,3) float32, origin (3,) float32) as graph2tree computes them.

    ``t`` is the node translation and ``q_wxyz`` its rotation quaternion in OctoMap's order
    (w, x, y, z), both narrowed to float32 like ScanGraph's reader does.
    """
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    t = tuple(f32(c) for c in np.asarray(t, dtype=np.float64).reshape(3))
    q = tuple(f32(c) for c in np.asarray(q_wxyz, dtype=np.float64).reshape(4))
    # the points in one kernel pass (the same float32 operations as _rotate, in order)
    world = _k().transform_points_f32(p, np.array(q, np.float32), np.array(t, np.float32))
    with np.errstate(all="ignore"):
        # sensor origin: frame_origin.inv().transform(t), then frame_origin.transform(that)
        qinv = _normalized((q[0], -q[1], -q[2], -q[3]))
        mt = tuple(np.array([-c], np.float32) for c in t)
        ti = _rotate(qinv, mt)  # inv().trans = rot_inv.rotate(-t)
        tv = tuple(np.array([c], np.float32) for c in t)
        s = _rotate(qinv, tv)
        s = (f32(s[0] + ti[0]), f32(s[1] + ti[1]), f32(s[2] + ti[2]))
        o = _rotate(q, s)
        origin = np.array([f32(o[0][0] + t[0]), f32(o[1][0] + t[1]), f32(o[2][0] + t[2])],
                          np.float32)
    return world, origin


def _pose_to_t_q(pose) -> tuple[np.ndarray, np.ndarray]:
    """(t (3,), q (w,x,y,z)) of a gtsam.Pose3 or a 4x4 matrix."""
    if hasattr(pose, "translation") and hasattr(pose, "rotation"):
        t = np.asarray(pose.translation(), dtype=np.float64).reshape(3)
        rq = pose.rotation().toQuaternion()
        q = np.array([rq.w(), rq.x(), rq.y(), rq.z()], dtype=np.float64)
        return t, q
    m = np.asarray(pose, dtype=np.float64)
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return m[:3, 3].copy(), np.array([w, x, y, z])


def _same_pose(cached, t, q) -> bool:
    ct = np.asarray(cached.t, dtype=np.float64)
    cq = np.asarray(cached.q_wxyz, dtype=np.float64)
    same_q = min(np.abs(cq - q).max(), np.abs(cq + q).max()) < 1e-6
    return bool(np.abs(ct - t).max() < 1e-6 and same_q)


def fuse_scan_records(records, resolution: float, max_range: float = -1.0,
                      discretize: bool = False, progress: bool = False) -> OcTree:
    """:func:`fuse` for the nodes of a .graph file as
    :func:`estimation.scan_graph.map_scan_graph_records` gives them (no PoseGraph, so no
    GTSAM): the scans inserted at the file's float32 poses in id order, bit-identical to
    graph2tree. Each node's points are narrowed, checked and transformed on the insertion
    threads (:meth:`OcTree.insert_point_clouds`), so reading overlaps marking."""
    tree = OcTree(resolution)
    ordered = [r for r in sorted(records, key=lambda r: r.node_id) if r.n_points]
    if progress:
        from tqdm import tqdm

        ordered = tqdm(ordered, desc="fusing scans", unit="scan")

    def world_scan(record):
        return transform_points_octomap(record.points(), record.pose.t, record.pose.q_wxyz)

    tree.insert_point_clouds(ordered, max_range=max_range, discretize=discretize,
                             prepare=world_scan)
    return tree


def fuse(pose_graph, resolution: float, max_range: float = -1.0, discretize: bool = False,
         tree: OcTree | None = None, progress: bool = False, n_classes: int | None = None,
         **tree_kwargs) -> OcTree:
    """The OcTree of every node scan of ``pose_graph`` inserted at its node pose, in id order.

    Matches ``graph2tree -res R [-m max_range] [-discretize]`` bit for bit (the float32
    transform is :func:`transform_points_octomap`). The tree is not pruned further (insertion
    already prunes); ``write_bt`` converts to max-likelihood. With ``n_classes`` (or a
    SemanticOcTree as ``tree``) the scans' ``probs``/``labels`` are fused as class evidence.
    """
    from .semantic import SemanticOcTree

    if tree is None:
        if n_classes is not None:
            tree = SemanticOcTree(resolution, n_classes, **tree_kwargs)
        else:
            tree = OcTree(resolution, **tree_kwargs)
    semantic = isinstance(tree, SemanticOcTree)
    ids = pose_graph.sorted_ids() if hasattr(pose_graph, "sorted_ids") else sorted(
        pose_graph.nodes)
    nodes = [n for n in (pose_graph.nodes[i] for i in ids)
             if getattr(n, "scan", None) is not None and n.scan.points is not None
             and len(n.scan.points)]
    if progress:
        from tqdm import tqdm

        nodes = tqdm(nodes, desc="fusing scans", unit="scan")

    def world_scan(node):
        t, q = _pose_to_t_q(node.pose)
        # A node read from a .graph file keeps the file's float32 pose: use it while the pose
        # is unchanged (a Pose3 -> quaternion round trip can move the last float32 bit).
        cached = getattr(node, "metadata", {}).get("octomap_pose_f32")
        if cached is not None and _same_pose(cached, t, q):
            t = np.asarray(cached.t, dtype=np.float64)
            q = np.asarray(cached.q_wxyz, dtype=np.float64)
        return transform_points_octomap(node.scan.points, t, q)

    if not semantic:  # the scans marked concurrently, applied in id order
        tree.insert_point_clouds(nodes, max_range=max_range, discretize=discretize,
                                 prepare=world_scan)
        return tree
    for node in nodes:
        points_world, origin = world_scan(node)
        scan = node.scan
        tree.insert_point_cloud(points_world, origin, probs=scan.probs,
                                labels=None if scan.probs is not None else scan.labels,
                                max_range=max_range, discretize=discretize)
    return tree
