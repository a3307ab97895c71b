"""perception.simulation.corridor: determinism, geometry, noise model, files and CLI."""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from perception.errors import PerceptionError
from perception.rgbd import TumRgbdSequence, read_camera_file
from perception.simulation.corridor import (
    CorridorConfig,
    build_corridor_scene,
    corridor_trajectory,
    forward_vanishing_point,
    read_vps_file,
    render_frame,
    simulate_corridor,
)

# 1 m of walk: 5 frames; short enough that the end wall is within the 3.5 m depth range
SHORT = CorridorConfig(seed=3, length=3.5, clutter=1)


@pytest.fixture(scope="module")
def short_scene():
    return build_corridor_scene(SHORT)


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_files_and_other_seed_differs(tmp_path):
    assert simulate_corridor(tmp_path / "a", SHORT) == 5
    simulate_corridor(tmp_path / "b", SHORT)
    first, second = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert first.keys() == second.keys() and len(first) == 2 * 5 + 5
    assert first == second
    simulate_corridor(tmp_path / "c", CorridorConfig(seed=4, length=3.5, clutter=1))
    other = _files(tmp_path / "c")
    assert other.keys() == first.keys()
    assert other[next(k for k in first if k.parts[0] == "rgb")] != \
        first[next(k for k in first if k.parts[0] == "rgb")]


def test_written_sequence_reads_back(tmp_path):
    simulate_corridor(tmp_path, SHORT)
    sequence = TumRgbdSequence(tmp_path)
    assert sequence.intrinsics == SHORT.intrinsics == read_camera_file(tmp_path / "camera.txt")
    stamps, poses = corridor_trajectory(SHORT)
    np.testing.assert_allclose(sequence.timestamps, stamps)
    scene = build_corridor_scene(SHORT)
    rng = np.random.default_rng([SHORT.seed, 2])   # the writer's generator
    _, open_poses = corridor_trajectory(SHORT, -SHORT.exposure_time)   # motion blur
    for frame, pose, open_pose in zip(sequence, poses, open_poses):
        assert frame.T_world_camera_gt.equals(pose, 1e-8)
        rgb, depth = render_frame(scene, pose, SHORT.intrinsics, rng, open_pose)
        np.testing.assert_array_equal(frame.rgb, rgb)
        np.testing.assert_array_equal(frame.depth_m, depth)   # PNG step = render quantisation
    vp_stamps, uv, directions = read_vps_file(tmp_path / "vps.txt")
    np.testing.assert_allclose(vp_stamps, stamps)
    for k, pose in enumerate(poses):
        world_x = pose.rotation().rotate(directions[k])
        np.testing.assert_allclose(world_x, [1, 0, 0], atol=1e-9)
        projected = SHORT.intrinsics.K @ directions[k]
        np.testing.assert_allclose(uv[k], projected[:2] / projected[2], atol=1e-5)


