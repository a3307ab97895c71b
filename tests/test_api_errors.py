"""A newcomer's API calls (issue 15): 4x4 arrays wherever a Pose3 is taken, and one-line
errors that name the argument or the node."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation import PoseGraph
from estimation.errors import OctofactorError
from mapping import OcTree


def test_pose_graph_takes_4x4_arrays_everywhere():
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]
    pg = PoseGraph()
    pg.add_node(0, np.eye(4))
    pg.add_node(1, T)
    pg.add_prior(0, np.eye(4), np.eye(6) * 1e-6)
    pg.add_between(0, 1, T, np.eye(6) * 1e-2)
    pg.optimize("lm")
    assert np.allclose(pg.nodes[1].pose.matrix(), T)
    assert pg.marginal_covariance(1).shape == (6, 6)
    with pytest.raises(OctofactorError, match="T_i_j .*0->1.*shape \\(3, 3\\)"):
        pg.add_between(0, 1, np.eye(3), np.eye(6))
    with pytest.raises(OctofactorError, match="node 7"):
        pg.marginal_covariance(7)


def test_registration_initial_guess_takes_pose3_or_4x4():
    from estimation.registration import Registration, RegistrationConfig

    rng = np.random.default_rng(0)
    cloud = rng.uniform(-1, 1, (400, 3))
    reg = Registration(cloud, cloud, RegistrationConfig())
    assert reg.run(np.eye(4)).converged and reg.run(gtsam.Pose3()).converged
    with pytest.raises(OctofactorError, match="initial T.*shape \\(3, 3\\)"):
        reg.run(np.eye(3))


@pytest.mark.parametrize("points, origin, message", [
    (np.zeros((5, 2)), np.zeros(3), r"points must be an \(N, 3\) array, got shape \(5, 2\)"),
    (np.zeros(6), np.zeros(3), r"points must be an \(N, 3\) array, got shape \(6,\)"),
    (np.zeros((5, 3)), np.zeros(2), r"origin must be 3 numbers"),
])
def test_insert_point_cloud_names_the_bad_argument(points, origin, message):
    with pytest.raises(OctofactorError, match=message):
        OcTree(0.1).insert_point_cloud(points, origin)


def test_octree_queries_name_the_bad_argument():
    tree = OcTree(0.1)
    tree.insert_point_cloud(np.array([[1.0, 0.0, 0.0]]), np.zeros(3))
    assert tree.search([1.0, 0.0, 0.0]).known.tolist() == [True]  # one point is fine
    with pytest.raises(OctofactorError, match="directions"):
        tree.cast_ray(np.zeros((2, 3)), np.ones((2, 2)))
    with pytest.raises(OctofactorError, match="points"):
        tree.search(np.ones((4, 2)))
