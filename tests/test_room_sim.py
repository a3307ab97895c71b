"""The household-room simulator: labels, ground truth, files, the CLI round trip."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from estimation.registration import read_transform, transform_points
from perception.semantic_cloud import SemanticCloud
from perception.simulation.room import (
    CLASS,
    CLASS_NAMES,
    LEFT_HANDED_FLIP,
    RoomConfig,
    build_room,
    headset_cloud,
    look_at,
    noisy_labels,
    render_view,
)

SMALL = dict(image_width=96, image_height=72, focal=70.0)


@pytest.fixture(scope="module")
def room():
    return build_room(RoomConfig(**SMALL))


def test_look_at_is_a_camera_pose():
    T = look_at((1, 2, 1.5), (3, 2, 1.5))
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [1, 0, 0])   # camera z forward
    np.testing.assert_allclose(R[:, 1], [0, 0, -1])  # camera y down


def test_noisy_labels_flip_at_the_requested_rate(rng):
    labels = rng.integers(0, 11, 20000)
    noisy = noisy_labels(labels, 0.7, 11, rng)
    assert np.mean(noisy == labels) == pytest.approx(0.7, abs=0.015)
    assert np.all((noisy >= 0) & (noisy < 11))
    np.testing.assert_array_equal(noisy_labels(labels, 1.0, 11, rng), labels)


def test_rendered_labels_match_the_surfaces(room, rng):
    # the floor seen from above: every point near z = 0 is floor with perfect labels
    T = look_at((3.0, 2.5, 2.0), (3.0, 2.6, 0.0))
    cloud = render_view(room, T, rng, 1.0)
    assert len(cloud) > 1000
    on_floor = np.abs(cloud.points[:, 2]) < 0.02
    assert on_floor.mean() > 0.3
    # (table and chair legs also touch the floor)
    assert np.mean(cloud.labels[on_floor] == CLASS["floor"]) > 0.97
    assert np.all(cloud.points[:, 2] > -0.05)  # nothing below the floor


def test_headset_cloud_matches_the_map_at_ground_truth(room):
    cfg = RoomConfig(**SMALL, label_accuracy=1.0)
    cloud, T_map_headset = headset_cloud(room, "shelf", cfg)
    near = headset_cloud(room, "shelf", RoomConfig(**SMALL, seed=0, label_accuracy=1.0))[0]
    np.testing.assert_allclose(cloud.points, near.points)  # deterministic for a seed
    in_map = transform_points(T_map_headset, cloud.points)
    # the room box [0, 6] x [0, 5] x [0, 2.6] holds the cloud only at the true transform
    assert np.all(in_map > -0.1) and np.all(in_map < [6.1, 5.1, 2.7])
    assert {CLASS["shelf"], CLASS["books"]} <= set(np.unique(cloud.labels))
    left, _ = headset_cloud(room, "shelf", RoomConfig(**SMALL, left_handed=True))
    np.testing.assert_allclose(transform_points(LEFT_HANDED_FLIP, left.points), cloud.points,
                               atol=1e-9)


def test_robot_map_covers_every_headset_view(room):
    from perception.simulation.room import robot_semantic_map

    cfg = RoomConfig(**SMALL, robot_label_accuracy=1.0)
    robot_map = robot_semantic_map(room, cfg)
    assert set(np.unique(robot_map.labels)) >= {CLASS[n] for n in ("floor", "wall", "tv", "desk",
                                                                    "shelf", "table")}
    tree = cKDTree(robot_map.points)
    for view in ("tv", "desk", "shelf", "dining"):
        cloud, T = headset_cloud(room, view, cfg)
        dist, _ = tree.query(transform_points(T, cloud.points))
        assert np.median(dist) < 0.05, view



def test_label_accuracy_changes_only_the_labels(room):
    # depth noise and label noise have separate random streams: the same points for every
    # label accuracy (headset views and the robot's map), different labels
    from perception.simulation.room import robot_semantic_map

    clean = RoomConfig(**SMALL, label_accuracy=1.0, robot_label_accuracy=1.0)
    noisy = RoomConfig(**SMALL, label_accuracy=0.5, robot_label_accuracy=0.5)
    for view in ("desk", "dining"):
        a, T_a = headset_cloud(room, view, clean)
        b, T_b = headset_cloud(room, view, noisy)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(T_a, T_b)
        agree = np.mean(a.labels == b.labels)
        assert 0.3 < agree < 0.8, (view, agree)  # about half the labels flipped
    map_a = robot_semantic_map(room, clean)
    map_b = robot_semantic_map(room, noisy)
    np.testing.assert_array_equal(map_a.points, map_b.points)
    assert np.mean(map_a.labels == map_b.labels) < 0.99
    # a different seed still gives different depth noise (compared in the map frame)
    other, T_other = headset_cloud(room, "dining", RoomConfig(**SMALL, seed=1,
                                                               label_accuracy=1.0))
    in_map = transform_points(T_a, a.points)
    assert len(other) != len(a) or not np.allclose(transform_points(T_other, other.points),
                                                   in_map, atol=1e-6)

@pytest.mark.slow
def test_cli_simulate_then_register(tmp_path):
    from pipelines.cli import main

    out = tmp_path / "room"
    assert main(["simulate", "room", "-o", str(out), "--views", "dining", "--image-size",
                 "160x120"]) == 0
    names = (out / "classes.txt").read_text().split()
    assert tuple(names) == CLASS_NAMES
    robot_map = SemanticCloud.read_ply(out / "robot_map.ply")
    headset = SemanticCloud.read_ply(out / "headset_dining.ply")
    assert robot_map.n_classes == headset.n_classes == len(CLASS_NAMES)
    T_gt = read_transform(out / "T_map_headset_dining.txt")
    # start 10 cm / ~3 deg off the truth
    import gtsam

    init = T_gt @ gtsam.Pose3(gtsam.Rot3.Yaw(0.05), np.array([0.1, 0.0, 0.0])).matrix()
    np.savetxt(tmp_path / "init.txt", init)
    result = tmp_path / "result.json"
    code = main(["calibrate", str(out / "headset_dining.ply"), str(out / "robot_map.ply"),
                 "--init", str(tmp_path / "init.txt"), "--gt",
                 str(out / "T_map_headset_dining.txt"), "-o", str(result)])
    data = json.loads(result.read_text())
    assert code == (0 if data["converged"] else 1)
    for key in ("T", "covariance", "converged", "iterations", "time_s", "d_se3", "t_err_m",
                "r_err_rad"):
        assert key in data
    assert np.array(data["covariance"]).shape == (6, 6)
    assert data["t_err_m"] < 0.1 and data["r_err_rad"] < np.deg2rad(3)
