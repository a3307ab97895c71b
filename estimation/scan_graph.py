"""OctoMap ScanGraph ``.graph`` records, read without GTSAM.

``octofactor map G.graph`` needs only the nodes' float32 poses and scans: reading them here
keeps GTSAM (0.13-0.18 s to import) out of that process. :func:`estimation.io.read_scan_graph`
builds a :class:`~estimation.pose_graph.PoseGraph` from the same records, so both paths
accept and reject the same files.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

import numpy as np

from .errors import FormatError
from .fileio import BinaryReader, map_input_file, read_input_bytes

PathLike = str | os.PathLike

#: largest |coordinate| (m) a pose-graph file may hold: beyond it float64 costs overflow
MAX_COORDINATE = 1e9
#: edge information eigenvalues must lie in [1/MAX_SIGMA**2, 1/MIN_SIGMA**2]
MIN_SIGMA, MAX_SIGMA = 1e-10, 1e10
_QUICK_LIMIT = np.float32(0.999 * MAX_COORDINATE)

POINT = struct.Struct("<iddd")            # int32 tag 3, then x y z as float64
POSE = struct.Struct("<iddd" + "idddd")   # tag 3, t; tag 4, qw qx qy qz
POINT_DTYPE = np.dtype([("tag", "<i4"), ("xyz", "<f8", (3,))])


@dataclass(frozen=True)
class Pose6D:
    """An OctoMap Pose6D as float32: translation and quaternion (w, x, y, z)."""

    t: np.ndarray
    q_wxyz: np.ndarray

    def pack(self) -> bytes:
        return POSE.pack(3, *(float(v) for v in self.t), 4, *(float(v) for v in self.q_wxyz))


@dataclass(frozen=True)
class ScanNode:
    """One node of a .graph file: id, float32 points in the sensor frame, float32 pose."""

    node_id: int
    points: np.ndarray
    pose: Pose6D


@dataclass(frozen=True)
class ScanEdge:
    """One edge of a .graph file: node ids, the float32 constraint and its weight."""

    first: int
    second: int
    constraint: Pose6D
    weight: float


def read_pose6d(reader: BinaryReader, what: str) -> Pose6D:
    start = reader.pos
    values = reader.unpack("iddd" "idddd", what)
    t64, q64 = np.array(values[1:4]), np.array(values[5:9])
    if not (np.all(np.isfinite(t64)) and np.all(np.isfinite(q64))):
        raise reader.error(f"{what} has NaN or inf values", offset=start)
    if np.max(np.abs(t64)) > MAX_COORDINATE:
        raise reader.error(f"{what} translation is beyond {MAX_COORDINATE:g} m", offset=start)
    if np.max(np.abs(q64)) > 2.0:
        raise reader.error(f"{what} quaternion is not of unit norm", offset=start)
    t, q = t64.astype(np.float32), q64.astype(np.float32)
    norm = float(np.linalg.norm(q.astype(float)))
    if abs(norm - 1.0) > 1e-3:
        raise reader.error(f"{what} quaternion norm is {norm:.6g}, not 1", offset=start)
    return Pose6D(t, q)


@dataclass(frozen=True)
class ScanRecord:
    """A node of a .graph file whose points are still the file's float64 records:
    :meth:`points` narrows them to float32 and checks them, so that a reader can hand the
    nodes to several threads (:func:`map_scan_graph_records`)."""

    node_id: int
    pose: Pose6D
    raw: np.ndarray = field(repr=False)  # POINT_DTYPE records, a view into the file
    index: int = 0                       # the node's position in the file
    offset: int = 0                      # the byte offset of its point count
    path: PathLike = ""

    @property
    def n_points(self) -> int:
        return int(self.raw.shape[0])

    def points(self) -> np.ndarray:
        """The node's points as float32 (N, 3); a FormatError names the first bad point."""
        return _narrow_points(self.raw, self.path, self.index, self.offset)