def test_trajectory_walks_along_x_looking_forward():
    config = CorridorConfig()
    stamps, poses = corridor_trajectory(config)
    np.testing.assert_allclose(np.diff(stamps), 0.3)
    xs = np.array([p.x() for p in poses])
    np.testing.assert_allclose(np.diff(xs), 0.8 * 0.3)
    ys = np.array([p.y() for p in poses])
    assert 0 < np.abs(ys).max() <= config.zigzag_amplitude + 1e-12
    for pose in poses:
        R = pose.rotation().matrix()
        # camera z roughly world +x, camera x roughly world -y, camera y roughly world -z
        assert R[:, 2] @ [1, 0, 0] > np.cos(np.deg2rad(5))
        assert R[:, 0] @ [0, -1, 0] > np.cos(np.deg2rad(5))
        assert R[:, 1] @ [0, 0, -1] > np.cos(np.deg2rad(5))
    direction, uv = forward_vanishing_point(gtsam.Pose3(gtsam.Rot3(
        np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])), np.zeros(3)), config.intrinsics)
    np.testing.assert_allclose(direction, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(uv, [319.5, 239.5])


def _analytic_box_depth(pose, u, v, intr, config):
    """z-depth of pixel (u, v) in the empty corridor box: the nearest of its six planes."""
    ray_camera = np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
    ray_world = pose.rotation().matrix() @ ray_camera
    origin = np.asarray(pose.translation())
    planes = [(0, 0.0), (0, config.length), (1, -config.width / 2), (1, config.width / 2),
              (2, 0.0), (2, config.height)]
    ts = [(value - origin[axis]) / ray_world[axis] for axis, value in planes
          if abs(ray_world[axis]) > 1e-12]
    return min(t for t in ts if t > 0)  # the camera ray has unit z: t is the z-depth


def test_noise_free_depth_matches_analytic_geometry():
    config = CorridorConfig(seed=3, length=3.5)   # no clutter; doors stay on the walls
    scene = build_corridor_scene(config)
    intr = config.intrinsics
    stamps, poses = corridor_trajectory(config)
    for pose in (poses[0], poses[-1]):
        rgb, depth = render_frame(scene, pose, intr, rng=None)
        # the end wall (centre), the floor or the end wall (bottom centre rows)
        for u, v in [(319, 239), (320, 479), (320, 400), (300, 300)]:
            expected = _analytic_box_depth(pose, u, v, intr, config)
            assert depth[v, u] == pytest.approx(expected, abs=1e-4)
        assert rgb[239, 319].max() > 0
    assert depth.dtype == np.float32 and rgb.dtype == np.uint8
    assert depth.shape == (480, 640) and rgb.shape == (480, 640, 3)


def test_depth_range_limits():
    config = CorridorConfig(seed=1, length=20.0)
    assert (config.min_depth, config.max_depth) == (0.8, 3.5)   # the paper's Xtion (Table 1)
    scene = build_corridor_scene(config)
    _, poses = corridor_trajectory(config)
    for rng in (None, np.random.default_rng(3)):
        _, depth = render_frame(scene, poses[0], config.intrinsics, rng=rng)
        assert depth[239, 319] == 0.0         # end wall 19.5 m away: beyond 3.5 m
        assert depth.max() <= config.max_depth
        assert depth[depth > 0].min() >= config.min_depth
        # the walls within 3.5 m are measured: the image's side columns
        assert np.mean(depth[:, :100] > 0) > 0.5


def test_depth_noise_follows_the_xtion_model():
    config = CorridorConfig(seed=3, length=3.5, clutter=1, disparity_step=0.0)
    scene = build_corridor_scene(config)
    intr = config.intrinsics
    _, poses = corridor_trajectory(config)
    _, exact = render_frame(scene, poses[0], intr, rng=None)
    _, noisy = render_frame(scene, poses[0], intr, rng=np.random.default_rng(7))
    both = (exact > 0) & (noisy > 0)
    normalised = (noisy[both] - exact[both]) / exact[both] ** 2
    # sigma = 1.425e-3 z^2 (Khoshelham & Elberink); the 0.2 mm PNG step adds little
    assert np.std(normalised) == pytest.approx(SHORT.depth_noise, rel=0.1)
    assert abs(np.mean(normalised)) < 1e-4
    dropped = np.mean((exact > 0) & (noisy == 0))
    assert 0.5 * SHORT.dropout < dropped < 0.1    # random dropouts + grazing angles
    np.testing.assert_allclose(np.rint(noisy * 5000.0), noisy * 5000.0, atol=1e-3)  # 0.2 mm


def test_depth_lies_on_the_disparity_lattice(short_scene):
    intr = SHORT.intrinsics
    _, poses = corridor_trajectory(SHORT)
    _, depth = render_frame(short_scene, poses[1], intr, rng=np.random.default_rng(8))
    z = depth[depth > 0].astype(np.float64)
    steps = intr.fx * SHORT.baseline / z / SHORT.disparity_step
    # only the 0.2 mm PNG rounding moves depth off the lattice (< 0.05 step up to 3.5 m)
    assert np.max(np.abs(steps - np.rint(steps))) < 0.05
    # and the lattice is coarse: between 2.3 and 2.5 m (levels ~1.7 cm apart) only ~11 depth
    # values occur, where the 0.2 mm PNG step alone would allow 1000
    band = (z > 2.3) & (z < 2.5)
    assert band.sum() > 1000 and len(np.unique(z[band])) <= 14


def test_config_errors():
    with pytest.raises(PerceptionError, match="too short"):
        corridor_trajectory(CorridorConfig(length=2.0))
    with pytest.raises(PerceptionError, match="positive"):
        build_corridor_scene(CorridorConfig(width=0.0))
    with pytest.raises(PerceptionError, match="camera_height"):
        corridor_trajectory(CorridorConfig(camera_height=3.0))


def test_cli_writes_a_sequence(tmp_path, capsys):
    from pipelines.cli import main

    out = tmp_path / "seq"
    assert main(["simulate", "corridor", "-o", str(out), "--seed", "2", "--length", "3.5",
                 "--clutter", "2"]) == 0
    assert "5 frames" in capsys.readouterr().out
    assert len(TumRgbdSequence(out)) == 5
    assert main(["simulate", "corridor", "-o", str(out), "--width", "0", "--quiet"]) == 2
    assert "--width must be" in capsys.readouterr().err


def _noise_free(config, k=1, open_pose=False):
    scene = build_corridor_scene(config)
    _, poses = corridor_trajectory(config)
    opened = corridor_trajectory(config, -config.exposure_time)[1][k] if open_pose else None
    return render_frame(scene, poses[k], config.intrinsics, None, opened)


def test_vignetting_darkens_the_corners_by_the_configured_share():
    rgb0, _ = _noise_free(replace(SHORT, vignetting=0.0))
    rgb1, _ = _noise_free(replace(SHORT, vignetting=0.3))
    ratio = rgb1.astype(float).sum(axis=2) / np.maximum(rgb0.astype(float).sum(axis=2), 1)
    assert ratio[239, 319] == pytest.approx(1.0, abs=0.02)
    for v, u in [(0, 0), (0, 639), (479, 0), (479, 639)]:
        assert ratio[v, u] == pytest.approx(0.7, abs=0.03)
    assert ratio[239, 0] < ratio[239, 200] < ratio[239, 319] + 0.01   # smooth fall-off


def test_exposure_jitter_changes_the_brightness_per_frame():
    scene = build_corridor_scene(replace(SHORT, exposure_jitter=0.1, rgb_noise=0.0))
    steady = build_corridor_scene(replace(SHORT, exposure_jitter=0.0, rgb_noise=0.0))
    _, poses = corridor_trajectory(SHORT)
    rng = np.random.default_rng(4)
    gains = []
    for seed in range(6):
        a, _ = render_frame(scene, poses[0], SHORT.intrinsics, np.random.default_rng(seed))
        b, _ = render_frame(steady, poses[0], SHORT.intrinsics, np.random.default_rng(seed))
        gains.append(a.astype(float).mean() / b.astype(float).mean())
    assert np.std(np.log(gains)) == pytest.approx(0.1, rel=0.6)
    # without jitter and noise, two noisy renders have the same colours
    a, _ = render_frame(steady, poses[0], SHORT.intrinsics, rng)
    b, _ = render_frame(steady, poses[0], SHORT.intrinsics, rng)
    np.testing.assert_array_equal(a, b)


def test_motion_blur_smears_the_periphery_not_the_centre():
    config = replace(SHORT, exposure_time=0.05, blur_samples=5)
    sharp, depth_sharp = _noise_free(config)
    blurred, depth_blurred = _noise_free(config, open_pose=True)
    np.testing.assert_array_equal(depth_sharp, depth_blurred)      # depth is at t
    diff = np.abs(sharp.astype(float) - blurred.astype(float)).sum(axis=2)
    # forward motion: the image flow, hence the blur, grows away from the focus of expansion
    assert diff[200:280, 280:360].mean() < 0.5 * diff[:, :80].mean()
    assert diff.max() > 10
    # zero exposure time: no blur even with the shutter-open pose
    none, _ = _noise_free(replace(config, exposure_time=0.0), open_pose=True)
    np.testing.assert_array_equal(none, sharp)


def test_disparity_tilt_bends_depth_as_modelled():
    # noise, dropouts and quantisation off: only the systematic disparity offset remains
    config = replace(SHORT, depth_noise=0.0, dropout=0.0, disparity_step=0.0,
                     disparity_tilt=(0.0, 0.1))
    scene = build_corridor_scene(config)
    _, poses = corridor_trajectory(config)
    _, exact = render_frame(scene, poses[0], config.intrinsics, None)
    _, tilted = render_frame(scene, poses[0], config.intrinsics, np.random.default_rng(1))
    intr = config.intrinsics
    fb = intr.fx * config.baseline
    v = np.arange(intr.height, dtype=float)[:, None] * np.ones((1, intr.width))
    offset = 0.1 * (v - intr.cy) / (intr.height - 1 - intr.cy)
    expected = fb / (fb / exact.astype(float) + offset)
    both = (exact > 0) & (tilted > 0)
    np.testing.assert_allclose(tilted[both], expected[both], atol=1.5e-4)  # PNG step 0.2 mm
    # top rows nearer than the truth would be farther: the sign follows the offset
    assert np.mean(tilted[both & (v > 400)] - exact[both & (v > 400)]) < -1e-3
