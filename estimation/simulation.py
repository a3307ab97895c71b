"""Synthetic pose graphs with known ground truth (for the demo and consistency tests)."""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from .pose_graph import PoseGraph


def sample_pose_noise(rng: np.random.Generator, cov: np.ndarray) -> gtsam.Pose3:
    """``Expmap(xi)`` with ``xi ~ N(0, cov)`` in the tangent order [rotation, translation]."""
    xi = rng.multivariate_normal(np.zeros(6), cov)
    return gtsam.Pose3.Expmap(xi)


@dataclass(frozen=True)
class LoopGraph:
    """A noisy pose graph and the ground truth it was simulated from."""

    graph: PoseGraph
    truth: list[gtsam.Pose3]          # T_world_sensor per node id 0..N-1
    odometry_cov: np.ndarray          # the covariance the measurements were drawn with
    loop_cov: np.ndarray


def loop_ground_truth(n_poses: int = 24, radius: float = 5.0, height: float = 0.5,
                      ) -> list[gtsam.Pose3]:
    """Poses on a rising circle, x forward along the tangent, one full lap."""
    poses = []
    for k in range(n_poses):
        angle = 2 * np.pi * k / n_poses
        position = np.array([radius * np.cos(angle), radius * np.sin(angle),
                             height * np.sin(angle)])
        rotation = gtsam.Rot3.Ypr(angle + np.pi / 2, 0.0, 0.0)
        poses.append(gtsam.Pose3(rotation, position))
    return poses


def simulate_loop_graph(rng: np.random.Generator, n_poses: int = 24, *,
                        odometry_sigmas: tuple[float, float] = (0.01, 0.05),
                        loop_sigmas: tuple[float, float] = (0.005, 0.02),
                        model_scale: float = 1.0, prior_sigmas: tuple[float, float] = (1e-3, 1e-3),
                        ) -> LoopGraph:
    """Simulate odometry around a loop plus one loop closure, with known noise.

    Measurements are drawn with the given (rotation rad, translation m) sigmas; the
    factors' noise models use the same covariances times ``model_scale`` (1.0 = correctly
    tuned; use another value for a mis-tuned negative control). The initial estimate is
    dead reckoning from the noisy odometry.
    """
    truth = loop_ground_truth(n_poses)
    odo_cov = np.diag(np.repeat(np.square(odometry_sigmas), 3))
    loop_cov = np.diag(np.repeat(np.square(loop_sigmas), 3))
    prior_cov = np.diag(np.repeat(np.square(prior_sigmas), 3))
    graph = PoseGraph()
    # The prior is a measurement like any other: drawn around the truth with its covariance.
    first = truth[0].compose(sample_pose_noise(rng, prior_cov))
    graph.add_node(0, first, timestamp=0.0)
    graph.add_prior(0, first, prior_cov * model_scale)
    pose = first
    for k in range(1, n_poses):
        measured = truth[k - 1].between(truth[k]).compose(sample_pose_noise(rng, odo_cov))
        pose = pose.compose(measured)
        graph.add_node(k, pose, timestamp=float(k))
        graph.add_between(k - 1, k, measured, odo_cov * model_scale, kind="odometry")
    closure = truth[-1].between(truth[0]).compose(sample_pose_noise(rng, loop_cov))
    graph.add_between(n_poses - 1, 0, closure, loop_cov * model_scale, kind="loop")
    return LoopGraph(graph, truth, odo_cov, loop_cov)


def pose_errors(graph: PoseGraph, truth: list[gtsam.Pose3]) -> np.ndarray:
    """(N, 6) errors ``localCoordinates``: the tangent at the estimate pointing to the truth.

    Order [rotation, translation], matching :meth:`PoseGraph.marginal_covariance`.
    """
    return np.array([graph.nodes[i].pose.localCoordinates(truth[i]) for i in graph.sorted_ids()])


@dataclass(frozen=True)
class LoopGraphNees:
    """NEES of one optimised simulated loop: per node (6 dof each) and joint (6 x N dof)."""

    per_node: np.ndarray              # (N,) with each node's marginal covariance
    joint: float                      # with GTSAM's joint marginal of all nodes


def loop_graph_nees(seed: int, n_poses: int = 10, model_scale: float = 1.0) -> LoopGraphNees:
    """Per-node and joint NEES of one simulated loop after Levenberg-Marquardt.

    Errors are ``localCoordinates`` (tangent [rotation, translation] at the estimate); the joint
    value uses GTSAM's joint marginal of all nodes, so correlations along the loop count.
    """
    from .covariance import nees
    from .pose_graph import node_key

    sim = simulate_loop_graph(np.random.default_rng(seed), n_poses=n_poses,
                              model_scale=model_scale)
    sim.graph.optimize("lm")
    errors = pose_errors(sim.graph, sim.truth)
    ids = sim.graph.sorted_ids()
    keys = gtsam.KeyVector()
    for node_id in ids:
        keys.append(node_key(node_id))
    marginals = gtsam.Marginals(sim.graph.graph(), sim.graph.values())
    joint = marginals.jointMarginalCovariance(keys).fullMatrix()
    per_node = nees(errors, np.array([marginals.marginalCovariance(node_key(i)) for i in ids]))
    flat = errors.reshape(-1)
    return LoopGraphNees(np.asarray(per_node, dtype=float),
                         float(flat @ np.linalg.solve(joint, flat)))


def loop_graph_joint_nees(seed: int, n_poses: int = 10, model_scale: float = 1.0) -> float:
    """Joint NEES (dof 6 x n_poses) of one simulated loop: :func:`loop_graph_nees`'s ``joint``."""
    return loop_graph_nees(seed, n_poses, model_scale).joint
