"""The one pose-graph representation every octofactor capability reads and writes.

Node poses are ``T_world_sensor`` (:class:`gtsam.Pose3`). Every 6x6 covariance is in
GTSAM's tangent order **[rotation, translation]**, expressed in the body (sensor) frame:
a perturbation ``xi`` acts as ``T * Expmap(xi)``. Node ``i`` is the GTSAM key
``gtsam.symbol('x', i)``.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from .errors import EstimationError

FACTOR_KINDS = ("prior", "odometry", "registration", "loop", "calibration", "custom")

# A node without any prior factor leaves the graph's gauge free; optimize() then pins the
# first node with this standard deviation (rad, m) so that marginals exist.
GAUGE_SIGMA = 1e-6


def node_key(node_id: int) -> int:
    """The GTSAM key of node ``node_id``."""
    return gtsam.symbol("x", int(node_id))


def as_covariance(cov: np.ndarray, what: str = "covariance") -> np.ndarray:
    """Return ``cov`` as a validated 6x6 symmetric positive-definite float array."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6):
        raise EstimationError(f"{what} must be 6x6, got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise EstimationError(f"{what} has NaN or inf entries")
    cov = 0.5 * (cov + cov.T)
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise EstimationError(f"{what} is not positive definite") from None
    return cov


def check_pose(pose: gtsam.Pose3, what: str = "pose") -> gtsam.Pose3:
    """Reject non-Pose3 values and poses with NaN or inf entries."""
    if not isinstance(pose, gtsam.Pose3):
        raise EstimationError(f"{what} must be a gtsam.Pose3, got {type(pose).__name__}")
    if not np.all(np.isfinite(pose.matrix())):
        raise EstimationError(f"{what} has NaN or inf entries")
    return pose


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
    m-estimator, if any.
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
    """What an optimisation did: errors are GTSAM's 0.5 * sum of squared whitened residuals."""

    method: str
    initial_error: float
    final_error: float
    iterations: int


class PoseGraph:
    """Nodes with poses, scans and timestamps, and the factors between them.

    Attributes
    ----------
    nodes : dict[int, Node]
    factors : list[FactorRecord]
    """

    def __init__(self) -> None:
        self.nodes: dict[int, Node] = {}
        self.factors: list[FactorRecord] = []
        self._marginals: gtsam.Marginals | None = None
        self._isam: gtsam.ISAM2 | None = None
        self._isam_nodes: set[int] = set()
        self._isam_factor_count = 0
        self._isam_gauge_done = False

    # ---------------------------------------------------------------- building
    def add_node(self, node_id: int, T_world_sensor: gtsam.Pose3, timestamp: float = 0.0,
                 scan: Scan | None = None, cov: np.ndarray | None = None,
                 **metadata: Any) -> Node:
        """Add node ``node_id`` at pose ``T_world_sensor`` and return it."""
        node_id = int(node_id)
        if node_id < 0:
            raise EstimationError(f"node id must be >= 0, got {node_id}")
        if node_id in self.nodes:
            raise EstimationError(f"node {node_id} already exists")
        check_pose(T_world_sensor, f"pose of node {node_id}")
        if not math.isfinite(timestamp):
            raise EstimationError(f"timestamp of node {node_id} is not finite")
        node = Node(node_id, T_world_sensor, float(timestamp), scan,
                    None if cov is None else as_covariance(cov, f"covariance of node {node_id}"),
                    dict(metadata))
        self.nodes[node_id] = node
        self._marginals = None
        return node

    def _require(self, *node_ids: int) -> None:
        for node_id in node_ids:
            if node_id not in self.nodes:
                raise EstimationError(f"factor refers to unknown node {node_id}")

    def add_prior(self, node_id: int, pose: gtsam.Pose3, cov: np.ndarray,
                  kind: str = "prior") -> FactorRecord:
        """Add a prior on node ``node_id``: ``pose`` with 6x6 ``cov`` [rotation, translation]."""
        self._require(node_id)
        check_pose(pose, f"prior on node {node_id}")
        cov = as_covariance(cov, f"prior covariance on node {node_id}")
        factor = gtsam.PriorFactorPose3(node_key(node_id), pose,
                                        gtsam.noiseModel.Gaussian.Covariance(cov))
        return self._append(FactorRecord(kind, (node_id,), factor, pose, cov))

    def add_between(self, i: int, j: int, T_i_j: gtsam.Pose3, cov: np.ndarray,
                    kind: str = "odometry",
                    robust: gtsam.noiseModel.mEstimator.Base | None = None) -> FactorRecord:
        """Add a relative-pose measurement ``T_i_j`` (pose of j in the frame of i).

        ``cov`` is 6x6 in the tangent space of ``T_i_j`` [rotation, translation];
        ``robust`` wraps the Gaussian noise model in an m-estimator (e.g.
        ``gtsam.noiseModel.mEstimator.Cauchy.Create(1.0)``).
        """
        self._require(i, j)
        if kind not in FACTOR_KINDS:
            raise EstimationError(f"unknown factor kind {kind!r}; one of {FACTOR_KINDS}")
        check_pose(T_i_j, f"between measurement {i}->{j}")
        cov = as_covariance(cov, f"between covariance {i}->{j}")
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        robust_name = None
        if robust is not None:
            noise = gtsam.noiseModel.Robust.Create(robust, noise)
            robust_name = type(robust).__name__
        factor = gtsam.BetweenFactorPose3(node_key(i), node_key(j), T_i_j, noise)
        return self._append(FactorRecord(kind, (i, j), factor, T_i_j, cov, robust_name))

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

    def _has_prior(self) -> bool:
        return any(len(record.nodes) == 1 for record in self.factors)

    def _gauge_factor(self) -> gtsam.NonlinearFactor:
        first = self.sorted_ids()[0]
        return gtsam.PriorFactorPose3(node_key(first), self.nodes[first].pose,
                                      gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA))

    def _graph_for_solving(self) -> gtsam.NonlinearFactorGraph:
        graph = self.graph()
        if not self._has_prior() and self.nodes:
            graph.add(self._gauge_factor())
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
        online use); ``isam2_extra_steps`` adds relinearisation-only updates. Without
        any prior factor the first node is pinned (``GAUGE_SIGMA``).
        """
        if not self.nodes:
            raise EstimationError("cannot optimise an empty pose graph")
        initial_error = self.error()
        if method == "lm":
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(max_iterations)
            params.setRelativeErrorTol(relative_tolerance)
            optimizer = gtsam.LevenbergMarquardtOptimizer(self._graph_for_solving(),
                                                          self.values(), params)
            estimate = optimizer.optimize()
            iterations = int(optimizer.iterations())
            self._isam = None
        elif method == "isam2":
            estimate = self._isam2_update(extra_steps=isam2_extra_steps)
            iterations = 1 + isam2_extra_steps
        else:
            raise EstimationError(f"unknown optimisation method {method!r}: use 'lm' or 'isam2'")
        for node_id, node in self.nodes.items():
            node.pose = estimate.atPose3(node_key(node_id))
        self._marginals = None
        return OptimizeResult(method, initial_error, self.error(), iterations)

    def _isam2_update(self, extra_steps: int = 0) -> gtsam.Values:
        if self._isam is None:
            params = gtsam.ISAM2Params()
            # Relinearise at every update (GTSAM's default waits 10 updates), so a few
            # updates reach the batch optimum on small graphs.
            params.relinearizeSkip = 1
            params.setRelinearizeThreshold(0.001)
            self._isam = gtsam.ISAM2(params)
            self._isam_nodes = set()
            self._isam_factor_count = 0
            self._isam_gauge_done = False
        new_factors = gtsam.NonlinearFactorGraph()
        for record in self.factors[self._isam_factor_count:]:
            new_factors.add(record.factor)
        if not self._isam_gauge_done and not self._has_prior():
            new_factors.add(self._gauge_factor())
        self._isam_gauge_done = True
        new_values = gtsam.Values()
        for node_id in self.sorted_ids():
            if node_id not in self._isam_nodes:
                new_values.insert(node_key(node_id), self.nodes[node_id].pose)
                self._isam_nodes.add(node_id)
        self._isam_factor_count = len(self.factors)
        self._isam.update(new_factors, new_values)
        for _ in range(max(0, extra_steps)):
            self._isam.update()
        return self._isam.calculateEstimate()

    def _marginals_now(self) -> gtsam.Marginals:
        if self._marginals is None:
            try:
                self._marginals = gtsam.Marginals(self._graph_for_solving(), self.values())
            except RuntimeError as exc:
                raise EstimationError(
                    f"marginals do not exist (graph is singular): {exc}") from None
        return self._marginals

    def marginal_covariance(self, node_id: int) -> np.ndarray:
        """6x6 marginal covariance of node ``node_id`` at the current poses.

        Order [rotation, translation], body frame (GTSAM's Pose3 tangent). After an
        iSAM2 optimisation it comes from the iSAM2 Bayes tree.
        """
        self._require(node_id)
        if self._isam is not None and len(self.factors) == self._isam_factor_count:
            return np.array(self._isam.marginalCovariance(node_key(node_id)))
        return np.array(self._marginals_now().marginalCovariance(node_key(node_id)))

    def relative_covariance(self, i: int, j: int) -> np.ndarray:
        """6x6 covariance of ``T_i_j = T_world_i^-1 T_world_j`` in the tangent of ``T_i_j``.

        Uses the joint marginal of (i, j), so correlations between the two nodes count:
        with ``xi_ij = -Ad(T_i_j^-1) xi_i + xi_j``.
        """
        self._require(i, j)
        keys = gtsam.KeyVector()
        keys.append(node_key(i))
        keys.append(node_key(j))
        joint = self._marginals_now().jointMarginalCovariance(keys).fullMatrix()
        T_i_j = self.nodes[i].pose.between(self.nodes[j].pose)
        J = np.hstack([-T_i_j.inverse().AdjointMap(), np.eye(6)])
        cov = J @ joint @ J.T
        return 0.5 * (cov + cov.T)
