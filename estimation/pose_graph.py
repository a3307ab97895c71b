"""The one pose-graph representation every octofactor capability reads and writes.

Node poses are ``T_world_sensor`` (:class:`gtsam.Pose3`, or a 4x4 homogeneous array where a
pose is taken). Every 6x6 covariance is in GTSAM's tangent order **[rotation, translation]**,
expressed in the body (sensor) frame: a perturbation ``xi`` acts as ``T * Expmap(xi)``.
Node ``i`` is the GTSAM key ``gtsam.symbol('x', i)``.
"""
from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from .errors import EstimationError

FACTOR_KINDS = ("prior", "odometry", "registration", "loop", "calibration", "direction",
                "custom")

# Without a Pose3 prior the graph's gauge (where the whole graph sits in the world) is free;
# optimize() and the marginals then anchor the first node at its current pose with this weak
# prior (standard deviation in rad for the rotation, m for the translation). Weak, so that
# direction factors, which observe absolute rotation, are not overruled by the first node's
# initial rotation; the marginals of such a graph include this anchor's uncertainty.
GAUGE_SIGMA = 1.0

# How far a 4x4 array's rotation block may be from orthonormal before it is rejected; within
# it the block is projected onto the nearest rotation (float32 matrices are ~1e-7 off).
ORTHONORMAL_TOL = 1e-5

# GTSAM 4.3 renamed Pose3AttitudeFactor(key, nZ, model, bRef) to
# AttitudeFactorPose3(key, nRef, model, bMeasured): same argument order and meaning.
_ATTITUDE_FACTOR = getattr(gtsam, "AttitudeFactorPose3", None) or getattr(
    gtsam, "Pose3AttitudeFactor", None)


def node_key(node_id: int) -> int:
    """The GTSAM key of node ``node_id``."""
    return gtsam.symbol("x", int(node_id))


