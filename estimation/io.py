"""PoseGraph files: TUM trajectories, g2o (via GTSAM, 3-D) and OctoMap ScanGraph ``.graph``.

Every reader raises :class:`~estimation.errors.FormatError` naming the file and the line
or byte offset; every writer writes a temporary file and renames it.

Quaternion orders: TUM lines are ``t tx ty tz qx qy qz qw`` (x y z w); g2o ``VERTEX_SE3:QUAT``
is ``x y z qx qy qz qw``; OctoMap ``.graph`` stores ``qw qx qy qz`` (w first).

A g2o file ``X.g2o`` written here gets a JSON sidecar ``X.g2o.json`` with what g2o cannot
hold (timestamps, node covariances, Pose3 priors, direction factors); :func:`read_g2o`
restores it.
"""
from __future__ import annotations

import json
import math
import os
import re
import struct
import warnings
from pathlib import Path

import gtsam
import numpy as np

from .errors import EstimationError, FormatError, OctofactorError
from .fileio import (
    atomic_write,
    check_input_file,
    library_path,
    read_input_bytes,
)
from .pose_graph import PoseGraph, Scan, as_covariance, direction_tangent_covariance, node_key
from .scan_graph import (
    MAX_COORDINATE,
    MAX_SIGMA,
    MIN_SIGMA,
    POINT_DTYPE,
    Pose6D,
    read_scan_graph_records,
)

PathLike = str | os.PathLike


def pose_from_tum(values: np.ndarray) -> gtsam.Pose3:
    """Pose3 from ``tx ty tz qx qy qz qw`` (TUM order, x y z w)."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in values)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.array([tx, ty, tz]))


def pose_to_tum(pose: gtsam.Pose3) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` (TUM order, x y z w) of a Pose3."""
    q = pose.rotation().toQuaternion()
    t = pose.translation()
    return np.array([t[0], t[1], t[2], q.x(), q.y(), q.z(), q.w()])


def _parse_float_line(path: PathLike, line_no: int, tokens: list[str], count: int,
                      what: str) -> np.ndarray:
    if len(tokens) != count:
        raise FormatError(path, f"{what}: expected {count} numbers, found {len(tokens)}",
                          line=line_no)
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError as exc:
        raise FormatError(path, f"{what}: {exc}", line=line_no) from None
    if not np.all(np.isfinite(values)):
        raise FormatError(path, f"{what}: NaN or inf value", line=line_no)
    return values


def _check_quaternion(path: PathLike, line_no: int, q: np.ndarray) -> None:
    if np.max(np.abs(q)) > 2.0:  # far from unit norm (and its norm could overflow)
        raise FormatError(path, "quaternion is not of unit norm (a component beyond 2)",
                          line=line_no)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise FormatError(path, f"quaternion norm is {norm:.6g}, not 1", line=line_no)