def _narrow_points(raw: np.ndarray, path: PathLike, index: int, node_start: int) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        points = raw["xyz"].astype(np.float32)
    # Quick check on the float32 copy (NaN fails it, and so does an overflow to inf; the
    # margin covers float32 rounding); only a file that fails it is checked exactly, in
    # float64, to name the first bad point. Reading 50 x 100k points: 0.10 s -> 0.04 s.
    if len(points) and not (points.max() < _QUICK_LIMIT and points.min() > -_QUICK_LIMIT):
        in_range = np.all(np.abs(raw["xyz"]) <= MAX_COORDINATE, axis=1)
        if not np.all(in_range):
            bad = int(np.flatnonzero(~in_range)[0])
            raise FormatError(path, f"node #{index} point {bad} is NaN, inf or beyond "
                              f"{MAX_COORDINATE:g} m", offset=node_start + 4 + bad * POINT.size)
    return points


def read_scan_graph_records(path: PathLike) -> tuple[list[ScanNode], list[ScanEdge]]:
    """The nodes and edges of an OctoMap ScanGraph ``.graph`` file (binary, little-endian),
    checked: one :class:`~estimation.errors.FormatError` naming the file and byte offset for
    a truncated file, a lying count, NaN/inf or out-of-range numbers, a duplicate node id, an
    edge to an unknown node or to itself, a weight out of range, or trailing bytes."""
    records, edges = _read_records(path, read_input_bytes(path), narrow=True)
    return [ScanNode(r.node_id, points, r.pose) for r, points in records], edges


def map_scan_graph_records(path: PathLike) -> tuple[list[ScanRecord], list[ScanEdge]]:
    """:func:`read_scan_graph_records` with the file mapped into memory
    (:func:`~estimation.fileio.map_input_file`) and the points left in it: everything but the
    points is checked here, each node's points when :meth:`ScanRecord.points` narrows them
    (the same FormatError). ``octofactor map`` narrows them on its insertion threads."""
    records, edges = _read_records(path, map_input_file(path), narrow=False)
    return [r for r, _ in records], edges


def _read_records(path: PathLike, data, narrow: bool):
    reader = BinaryReader(data, path)
    (n_nodes,) = reader.unpack("I", "node count")
    # The smallest node is 4 + 64 + 4 bytes: a lying count fails here, before allocation.
    reader.require(n_nodes * 72, f"{n_nodes} nodes")
    records: list[tuple[ScanRecord, np.ndarray | None]] = []
    ids: set[int] = set()
    for index in range(n_nodes):
        node_start = reader.pos
        (n_points,) = reader.unpack("I", f"point count of node #{index}")
        chunk = reader.take(n_points * POINT.size, f"{n_points} points of node #{index}")
        raw = np.frombuffer(chunk, dtype=POINT_DTYPE)
        # eager: in file order, so the first bad thing in the file is the one reported
        points = _narrow_points(raw, path, index, node_start) if narrow else None
        pose = read_pose6d(reader, f"pose of node #{index}")
        (node_id,) = reader.unpack("I", f"id of node #{index}")
        if node_id in ids:
            raise reader.error(f"duplicate node id {node_id}", offset=reader.pos - 4)
        ids.add(node_id)
        records.append((ScanRecord(node_id, pose, raw, index, node_start, path), points))
    (n_edges,) = reader.unpack("I", "edge count")
    reader.require(n_edges * (8 + 64 + 8), f"{n_edges} edges")
    edges: list[ScanEdge] = []
    for index in range(n_edges):
        edge_start = reader.pos
        first, second = reader.unpack("II", f"node ids of edge #{index}")
        constraint = read_pose6d(reader, f"constraint of edge #{index}")
        (weight,) = reader.unpack("d", f"weight of edge #{index}")
        if first not in ids or second not in ids:
            raise reader.error(f"edge #{index} refers to unknown node {first} or {second}",
                               offset=edge_start)
        if first == second:
            raise reader.error(f"edge #{index} goes from node {first} to itself (a self-loop)",
                               offset=edge_start)
        if not MAX_SIGMA ** -2 <= weight <= MIN_SIGMA ** -2:  # NaN fails too
            raise reader.error(f"edge #{index} weight {weight} is outside "
                               f"[{MAX_SIGMA ** -2:g}, {MIN_SIGMA ** -2:g}]",
                               offset=reader.pos - 8)
        edges.append(ScanEdge(first, second, constraint, weight))
    if reader.remaining:
        raise reader.error(f"{reader.remaining} unexpected bytes after the last edge")
    return records, edges