def as_covariance(cov: np.ndarray, what: str = "covariance", dim: int = 6) -> np.ndarray:
    """Return ``cov`` as a validated dim x dim symmetric positive-definite float array."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (dim, dim):
        raise EstimationError(f"{what} must be {dim}x{dim}, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise EstimationError(f"{what} has NaN or inf entries")
    cov = 0.5 * (cov + cov.T)
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise EstimationError(f"{what} is not positive definite") from None
    return cov


def as_pose3(pose: gtsam.Pose3 | np.ndarray, what: str = "pose") -> gtsam.Pose3:
    """Return ``pose`` as a finite :class:`gtsam.Pose3`.

    Parameters
    ----------
    pose : gtsam.Pose3 or (4, 4) array_like
        A 4x4 array must be a finite homogeneous transform: last row ``[0, 0, 0, 1]`` and a
        rotation block orthonormal with det +1 within ``ORTHONORMAL_TOL`` (it is projected
        onto the nearest rotation).
    what : str
        Names the argument in the :class:`EstimationError` raised for anything else.
    """
    if isinstance(pose, gtsam.Pose3):
        if not np.all(np.isfinite(pose.matrix())):
            raise EstimationError(f"{what} has NaN or inf entries")
        return pose
    if not isinstance(pose, (np.ndarray, list, tuple)):
        raise EstimationError(
            f"{what} must be a gtsam.Pose3 or a 4x4 array, got {type(pose).__name__}")
    try:
        T = np.asarray(pose, dtype=float)
    except (TypeError, ValueError):
        raise EstimationError(f"{what} must be a gtsam.Pose3 or a 4x4 array of numbers") from None
    if T.shape != (4, 4):
        raise EstimationError(
            f"{what} must be a gtsam.Pose3 or a 4x4 array, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise EstimationError(f"{what} has NaN or inf entries")
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > ORTHONORMAL_TOL:
        raise EstimationError(f"{what}: last row is {T[3].tolist()}, not [0, 0, 0, 1]")
    R = T[:3, :3]
    deviation = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if deviation > ORTHONORMAL_TOL:
        raise EstimationError(
            f"{what}: rotation block is not orthonormal (max |R^T R - I| = {deviation:.3g})")
    if np.linalg.det(R) < 0:
        raise EstimationError(f"{what}: rotation block has det -1 (a reflection)")
    U, _, Vt = np.linalg.svd(R)
    return gtsam.Pose3(gtsam.Rot3(U @ Vt), T[:3, 3].copy())


def check_pose(pose: gtsam.Pose3 | np.ndarray, what: str = "pose") -> gtsam.Pose3:
    """Reject poses with NaN or inf entries and non-poses (alias of :func:`as_pose3`)."""
    return as_pose3(pose, what)


def _unit_vector(vector: np.ndarray, what: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=float)
    if vector.shape != (3,):
        raise EstimationError(f"{what} must have shape (3,), got {vector.shape}")
    if not np.all(np.isfinite(vector)):
        raise EstimationError(f"{what} has NaN or inf entries")
    norm = float(np.linalg.norm(vector))
    if norm < 1e-12:
        raise EstimationError(f"{what} is the zero vector, not a direction")
    return vector / norm


def direction_tangent_covariance(R_world_sensor: np.ndarray, direction_sensor: np.ndarray,
                                 direction_world: np.ndarray, cov_sensor: np.ndarray,
                                 what: str = "direction covariance") -> np.ndarray:
    """The 2x2 covariance, in the error basis of a direction factor, of a sensor-frame one.

    The error of GTSAM's attitude factor is 2-D in ``gtsam.Unit3(direction_world).basis()``
    ``B``; to first order a perturbation ``delta`` of the unit ``direction_sensor`` moves it
    by ``B^T R delta``. ``R`` is ``R_world_sensor`` corrected by the smallest rotation that
    carries ``R direction_sensor`` onto ``direction_world`` (so a poor initial rotation does
    not tilt the projection); the result is ``B^T R cov_sensor R^T B``.
    """
    cov = np.asarray(cov_sensor, dtype=float)
    if cov.shape != (3, 3):
        raise EstimationError(f"{what} must be 3x3 (sensor frame), got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise EstimationError(f"{what} has NaN or inf entries")
    cov = 0.5 * (cov + cov.T)
    eigenvalues = np.linalg.eigvalsh(cov)
    if eigenvalues[0] < -1e-12 * max(1.0, float(eigenvalues[-1])):
        raise EstimationError(f"{what} is not positive semi-definite")
    rotated = R_world_sensor @ direction_sensor
    axis = np.cross(rotated, direction_world)
    sin_angle, cos_angle = float(np.linalg.norm(axis)), float(rotated @ direction_world)
    if sin_angle > 1e-12:
        axis = axis / sin_angle
    elif cos_angle < 0:  # opposite directions: any axis perpendicular to them
        axis = np.cross(rotated, np.eye(3)[int(np.argmin(np.abs(rotated)))])
        axis = axis / np.linalg.norm(axis)
    R = gtsam.Rot3.Expmap(axis * math.atan2(sin_angle, cos_angle)).matrix() @ R_world_sensor
    B = np.asarray(gtsam.Unit3(direction_world).basis())
    BR = B.T @ R
    cov_tangent = BR @ cov @ BR.T
    cov_tangent = 0.5 * (cov_tangent + cov_tangent.T)
    try:
        np.linalg.cholesky(cov_tangent)
    except np.linalg.LinAlgError:
        raise EstimationError(f"{what} has no spread perpendicular to direction_sensor "
                              "(a direction has 2 dof: its 2x2 projection is singular)") from None
    return cov_tangent


_SYMBOL = re.compile(r"Symbol: ([A-Za-z])(\d+)")


def gtsam_failure(what: str, exc: Exception) -> EstimationError:
    """One-line :class:`EstimationError` for an exception GTSAM raised during ``what``."""
    text = " ".join(str(exc).split())
    if "Indeterminate linear system" in text or "ndeterminant" in text:
        match = _SYMBOL.search(text)
        near = ""
        if match:
            near = (f" near node {match.group(2)}" if match.group(1) == "x"
                    else f" near variable {match.group(1)}{match.group(2)}")
        return EstimationError(
            f"{what} failed: indeterminate linear system{near} (some of its 6 dof are "
            "constrained by no factor, e.g. factors whose information is zero in some "
            "direction); add a prior or more factors")
    if len(text) > 300:
        text = text[:297] + "..."
    return EstimationError(f"{what} failed: {type(exc).__name__}: {text or 'no message'}")


@dataclass(frozen=True)
class Scan:
    """A point cloud attached to a node, in the node's **sensor** frame.

    Attributes
    ----------
    points : (N, 3) float32
    labels : (N,) int32 or None -- argmax class per point
    probs : (N, C) float32 or None -- class probabilities per point
    """

    points: np.ndarray
    labels: np.ndarray | None = None
    probs: np.ndarray | None = None

    def __post_init__(self):
        points = np.ascontiguousarray(np.asarray(self.points, dtype=np.float32).reshape(-1, 3))
        object.__setattr__(self, "points", points)
        n = len(points)
        if self.labels is not None:
            labels = np.asarray(self.labels, dtype=np.int32).reshape(-1)
            if len(labels) != n:
                raise EstimationError(f"scan has {n} points but {len(labels)} labels")
            object.__setattr__(self, "labels", labels)
        if self.probs is not None:
            probs = np.asarray(self.probs, dtype=np.float32)
            if probs.ndim != 2 or len(probs) != n:
                raise EstimationError(f"scan has {n} points but probs of shape {probs.shape}")
            object.__setattr__(self, "probs", probs)

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class Node:
    """A pose-graph node: ``pose`` is ``T_world_sensor``; ``cov`` an optional 6x6 prior
    knowledge of its uncertainty (e.g. the EKF's marginal), [rotation, translation]."""

    id: int
    pose: gtsam.Pose3
    timestamp: float = 0.0
    scan: Scan | None = None
    cov: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FactorRecord:
    """A factor with what octofactor knows about it.

    ``nodes`` are node ids; ``measured`` and ``covariance`` are set for prior and between
    factors (``measured`` is ``T_i_j`` for a between factor); ``robust`` names the
    m-estimator, if any. A ``direction`` factor keeps its inputs in ``metadata``
    (see :meth:`PoseGraph.add_direction`).
    """

    kind: str
    nodes: tuple[int, ...]
    factor: gtsam.NonlinearFactor
    measured: gtsam.Pose3 | None = None
    covariance: np.ndarray | None = None
    robust: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class OptimizeResult:
    """What an optimisation did: errors are GTSAM's 0.5 * sum of squared whitened residuals.

    ``anchored_nodes`` are the nodes a weak gauge prior (``GAUGE_SIGMA``) was put on: the
    first node of each connected part of the graph that has no Pose3 prior (one node for a
    connected graph without a prior); ``anchored_node`` is the first of them, else None. The
    errors never include those anchors.
    """

    method: str
    initial_error: float
    final_error: float
    iterations: int
    anchored_node: int | None = None
    anchored_nodes: tuple[int, ...] = ()


class PoseGraph:
    """Nodes with poses, scans and timestamps, and the factors between them.

    Attributes
    ----------
    nodes : dict[int, Node]
    factors : list[FactorRecord]
    timestamps_missing : str or None
        Why the node timestamps are unknown (e.g. the graph was read from a g2o file without
        its sidecar); None when they are known. Writers that need timestamps refuse then.
    """

    def __init__(self) -> None:
        self.nodes: dict[int, Node] = {}
        self.factors: list[FactorRecord] = []
        self.timestamps_missing: str | None = None
        self._marginals: gtsam.Marginals | None = None
        self._reset_isam()

    def _reset_isam(self) -> None:
        self._isam: gtsam.ISAM2 | None = None
        self._isam_nodes: set[int] = set()
        self._isam_factor_count = 0
        self._isam_anchors: list[int] = []

    # ---------------------------------------------------------------- building
    def add_node(self, node_id: int, T_world_sensor: gtsam.Pose3 | np.ndarray,
                 timestamp: float = 0.0, scan: Scan | None = None,
                 cov: np.ndarray | None = None, **metadata: Any) -> Node:
        """Add node ``node_id`` at pose ``T_world_sensor`` (Pose3 or 4x4) and return it."""
        node_id = int(node_id)
        if not 0 <= node_id < 1 << 56:
            raise EstimationError(f"node_id must be in 0 .. 2^56 - 1 (GTSAM's key range), got "
                                  f"{node_id}")
        if node_id in self.nodes:
            raise EstimationError(f"node {node_id} already exists")
        pose = as_pose3(T_world_sensor, f"T_world_sensor of node {node_id}")
        if not math.isfinite(timestamp):
            raise EstimationError(f"timestamp of node {node_id} is not finite")
        node = Node(node_id, pose, float(timestamp), scan,
                    None if cov is None else as_covariance(cov, f"covariance of node {node_id}"),
                    dict(metadata))
        self.nodes[node_id] = node
        self._marginals = None
        return node

    def _require(self, *node_ids: int) -> None:
        for node_id in node_ids:
            if node_id not in self.nodes:
                raise EstimationError(f"factor refers to unknown node {node_id}")

    def _require_node(self, *node_ids: int) -> None:
        for node_id in node_ids:
            if node_id not in self.nodes:
                raise EstimationError(f"node {node_id} is not in the graph")

    def add_prior(self, node_id: int, pose: gtsam.Pose3 | np.ndarray, cov: np.ndarray,
                  kind: str = "prior") -> FactorRecord:
        """Add a prior on node ``node_id``: ``pose`` (Pose3 or 4x4) with 6x6 ``cov``
        [rotation, translation]."""
        self._require(node_id)
        pose = as_pose3(pose, f"pose of the prior on node {node_id}")
        cov = as_covariance(cov, f"prior covariance on node {node_id}")
        factor = gtsam.PriorFactorPose3(node_key(node_id), pose,
                                        gtsam.noiseModel.Gaussian.Covariance(cov))
        return self._append(FactorRecord(kind, (node_id,), factor, pose, cov))

    def add_between(self, i: int, j: int, T_i_j: gtsam.Pose3 | np.ndarray, cov: np.ndarray,
                    kind: str = "odometry",
                    robust: gtsam.noiseModel.mEstimator.Base | None = None) -> FactorRecord:
        """Add a relative-pose measurement ``T_i_j`` (pose of j in the frame of i).

        ``T_i_j`` is a Pose3 or a 4x4 array; ``cov`` is 6x6 in the tangent space of
        ``T_i_j`` [rotation, translation]; ``robust`` wraps the Gaussian noise model in an
        m-estimator (e.g. ``gtsam.noiseModel.mEstimator.Cauchy.Create(1.0)``).
        """
        self._require(i, j)
        if i == j:
            raise EstimationError(f"a between factor needs two nodes, got {i} -> {j} (a "
                                  "self-loop)")
        if kind not in FACTOR_KINDS:
            raise EstimationError(f"unknown factor kind {kind!r}; one of {FACTOR_KINDS}")
        T_i_j = as_pose3(T_i_j, f"T_i_j of the between factor {i}->{j}")
        cov = as_covariance(cov, f"between covariance {i}->{j}")
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        robust_name = None
        if robust is not None:
            noise = gtsam.noiseModel.Robust.Create(robust, noise)
            robust_name = type(robust).__name__
        factor = gtsam.BetweenFactorPose3(node_key(i), node_key(j), T_i_j, noise)
        return self._append(FactorRecord(kind, (i, j), factor, T_i_j, cov, robust_name))

    def add_direction(self, node_id: int, direction_sensor: np.ndarray,
                      direction_world: np.ndarray, cov: np.ndarray) -> FactorRecord:
        """Add a direction (vanishing-point) factor on the rotation of node ``node_id``.

        The factor wants ``R_world_sensor @ direction_sensor == direction_world``; it is
        GTSAM's own ``AttitudeFactorPose3`` (``Pose3AttitudeFactor`` before GTSAM 4.3) with
        ``nRef = direction_world`` and ``bMeasured = direction_sensor``.

        Parameters
        ----------
        node_id : int
        direction_sensor : (3,) array
            The measured direction in the node's **sensor (camera)** frame, e.g. a vanishing
            point back-projected as ``K^-1 [u, v, 1]``. Normalised here.
        direction_world : (3,) array
            The **world**-frame direction it should map to (a known or separately estimated
            dominant direction). Normalised here. ``d`` and ``-d`` are different directions:
            resolve a vanishing point's sign before adding it.
        cov : (3, 3) array
            Covariance of the unit ``direction_sensor``, in the **sensor** frame. Only its
            part perpendicular to ``direction_sensor`` counts (a direction has 2 dof), e.g.
            ``sigma**2 * (I - d d^T)`` for an angular error of ``sigma`` rad.

        Returns
        -------
        FactorRecord
            Kind ``"direction"``; ``metadata`` holds ``direction_sensor``,
            ``direction_world`` (unit, (3,)), ``cov`` ((3, 3), sensor frame) and
            ``cov_tangent``, the 2x2 covariance of the factor's error in the basis
            ``gtsam.Unit3(direction_world).basis()``.

        Notes
        -----
        The error is 2-D in the tangent of ``direction_world``; ``cov`` is mapped into it with
        the node's rotation at the time of the call (:func:`direction_tangent_covariance`;
        exact for ``sigma**2 (I - d d^T)`` whatever that rotation). The factor constrains the
        two rotation dof perpendicular to ``direction_world``; the rotation about it and the
        translation stay free.
        """
        self._require(node_id)
        what = f"direction factor on node {node_id}"
        if _ATTITUDE_FACTOR is None:
            raise EstimationError(f"{what}: this GTSAM has neither AttitudeFactorPose3 nor "
                                  "Pose3AttitudeFactor")
        d_sensor = _unit_vector(direction_sensor, f"direction_sensor of the {what}")
        d_world = _unit_vector(direction_world, f"direction_world of the {what}")
        cov = np.asarray(cov, dtype=float)
        cov_tangent = direction_tangent_covariance(
            self.nodes[node_id].pose.rotation().matrix(), d_sensor, d_world, cov,
            f"covariance of the {what}")
        return self._add_direction(node_id, d_sensor, d_world, 0.5 * (cov + cov.T), cov_tangent)

    def _add_direction(self, node_id: int, d_sensor: np.ndarray, d_world: np.ndarray,
                       cov: np.ndarray, cov_tangent: np.ndarray) -> FactorRecord:
        """Add a validated direction factor as given (the g2o sidecar reader restores one)."""
        factor = _ATTITUDE_FACTOR(node_key(node_id), gtsam.Unit3(d_world),
                                  gtsam.noiseModel.Gaussian.Covariance(cov_tangent),
                                  gtsam.Unit3(d_sensor))
        metadata = {"direction_sensor": d_sensor, "direction_world": d_world, "cov": cov,
                    "cov_tangent": cov_tangent}
        return self._append(FactorRecord("direction", (node_id,), factor, metadata=metadata))

    def add_factor(self, factor: gtsam.NonlinearFactor, kind: str = "custom") -> FactorRecord:
        """Add any GTSAM factor on node keys (``node_key(i)``)."""
        node_ids = []
        for key in factor.keys():
            symbol = gtsam.Symbol(key)
            if chr(symbol.chr()) != "x":
                raise EstimationError(f"factor key {symbol.string()} is not a node key x<i>")
            node_ids.append(int(symbol.index()))
        self._require(*node_ids)
        return self._append(FactorRecord(kind, tuple(node_ids), factor))

    def _append(self, record: FactorRecord) -> FactorRecord:
        self.factors.append(record)
        self._marginals = None
        return record

    # ---------------------------------------------------------------- views
    def sorted_ids(self) -> list[int]:
        return sorted(self.nodes)

    def factor_counts(self) -> dict[str, int]:
        """Number of factors per kind."""
        return dict(Counter(record.kind for record in self.factors))

    def graph(self) -> gtsam.NonlinearFactorGraph:
        """All factors as a GTSAM graph (without the automatic gauge prior)."""
        graph = gtsam.NonlinearFactorGraph()
        for record in self.factors:
            graph.add(record.factor)
        return graph

    def values(self) -> gtsam.Values:
        """The current node poses as GTSAM values."""
        values = gtsam.Values()
        for node_id, node in self.nodes.items():
            values.insert(node_key(node_id), node.pose)
        return values

    def poses(self) -> np.ndarray:
        """(N, 4, 4) pose matrices in ``sorted_ids()`` order."""
        return np.array([self.nodes[i].pose.matrix() for i in self.sorted_ids()]).reshape(-1, 4, 4)

    def timestamps(self) -> np.ndarray:
        return np.array([self.nodes[i].timestamp for i in self.sorted_ids()], dtype=float)

    def num_points(self) -> int:
        return sum(len(node.scan) for node in self.nodes.values() if node.scan is not None)

    def has_pose_prior(self) -> bool:
        """Whether some factor is a Pose3 prior, which fixes the gauge.

        Other one-node factors (direction factors fix 2 rotation dof) do not count.
        """
        return any(isinstance(record.factor, gtsam.PriorFactorPose3) for record in self.factors)

    def _has_prior(self) -> bool:  # the name older callers used
        return self.has_pose_prior()

    def unanchored_parts(self) -> list[int]:
        """The first node of each connected part of the graph (nodes joined by factors on
        two or more nodes) that holds no Pose3 prior: its gauge is free."""
        parent = {node_id: node_id for node_id in self.nodes}

        def root(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for record in self.factors:
            first, *rest = record.nodes
            for other in rest:
                parent[root(other)] = root(first)
        anchored = {root(record.nodes[0]) for record in self.factors
                    if isinstance(record.factor, gtsam.PriorFactorPose3)}
        firsts: dict[int, int] = {}
        for node_id in self.sorted_ids():
            firsts.setdefault(root(node_id), node_id)
        return sorted(first for r, first in firsts.items() if r not in anchored)

    def _gauge_factor(self, node_id: int) -> gtsam.NonlinearFactor:
        return gtsam.PriorFactorPose3(node_key(node_id), self.nodes[node_id].pose,
                                      gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA))

    def _graph_for_solving(self) -> gtsam.NonlinearFactorGraph:
        graph = self.graph()
        for node_id in self.unanchored_parts():
            graph.add(self._gauge_factor(node_id))
        return graph

    def error(self) -> float:
        """GTSAM's total error 0.5 * sum ||whitened residual||^2 at the current poses."""
        return float(self.graph().error(self.values()))

    # ---------------------------------------------------------------- solving
    def optimize(self, method: str = "lm", max_iterations: int = 100,
                 relative_tolerance: float = 1e-9, isam2_extra_steps: int = 0) -> OptimizeResult:
        """Optimise the node poses in place and return the errors before and after.

        ``method="lm"`` runs Levenberg-Marquardt on the whole graph. ``method="isam2"``
        feeds the nodes and factors added since the previous iSAM2 call to an
        incremental :class:`gtsam.ISAM2` and updates it (call it after each new node for
        online use); ``isam2_extra_steps`` adds relinearisation-only updates. Without a
        Pose3 prior the first node is anchored with a weak prior (``GAUGE_SIGMA``; reported
        as ``anchored_node``). A failure inside GTSAM (e.g. an indeterminate linear system)
        raises a one-line :class:`EstimationError`; the poses are then unchanged.
        """
        if not self.nodes:
            raise EstimationError("cannot optimise an empty pose graph")
        initial_error = self.error()
        if method == "lm":
            anchored = tuple(self.unanchored_parts())
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(max_iterations)
            params.setRelativeErrorTol(relative_tolerance)
            try:
                optimizer = gtsam.LevenbergMarquardtOptimizer(self._graph_for_solving(),
                                                              self.values(), params)
                estimate = optimizer.optimize()
            except (RuntimeError, IndexError, ValueError) as exc:
                raise gtsam_failure("Levenberg-Marquardt", exc) from None
            iterations = int(optimizer.iterations())
            self._reset_isam()
        elif method == "isam2":
            estimate = self._isam2_update(extra_steps=isam2_extra_steps)
            anchored = tuple(self._isam_anchors)
            iterations = 1 + isam2_extra_steps
        else:
            raise EstimationError(f"unknown optimisation method {method!r}: use 'lm' or 'isam2'")
        poses = {node_id: estimate.atPose3(node_key(node_id)) for node_id in self.nodes}
        if not all(np.all(np.isfinite(pose.matrix())) for pose in poses.values()):
            raise EstimationError(f"{method} produced NaN or inf poses; the graph is degenerate")
        for node_id, pose in poses.items():
            self.nodes[node_id].pose = pose
        self._marginals = None
        return OptimizeResult(method, initial_error, self.error(), iterations,
                              anchored[0] if anchored else None, anchored)

    def _isam2_update(self, extra_steps: int = 0) -> gtsam.Values:
        if self._isam is None:
            params = gtsam.ISAM2Params()
            # Relinearise at every update (GTSAM's default waits 10 updates), so a few
            # updates reach the batch optimum on small graphs.
            params.relinearizeSkip = 1
            params.setRelinearizeThreshold(0.001)
            self._isam = gtsam.ISAM2(params)
        new_factors = gtsam.NonlinearFactorGraph()
        for record in self.factors[self._isam_factor_count:]:
            new_factors.add(record.factor)
        # a weak prior on each part with a free gauge (once per part)
        anchors = [node_id for node_id in self.unanchored_parts()
                   if node_id not in self._isam_anchors]
        for node_id in anchors:
            new_factors.add(self._gauge_factor(node_id))
        new_values = gtsam.Values()
        new_nodes = [node_id for node_id in self.sorted_ids() if node_id not in self._isam_nodes]
        for node_id in new_nodes:
            new_values.insert(node_key(node_id), self.nodes[node_id].pose)
        try:
            self._isam.update(new_factors, new_values)
            for _ in range(max(0, extra_steps)):
                self._isam.update()
            estimate = self._isam.calculateEstimate()
        except (RuntimeError, IndexError, ValueError) as exc:
            # The Bayes tree may hold part of this update: start afresh next time rather
            # than trust it (a stale tree misses keys or returns a wrong estimate).
            self._reset_isam()
            raise gtsam_failure("iSAM2", exc) from None
        # Book-keep only once GTSAM has taken the update.
        self._isam_anchors.extend(anchors)
        self._isam_nodes.update(new_nodes)
        self._isam_factor_count = len(self.factors)
        return estimate

    def _isam_is_current(self) -> bool:
        return (self._isam is not None and len(self.factors) == self._isam_factor_count
                and self._isam_nodes == set(self.nodes))

    def _marginals_now(self) -> gtsam.Marginals:
        if self._marginals is None:
            try:
                self._marginals = gtsam.Marginals(self._graph_for_solving(), self.values())
            except (RuntimeError, IndexError, ValueError) as exc:
                raise gtsam_failure("marginals", exc) from None
        return self._marginals

    def marginal_covariance(self, node_id: int) -> np.ndarray:
        """6x6 marginal covariance of node ``node_id`` at the current poses.

        Order [rotation, translation], body frame (GTSAM's Pose3 tangent). After an
        iSAM2 optimisation that saw every node and factor it comes from the iSAM2 Bayes
        tree. Without a Pose3 prior it includes the weak gauge anchor (``GAUGE_SIGMA``).
        """
        self._require_node(node_id)
        if not any(node_id in record.nodes for record in self.factors):
            raise EstimationError(f"node {node_id} has no factor: its marginal covariance is "
                                  "undefined")
        try:
            if self._isam_is_current():
                return np.array(self._isam.marginalCovariance(node_key(node_id)))
            return np.array(self._marginals_now().marginalCovariance(node_key(node_id)))
        except (RuntimeError, IndexError, ValueError) as exc:
            raise gtsam_failure(f"marginal covariance of node {node_id}", exc) from None

    def relative_covariance(self, i: int, j: int) -> np.ndarray:
        """6x6 covariance of ``T_i_j = T_world_i^-1 T_world_j`` in the tangent of ``T_i_j``.

        Uses the joint marginal of (i, j), so correlations between the two nodes count:
        with ``xi_ij = -Ad(T_i_j^-1) xi_i + xi_j``.
        """
        self._require_node(i, j)
        keys = gtsam.KeyVector()
        keys.append(node_key(i))
        keys.append(node_key(j))
        try:
            joint = self._marginals_now().jointMarginalCovariance(keys).fullMatrix()
        except (RuntimeError, IndexError, ValueError) as exc:
            raise gtsam_failure(f"joint marginal of nodes {i} and {j}", exc) from None
        T_i_j = self.nodes[i].pose.between(self.nodes[j].pose)
        J = np.hstack([-T_i_j.inverse().AdjointMap(), np.eye(6)])
        cov = J @ joint @ J.T
        return 0.5 * (cov + cov.T)