# ---------------------------------------------------------------- TUM
def read_tum_arrays(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Parse a TUM trajectory: (timestamps (N,), poses (N, 7) ``tx ty tz qx qy qz qw``).

    Rows stay in file order (N may be 0). Text after ``#`` and blank lines are skipped;
    commas are accepted as separators. Every value must be finite and every quaternion
    of unit norm, else a :class:`FormatError` names the file and line.
    """
    rows = []
    check_input_file(path)
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line_no, line in enumerate(handle, 1):
            tokens = line.split("#", 1)[0].replace(",", " ").split()
            if not tokens:
                continue
            values = _parse_float_line(path, line_no, tokens, 8,
                                       "TUM pose line 't tx ty tz qx qy qz qw'")
            _check_quaternion(path, line_no, values[4:8])
            _check_translation(path, line_no, values[1:4], "TUM pose")
            rows.append(values)
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return data[:, 0].copy(), data[:, 1:].copy()


def read_tum(path: PathLike) -> PoseGraph:
    """Read a TUM trajectory (``t tx ty tz qx qy qz qw`` per line) into a PoseGraph.

    Nodes get ids 0..N-1 in file order and no factors (parsing: :func:`read_tum_arrays`).
    """
    stamps, poses = read_tum_arrays(path)
    if len(stamps) == 0:
        raise FormatError(path, "no poses found in TUM trajectory")
    graph = PoseGraph()
    for stamp, values in zip(stamps, poses):
        graph.add_node(len(graph.nodes), pose_from_tum(values), timestamp=float(stamp))
    return graph


def format_tum_line(timestamp: float, pose: gtsam.Pose3) -> str:
    """One TUM line; numbers in shortest round-trip form, so nothing is truncated."""
    return " ".join(repr(float(v)) for v in (timestamp, *pose_to_tum(pose)))


def write_tum(path: PathLike, graph: PoseGraph) -> None:
    """Write the node poses as a TUM trajectory in node-id order.

    Refuses (:class:`OctofactorError`, nothing written) when the graph's timestamps are
    unknown (``graph.timestamps_missing``, e.g. a g2o file read without its sidecar), rather
    than writing made-up ones.
    """
    if graph.timestamps_missing is not None:
        raise OctofactorError(f"{path}: a TUM trajectory needs timestamps, but "
                              f"{graph.timestamps_missing}")
    with atomic_write(path, "w") as handle:
        handle.write("# timestamp tx ty tz qx qy qz qw\n")
        for node_id in graph.sorted_ids():
            node = graph.nodes[node_id]
            handle.write(format_tum_line(node.timestamp, node.pose) + "\n")


# ---------------------------------------------------------------- g2o
_G2O_TOKENS = {"VERTEX_SE3:QUAT": 9, "EDGE_SE3:QUAT": 31, "FIX": None}
_G2O_TAG = re.compile(r"[A-Z][A-Z0-9_]*(:[A-Z0-9_]+)?")
_CONTROL = re.compile(r"[\x00-\x08\x0e-\x1f\x7f]")  # binary garbage in a text line
#: GTSAM keys at or above 2**56 carry a symbol character in their top byte
MAX_NODE_ID = (1 << 56) - 1


def _check_translation(path: PathLike, line_no: int, t: np.ndarray, what: str) -> None:
    if np.max(np.abs(t)) > MAX_COORDINATE:
        raise FormatError(path, f"{what}: translation beyond {MAX_COORDINATE:g} m",
                          line=line_no)


def _node_id(path: PathLike, line_no: int, token: str) -> int:
    if not token.isdigit() or not token.isascii():
        raise FormatError(path, f"bad vertex id {token!r} (a non-negative integer)",
                          line=line_no)
    node_id = int(token)
    if node_id > MAX_NODE_ID:
        raise FormatError(path, f"vertex id {token} is beyond 2^56 - 1 (GTSAM's key range)",
                          line=line_no)
    return node_id


def _check_information(path: PathLike, line_no: int, info: np.ndarray) -> None:
    eig = np.linalg.eigvalsh(info)
    if not eig[0] > 0:
        raise FormatError(path, "edge information matrix is not positive definite",
                          line=line_no)
    if eig[0] < MAX_SIGMA ** -2 or eig[-1] > MIN_SIGMA ** -2:
        raise FormatError(path, f"edge information eigenvalues {eig[0]:.3g}..{eig[-1]:.3g} "
                          f"outside [{MAX_SIGMA ** -2:g}, {MIN_SIGMA ** -2:g}] (sigmas between "
                          f"{MIN_SIGMA:g} and {MAX_SIGMA:g})", line=line_no)


def _validate_g2o(path: PathLike) -> None:
    """Check every line GTSAM will read, so errors name the line (GTSAM's do not)."""
    seen_vertex = set()
    count = 0
    skipped: dict[str, list[int]] = {}
    check_input_file(path)
    with open(path, "rb") as handle:
        for line_no, raw in enumerate(handle, 1):
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise FormatError(path, f"not UTF-8 text (byte {exc.start} of the line)",
                                  line=line_no) from None
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            tag = tokens[0]
            if not _G2O_TAG.fullmatch(tag) or _CONTROL.search(line):
                raise FormatError(path, f"not a g2o line (tag {tag[:20]!r})", line=line_no)
            if tag in ("VERTEX_SE2", "EDGE_SE2"):
                raise FormatError(path, f"{tag} is a 2-D element; octofactor reads 3-D g2o files",
                                  line=line_no)
            if tag not in _G2O_TOKENS:  # another g2o element: GTSAM skips it too, say so
                skipped.setdefault(tag, []).append(line_no)
                continue
            expected = _G2O_TOKENS[tag]
            if expected is None:  # FIX id...: the ids must be vertices defined before
                for token in tokens[1:]:
                    if _node_id(path, line_no, token) not in seen_vertex:
                        raise FormatError(path, f"FIX refers to vertex {token} not defined "
                                          "before it", line=line_no)
                continue
            if tag == "VERTEX_SE3:QUAT":
                node_id = _node_id(path, line_no, tokens[1]) if len(tokens) > 1 else None
                values = _parse_float_line(path, line_no, tokens[1:], expected - 1, tag)
                _check_translation(path, line_no, values[1:4], tag)
                _check_quaternion(path, line_no, values[4:8])
                if node_id in seen_vertex:
                    raise FormatError(path, f"vertex {node_id} defined twice", line=line_no)
                seen_vertex.add(node_id)
            else:
                ids = [_node_id(path, line_no, t) for t in tokens[1:3]]
                values = _parse_float_line(path, line_no, tokens[1:], expected - 1, tag)
                _check_translation(path, line_no, values[2:5], tag)
                _check_quaternion(path, line_no, values[5:9])
                if ids[0] == ids[1]:
                    raise FormatError(path, f"edge from vertex {ids[0]} to itself (a self-loop)",
                                      line=line_no)
                info = np.zeros((6, 6))
                info[np.triu_indices(6)] = values[9:]
                info = info + np.triu(info, 1).T
                _check_information(path, line_no, info)
                for vertex in ids:
                    if vertex not in seen_vertex:
                        raise FormatError(path, f"edge refers to vertex {vertex} "
                                          "not defined before it", line=line_no)
            count += 1
    if count == 0:
        raise FormatError(path, "no VERTEX_SE3:QUAT or EDGE_SE3:QUAT lines (not a 3-D g2o file)")
    if skipped:
        import warnings

        from .errors import FormatWarning

        listed = ", ".join(f"{tag} x{len(lines)} (line {lines[0]}"
                           + (", ..." if len(lines) > 1 else "") + ")"
                           for tag, lines in sorted(skipped.items()))
        warnings.warn(f"{path}: skipped g2o elements octofactor does not read: {listed}",
                      FormatWarning, stacklevel=3)


def read_g2o(path: PathLike) -> PoseGraph:
    """Read a 3-D g2o file with ``gtsam.readG2o(path, is3D=True)``, and its sidecar if any.

    (Without ``is3D=True`` GTSAM silently returns an empty graph for a 3-D file.) GTSAM
    reorders g2o's information from [t, R] to the Pose3 tangent [R, t]. Edges between
    consecutive ids become ``odometry`` factors, the others ``loop`` factors.

    The sidecar ``<path>.json`` (see :func:`write_g2o`), when present, restores the node
    timestamps, node covariances and direction factors; one that does not match the g2o
    file raises a :class:`FormatError` naming the sidecar. Without it the graph's
    ``timestamps_missing`` says why there are none.
    """
    path = Path(path)
    _validate_g2o(path)
    try:
        factor_graph, initial = gtsam.readG2o(library_path(path, "GTSAM"), True)
    except RuntimeError as exc:
        raise FormatError(path, f"GTSAM could not read it: {exc}") from None
    graph = PoseGraph()
    for key in sorted(initial.keys()):
        graph.add_node(int(key), initial.atPose3(key))
    for index in range(factor_graph.size()):
        factor = factor_graph.at(index)
        if not isinstance(factor, gtsam.BetweenFactorPose3):
            continue
        i, j = (int(k) for k in factor.keys())
        noise = factor.noiseModel()
        cov = np.linalg.inv(noise.R().T @ noise.R())
        kind = "odometry" if abs(i - j) == 1 else "loop"
        graph.add_between(i, j, factor.measured(), cov, kind=kind)
    sidecar = g2o_sidecar_path(path)
    if sidecar.is_file():
        _apply_g2o_sidecar(sidecar, graph)
    else:
        graph.timestamps_missing = (
            f"{path} has none (g2o cannot store timestamps) and its sidecar {sidecar.name}, "
            "which octofactor writes beside every .g2o, is missing: convert from the file "
            "that has the timestamps (TUM trajectory, vpslam output) or keep the sidecar "
            "beside the .g2o")
    return graph


def _g2o_numbers(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def write_g2o(path: PathLike, graph: PoseGraph) -> list[str]:
    """Write a 3-D g2o file and its JSON sidecar; return what neither holds (dropped).

    The layout is the one ``gtsam.writeG2o`` writes and ``gtsam.readG2o(path, True)``
    reads (``VERTEX_SE3:QUAT id x y z qx qy qz qw``; ``EDGE_SE3:QUAT i j x y z qx qy qz qw``
    and the upper triangle of the information matrix in g2o's [t, R] order), but with
    every number in shortest round-trip form: GTSAM's own writer prints 6 significant
    digits and so moves poses by up to ~1e-6.

    What g2o cannot hold -- node timestamps, node covariances, Gaussian Pose3 priors and
    direction factors -- goes to the sidecar ``<path>.json`` (:func:`g2o_sidecar_path`;
    schema in docs/pose_graph_formats.md), written after the g2o file, each atomically.
    Robust kernels, custom factors and scans are dropped.
    """
    dropped: dict[str, None] = {}  # insertion-ordered set
    lines = []
    for node_id in graph.sorted_ids():
        tx, ty, tz, qx, qy, qz, qw = pose_to_tum(graph.nodes[node_id].pose)
        lines.append(f"VERTEX_SE3:QUAT {node_id} {_g2o_numbers((tx, ty, tz, qx, qy, qz, qw))}")
    # g2o orders the tangent [t, R]; GTSAM's Pose3 tangent is [R, t].
    reorder = np.r_[3:6, 0:3]
    upper = np.triu_indices(6)
    for record in graph.factors:
        if _sidecar_factor(record):
            continue  # in the sidecar
        if record.measured is None or len(record.nodes) != 2:
            dropped[f"{record.kind} factors"] = None
            continue
        if record.robust is not None:
            dropped["robust kernels (edges written as Gaussian)"] = None
        info = np.linalg.inv(record.covariance)[np.ix_(reorder, reorder)]
        i, j = record.nodes
        lines.append(f"EDGE_SE3:QUAT {i} {j} {_g2o_numbers(pose_to_tum(record.measured))} "
                     f"{_g2o_numbers(info[upper])}")
    if any(node.scan is not None for node in graph.nodes.values()):
        dropped["scans"] = None
    sidecar = _g2o_sidecar(path, graph)
    with atomic_write(path, "w") as handle:
        handle.write("\n".join(lines) + "\n")
    with atomic_write(g2o_sidecar_path(path), "w") as handle:
        handle.write(sidecar)
    return list(dropped)


# ---------------------------------------------------------------- g2o sidecar
G2O_SIDECAR_FORMAT = "octofactor-g2o-sidecar"
G2O_SIDECAR_VERSION = 2  # 2 added "priors"
G2O_SIDECAR_READS = (1, 2)


def _sidecar_factor(record) -> bool:
    """Whether the sidecar holds this factor: a direction factor, or a Gaussian Pose3 prior
    (a prior record of kind "prior" without a robust kernel)."""
    if record.kind == "direction":
        return "cov_tangent" in record.metadata
    return (isinstance(record.factor, gtsam.PriorFactorPose3) and record.robust is None
            and record.measured is not None and record.covariance is not None
            and len(record.nodes) == 1)


def g2o_sidecar_path(path: PathLike) -> Path:
    """The sidecar of a g2o file: ``X.g2o`` -> ``X.g2o.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def _floats(array: np.ndarray) -> list:
    return np.asarray(array, dtype=float).tolist()  # Python floats: json writes them with repr


def _g2o_sidecar(path: PathLike, graph: PoseGraph) -> str:
    """The sidecar's JSON text for ``graph`` written to ``path``."""
    known = graph.timestamps_missing is None
    nodes = []
    for node_id in graph.sorted_ids():
        node = graph.nodes[node_id]
        nodes.append({"id": node_id, "timestamp": node.timestamp if known else None,
                      "cov": None if node.cov is None else _floats(node.cov)})
    directions, priors = [], []
    for record in graph.factors:
        if record.kind != "direction" and _sidecar_factor(record):
            priors.append({"node": record.nodes[0], "kind": record.kind,
                           "pose": _floats(pose_to_tum(record.measured)),
                           "cov": _floats(record.covariance)})
        elif record.kind == "direction" and "cov_tangent" in record.metadata:
            meta = record.metadata
            directions.append({
                "node": record.nodes[0],
                "direction_sensor": _floats(meta["direction_sensor"]),
                "direction_world": _floats(meta["direction_world"]),
                "cov": _floats(meta["cov"]),
                "cov_tangent": _floats(meta["cov_tangent"]),
            })
    header = {"format": G2O_SIDECAR_FORMAT, "version": G2O_SIDECAR_VERSION,
              "g2o": Path(path).name}

    def dump(value) -> str:
        try:
            return json.dumps(value, allow_nan=False)
        except ValueError:  # unreachable through PoseGraph's checks
            raise OctofactorError(f"{g2o_sidecar_path(path)}: NaN or inf value") from None

    # One node or factor per line: readable and diffable for long graphs.
    parts = [f" {dump(key)}: {dump(value)}" for key, value in header.items()]
    for key, entries in (("nodes", nodes), ("priors", priors), ("directions", directions)):
        body = ",\n".join(f"  {dump(entry)}" for entry in entries)
        parts.append(f' "{key}": [\n{body}\n ]' if entries else f' "{key}": []')
    return "{\n" + ",\n".join(parts) + "\n}\n"


def _reject_constant(name: str):
    raise ValueError(f"non-finite number {name}")


def _is_number(value) -> bool:
    if type(value) not in (int, float):  # not bool, str, None, list
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float range
        return False


def _sidecar_array(sidecar: Path, value, shape: tuple[int, ...], where: str) -> np.ndarray:
    def leaves(item):
        if isinstance(item, list):
            for sub in item:
                yield from leaves(sub)
        else:
            yield item

    if not isinstance(value, list) or not all(_is_number(v) for v in leaves(value)):
        raise FormatError(sidecar, f"{where} must be an array of shape {shape} of finite "
                          "numbers")
    try:
        array = np.array(value, dtype=float)
    except ValueError:
        raise FormatError(sidecar, f"{where} must be an array of shape {shape}, got rows of "
                          "different lengths") from None
    if array.shape != shape:
        raise FormatError(sidecar, f"{where} must be an array of shape {shape}, got shape "
                          f"{array.shape}")
    return array


def _sidecar_list(sidecar: Path, document: dict, key: str) -> list:
    value = document.get(key)
    if not isinstance(value, list):
        raise FormatError(sidecar, f"'{key}' must be a list")
    for index, entry in enumerate(value):
        if not isinstance(entry, dict):
            raise FormatError(sidecar, f"{key}[{index}] must be an object")
    return value


def _sidecar_node(sidecar: Path, entry: dict, where: str, graph: PoseGraph) -> int:
    """The ``node`` of a sidecar entry: a node id of the g2o file, else a FormatError."""
    node_id = entry.get("node")
    if type(node_id) is not int or node_id not in graph.nodes:
        raise FormatError(sidecar, f"{where}.node must be a node id of the g2o file")
    return node_id


def _apply_g2o_sidecar(sidecar: Path, graph: PoseGraph) -> None:
    """Validate the sidecar against ``graph`` (read from its g2o file) and apply it."""
    try:
        document = json.loads(read_input_bytes(sidecar).decode("utf-8"),
                              parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise FormatError(sidecar, f"not valid JSON: {exc.msg}", line=exc.lineno) from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise FormatError(sidecar, f"not valid JSON: {exc}") from None
    except RecursionError:
        raise FormatError(sidecar, "not an octofactor g2o sidecar (JSON nested too deeply)") \
            from None
    if not isinstance(document, dict) or document.get("format") != G2O_SIDECAR_FORMAT:
        raise FormatError(sidecar, f"not an octofactor g2o sidecar (no \"format\": "
                          f"\"{G2O_SIDECAR_FORMAT}\")")
    version = document.get("version")
    if type(version) is not int or version not in G2O_SIDECAR_READS:
        raise FormatError(sidecar, f"sidecar version {version!r} is not one this octofactor "
                          f"reads ({', '.join(map(str, G2O_SIDECAR_READS))})")
    nodes = _sidecar_list(sidecar, document, "nodes")
    directions = _sidecar_list(sidecar, document, "directions")
    priors = _sidecar_list(sidecar, document, "priors") if version >= 2 else []

    ids = []
    for index, entry in enumerate(nodes):
        node_id = entry.get("id")
        if type(node_id) is not int:
            raise FormatError(sidecar, f"nodes[{index}].id must be an integer")
        ids.append(node_id)
    if sorted(ids) != graph.sorted_ids():
        only_sidecar = sorted(set(ids) - set(graph.nodes))[:5]
        only_g2o = sorted(set(graph.nodes) - set(ids))[:5]
        detail = ("duplicate ids" if len(set(ids)) != len(ids) else
                  f"only in the sidecar: {only_sidecar}, only in the g2o file: {only_g2o}")
        raise FormatError(sidecar, f"node ids do not match the g2o file ({len(ids)} in the "
                          f"sidecar, {len(graph.nodes)} in the g2o file; {detail})")

    stamps = {}
    covs = {}
    for index, entry in enumerate(nodes):
        stamp = entry.get("timestamp")
        if stamp is not None and not _is_number(stamp):
            raise FormatError(sidecar, f"nodes[{index}].timestamp must be a finite number or "
                              "null")
        stamps[entry["id"]] = stamp
        if entry.get("cov") is not None:
            cov = _sidecar_array(sidecar, entry["cov"], (6, 6), f"nodes[{index}].cov")
            try:
                covs[entry["id"]] = as_covariance(cov, f"nodes[{index}].cov")
            except EstimationError as exc:
                raise FormatError(sidecar, str(exc)) from None
    known = [stamp is not None for stamp in stamps.values()]
    if any(known) and not all(known):
        raise FormatError(sidecar, "some nodes have a timestamp and others null")

    restored_priors = []
    for index, entry in enumerate(priors):
        where = f"priors[{index}]"
        node_id = _sidecar_node(sidecar, entry, where, graph)
        kind = entry.get("kind", "prior")
        if not isinstance(kind, str) or not kind:
            raise FormatError(sidecar, f"{where}.kind must be a non-empty string")
        values = _sidecar_array(sidecar, entry.get("pose"), (7,), f"{where}.pose")
        norm = float(np.linalg.norm(values[3:]))
        if abs(norm - 1.0) > 1e-3:  # the tolerance of TUM files (a pose may come from one)
            raise FormatError(sidecar, f"{where}.pose: quaternion qx qy qz qw has norm "
                              f"{norm:.6g}, not 1")
        values[3:] /= norm
        cov = _sidecar_array(sidecar, entry.get("cov"), (6, 6), f"{where}.cov")
        try:
            cov = as_covariance(cov, f"{where}.cov")
        except EstimationError as exc:
            raise FormatError(sidecar, str(exc)) from None
        restored_priors.append((node_id, pose_from_tum(values), cov, kind))

    restored = []
    for index, entry in enumerate(directions):
        where = f"directions[{index}]"
        node_id = _sidecar_node(sidecar, entry, where, graph)
        vectors = []
        for key in ("direction_sensor", "direction_world"):
            vector = _sidecar_array(sidecar, entry.get(key), (3,), f"{where}.{key}")
            if abs(float(np.linalg.norm(vector)) - 1.0) > 1e-6:
                raise FormatError(sidecar, f"{where}.{key} is not a unit vector")
            vectors.append(vector)
        cov = _sidecar_array(sidecar, entry.get("cov"), (3, 3), f"{where}.cov")
        try:
            tangent = direction_tangent_covariance(
                graph.nodes[node_id].pose.rotation().matrix(), *vectors, cov, f"{where}.cov")
            if entry.get("cov_tangent") is not None:
                tangent = as_covariance(
                    _sidecar_array(sidecar, entry["cov_tangent"], (2, 2), f"{where}.cov_tangent"),
                    f"{where}.cov_tangent", dim=2)
        except EstimationError as exc:
            raise FormatError(sidecar, str(exc)) from None
        restored.append((node_id, *vectors, 0.5 * (cov + cov.T), tangent))

    # Everything checked: now change the graph.
    if all(known):
        for node_id, stamp in stamps.items():
            graph.nodes[node_id].timestamp = float(stamp)
    else:
        graph.timestamps_missing = (f"its source had none ({sidecar} records the node "
                                    "timestamps as null)")
    for node_id, cov in covs.items():
        graph.nodes[node_id].cov = cov
    for args in restored_priors:
        graph.add_prior(*args)
    for args in restored:
        graph._add_direction(*args)



# ---------------------------------------------------------------- OctoMap .graph
GRAPH_POSE_KEY = "octomap_pose_f32"        # node metadata: the file's float32 pose, kept exact


class _Pose6D(Pose6D):
    """A :class:`~estimation.scan_graph.Pose6D` that converts to and from ``gtsam.Pose3``."""

    def to_pose3(self) -> gtsam.Pose3:
        w, x, y, z = (float(v) for v in self.q_wxyz)
        return gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, z), self.t.astype(float))

    @classmethod
    def from_pose3(cls, pose: gtsam.Pose3) -> _Pose6D:
        q = pose.rotation().toQuaternion()
        return cls(np.asarray(pose.translation(), dtype=np.float32),
                   np.array([q.w(), q.x(), q.y(), q.z()], dtype=np.float32))


def _pose6d_for(pose: gtsam.Pose3, cached: Pose6D | None) -> Pose6D:
    # Reuse the float32 numbers read from a file while the pose is unchanged, so that a
    # read -> write round trip is byte-identical (a quaternion -> matrix -> quaternion
    # round trip can flip the last float32 bit or the sign of q).
    if cached is not None and _Pose6D(cached.t, cached.q_wxyz).to_pose3().equals(pose, 1e-6):
        return cached
    return _Pose6D.from_pose3(pose)


def read_scan_graph(path: PathLike) -> PoseGraph:
    """Read an OctoMap ScanGraph ``.graph`` file (binary, little-endian).

    Points stay float32 in the sensor frame, as OctoMap stores them. Edges become
    ``odometry`` between factors whose covariance is the identity divided by the edge
    weight (the format carries no covariance; the weight is kept in the record's metadata).
    The records are read and checked by :func:`estimation.scan_graph.read_scan_graph_records`.
    """
    nodes, edges = read_scan_graph_records(path)
    graph = PoseGraph()
    for node in nodes:
        pose6d = _Pose6D(node.pose.t, node.pose.q_wxyz)
        graph.add_node(node.node_id, pose6d.to_pose3(), scan=Scan(node.points),
                       **{GRAPH_POSE_KEY: pose6d})
    for edge in edges:
        constraint = _Pose6D(edge.constraint.t, edge.constraint.q_wxyz)
        record = graph.add_between(edge.first, edge.second, constraint.to_pose3(),
                                   np.eye(6) / edge.weight)
        record.metadata.update({GRAPH_POSE_KEY: constraint, "weight": edge.weight})
    graph.timestamps_missing = f"{path} has none (OctoMap .graph files store no timestamps)"
    return graph


def write_scan_graph(path: PathLike, graph: PoseGraph) -> list[str]:
    """Write an OctoMap ScanGraph ``.graph`` file; return what the format could not hold.

    Node ids must fit in uint32; nodes without a scan get zero points. Between factors
    become edges (their measured pose, weight from metadata or 1.0); other factors, labels
    and covariances are dropped.
    """
    dropped: dict[str, None] = {}  # insertion-ordered set
    too_big = [node_id for node_id in graph.nodes if not 0 <= node_id < 1 << 32]
    if too_big:
        raise OctofactorError(f"{path}: node id {too_big[0]} does not fit the .graph format's "
                              "uint32 ids (0 .. 2^32 - 1)")
    parts: list[bytes] = [struct.pack("<I", len(graph.nodes))]
    for node_id in graph.sorted_ids():
        node = graph.nodes[node_id]
        points = np.zeros((0, 3), np.float32) if node.scan is None else node.scan.points
        if node.scan is not None and (node.scan.labels is not None or node.scan.probs is not None):
            dropped["point labels"] = None
        if node.cov is not None:
            dropped["node covariances"] = None
        block = np.empty(len(points), dtype=POINT_DTYPE)
        block["tag"] = 3
        block["xyz"] = points.astype(np.float64)
        parts.append(struct.pack("<I", len(points)))
        parts.append(block.tobytes())
        parts.append(_pose6d_for(node.pose, node.metadata.get(GRAPH_POSE_KEY)).pack())
        parts.append(struct.pack("<I", node_id))
    edges = []
    for record in graph.factors:
        if record.measured is not None and len(record.nodes) == 2:
            edges.append(record)
        else:
            dropped[f"{record.kind} factors"] = None
    if any(record.covariance is not None for record in edges):
        dropped["edge covariances (kept as weights only)"] = None
    parts.append(struct.pack("<I", len(edges)))
    for record in edges:
        i, j = record.nodes
        parts.append(struct.pack("<II", i, j))
        parts.append(_pose6d_for(record.measured, record.metadata.get(GRAPH_POSE_KEY)).pack())
        parts.append(struct.pack("<d", float(record.metadata.get("weight", 1.0))))
    if any(node.timestamp != 0.0 for node in graph.nodes.values()):
        dropped["timestamps"] = None
    with atomic_write(path, "wb") as handle:
        for part in parts:
            handle.write(part)
    return list(dropped)


# ---------------------------------------------------------------- dispatch
FORMATS = {".graph": "octomap", ".g2o": "g2o", ".txt": "tum", ".tum": "tum",
           ".kitti": "kitti"}


def format_of(path: PathLike) -> str:
    """The pose-graph format a file name implies: 'octomap', 'g2o', 'tum' or 'kitti'."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise OctofactorError(f"{path}: unknown pose-graph format {suffix!r} "
                              "(use .graph, .g2o, .txt/.tum for TUM or .kitti for KITTI poses)")
    return FORMATS[suffix]


def read_pose_graph(path: PathLike) -> PoseGraph:
    """Read any supported pose-graph file, chosen by its extension."""
    kind = format_of(path)
    try:
        check_input_file(path)
    except FileNotFoundError:
        raise OctofactorError(f"{path}: no such file") from None
    if kind == "tum":
        from .trajectory_io import detect_trajectory_format

        # KITTI poses are often named .txt (the KITTI odometry benchmark's poses/00.txt)
        kind = detect_trajectory_format(path)
    return {"octomap": read_scan_graph, "g2o": read_g2o, "tum": read_tum,
            "kitti": read_kitti}[kind](path)


def read_kitti(path: PathLike) -> PoseGraph:
    """Read a KITTI pose file (12 numbers a line) into a PoseGraph: nodes 0..N-1 in file
    order, no factors, timestamps unknown (KITTI has none)."""
    from .trajectory_io import read_kitti_arrays

    poses = read_kitti_arrays(path)
    if len(poses) == 0:
        raise FormatError(path, "no poses found in KITTI pose file")
    graph = PoseGraph()
    for T in poses:
        graph.add_node(len(graph.nodes), T)
    graph.timestamps_missing = f"{path} is a KITTI pose file (KITTI has no timestamps)"
    return graph


def write_kitti_graph(path: PathLike, graph: PoseGraph) -> list[str]:
    """Write the node poses in node-id order as a KITTI pose file; return what was dropped."""
    from .trajectory_io import write_kitti

    ids = graph.sorted_ids()
    write_kitti(path, np.array([graph.nodes[i].pose.matrix() for i in ids]).reshape(-1, 4, 4))
    dropped = []
    if graph.timestamps_missing is None and len(ids):
        dropped.append("timestamps")
    if graph.factors:
        dropped.append("factors")
    if graph.num_points():
        dropped.append("scans")
    return dropped


def write_pose_graph(path: PathLike, graph: PoseGraph) -> list[str]:
    """Write a pose graph in the format its extension implies; return what was dropped."""
    kind = format_of(path)
    if kind == "tum":
        write_tum(path, graph)
        dropped = []
        if graph.factors:
            dropped.append("factors")
        if graph.num_points():
            dropped.append("scans")
        return dropped
    return {"octomap": write_scan_graph, "g2o": write_g2o,
            "kitti": write_kitti_graph}[kind](path, graph)


def load_node_clouds(graph: PoseGraph, directory: PathLike) -> int:
    """Attach per-node clouds ``<directory>/<node_id>.xyz|.ply|.pcd`` (sensor frame).

    ``.xyz`` is OctoMap's ASCII point file (``x y z`` per line); PLY/PCD are read with
    Open3D. Returns the number of nodes that got a cloud.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise OctofactorError(f"{directory}: cloud directory does not exist")
    attached = 0
    for node_id, node in graph.nodes.items():
        for suffix in (".xyz", ".ply", ".pcd"):
            candidate = directory / f"{node_id}{suffix}"
            if candidate.is_file():
                node.scan = Scan(_read_cloud(candidate))
                attached += 1
                break
    return attached


def _read_cloud(path: Path) -> np.ndarray:
    if path.suffix == ".xyz":
        check_input_file(path)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "no data": an error below
                points = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#",
                                    encoding="utf-8")
        except (ValueError, UnicodeDecodeError) as exc:
            reason = " ".join(str(exc).split())[:200]
            raise FormatError(path, f"not an 'x y z' point file: {reason}") from None
        if points.size == 0:
            raise FormatError(path, "no points (empty or only comments)")
        if points.shape[1] != 3:
            raise FormatError(path, f"expected 3 columns, found {points.shape[1]}")
        points = points.reshape(-1, 3)
    else:
        from .ply import check_pcd, check_ply, read_ply_quietly  # Open3D: only PLY/PCD

        if path.suffix == ".ply":
            check_ply(path)
        else:
            check_pcd(path)
        points = np.asarray(read_ply_quietly(path, legacy=True).points)
        if len(points) == 0:
            raise FormatError(path, "no points read (unreadable or empty cloud)")
    in_range = np.all(np.abs(points) <= MAX_COORDINATE, axis=1)  # NaN fails too
    if not np.all(in_range):
        raise FormatError(path, f"point {int(np.argmin(in_range))} is NaN, inf or beyond "
                          f"{MAX_COORDINATE:g} m")
    return points.astype(np.float32)


__all__ = [
    "read_tum", "read_tum_arrays", "write_tum", "read_g2o", "write_g2o", "g2o_sidecar_path",
    "read_scan_graph",
    "write_scan_graph",
    "read_pose_graph", "write_pose_graph", "load_node_clouds", "pose_from_tum", "pose_to_tum",
    "format_of", "node_key",
]
