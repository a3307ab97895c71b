"""perception.rgbd: camera file, TUM reader and association, back-projection, voxel filter."""
from __future__ import annotations

import itertools

import cv2
import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import FormatError
from perception.errors import ImageError, PerceptionError
from perception.rgbd import (
    CameraIntrinsics,
    TumRgbdSequence,
    associate,
    backproject,
    read_camera_file,
    voxel_filter,
    write_camera_file,
)

SMALL = CameraIntrinsics(40.0, 42.0, 15.5, 11.5, 32, 24, 5000.0)


# ---------------------------------------------------------------- camera file
@settings(max_examples=25, deadline=None)
@given(fx=st.floats(1, 2000), fy=st.floats(1, 2000), cx=st.floats(-100, 2000),
       cy=st.floats(-100, 2000), width=st.integers(1, 4096), height=st.integers(1, 4096),
       scale=st.floats(1e-3, 1e5))
def test_camera_file_round_trip(tmp_path_factory, fx, fy, cx, cy, width, height, scale):
    path = tmp_path_factory.mktemp("cam") / "camera.txt"
    intr = CameraIntrinsics(fx, fy, cx, cy, width, height, scale)
    write_camera_file(path, intr)
    assert read_camera_file(path) == intr


@pytest.mark.parametrize("text, message", [
    ("525 525 319.5 239.5 640 480\n", "expected 7 numbers"),
    ("525 525 319.5 239.5 640 480 5000\n1 2 3 4 5 6 7\n", "one data line"),
    ("525 525 319.5 239.5 640.5 480 5000\n", "integers"),
    ("525 -1 319.5 239.5 640 480 5000\n", "positive"),
    ("525 a 319.5 239.5 640 480 5000\n", "numbers"),
])
def test_camera_file_errors_name_the_file(tmp_path, text, message):
    path = tmp_path / "camera.txt"
    path.write_text("# comment\n" + text)
    with pytest.raises(FormatError, match=message) as info:
        read_camera_file(path)
    assert str(path) in str(info.value)


def test_K_matrix():
    np.testing.assert_array_equal(SMALL.K, [[40, 0, 15.5], [0, 42, 11.5], [0, 0, 1]])


# ---------------------------------------------------------------- TUM sequence
def _write_sequence(root, rng, rgb_stamps, depth_stamps, gt_rows=None, intr=SMALL):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    images = {}
    for kind, stamps in (("rgb", rgb_stamps), ("depth", depth_stamps)):
        lines = ["# timestamp filename"]
        for stamp in stamps:
            name = f"{kind}/{stamp:.6f}.png"
            if kind == "rgb":
                image = rng.integers(0, 256, (intr.height, intr.width, 3), dtype=np.uint8)
                cv2.imwrite(str(root / name), image[..., ::-1])
            else:
                image = rng.integers(0, 40000, (intr.height, intr.width), dtype=np.uint16)
                cv2.imwrite(str(root / name), image)
            images[(kind, round(stamp, 6))] = image
            lines.append(f"{stamp:.6f} {name}")
        (root / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    if gt_rows is not None:
        (root / "groundtruth.txt").write_text(
            "# t tx ty tz qx qy qz qw\n" + "\n".join(" ".join(f"{v:.9f}" for v in row)
                                                    for row in gt_rows) + "\n")
    write_camera_file(root / "camera.txt", intr)
    return images


def test_tum_round_trip_association_and_groundtruth(tmp_path, rng):
    rgb_stamps = [1.00, 1.10, 1.20, 1.50]
    depth_stamps = [1.005, 1.093, 1.212, 1.30]   # 1.50 has no partner within 0.02 s
    q = gtsam.Rot3.Ypr(0.4, 0.0, 0.0).toQuaternion()
    gt_rows = [[0.9, 0, 0, 0, 0, 0, 0, 1], [1.3, 4, 0, 0, q.x(), q.y(), q.z(), q.w()]]
    images = _write_sequence(tmp_path, rng, rgb_stamps, depth_stamps, gt_rows)
    sequence = TumRgbdSequence(tmp_path, gt_max_gap=0.5)
    assert sequence.intrinsics == SMALL
    assert len(sequence) == 3
    frames = list(sequence)
    for frame, (t_rgb, t_depth) in zip(frames, [(1.0, 1.005), (1.1, 1.093), (1.2, 1.212)]):
        assert frame.timestamp == pytest.approx(t_rgb)
        np.testing.assert_array_equal(frame.rgb, images[("rgb", t_rgb)])
        expected = images[("depth", t_depth)].astype(np.float32) / np.float32(5000.0)
        np.testing.assert_array_equal(frame.depth_m, expected)
        assert frame.depth_m.dtype == np.float32
        # ground truth interpolated at the colour timestamp: x linear, yaw slerped
        alpha = (t_rgb - 0.9) / 0.4
        pose = frame.T_world_camera_gt
        assert pose.x() == pytest.approx(4 * alpha)
        assert pose.rotation().yaw() == pytest.approx(0.4 * alpha)


def test_groundtruth_missing_or_far_gives_none(tmp_path, rng):
    _write_sequence(tmp_path, rng, [1.0, 2.0], [1.0, 2.0], [[2.05, 1, 2, 3, 0, 0, 0, 1]])
    frames = list(TumRgbdSequence(tmp_path))
    assert frames[0].T_world_camera_gt is None              # 1.05 s from the only sample
    np.testing.assert_allclose(frames[1].T_world_camera_gt.translation(), [1, 2, 3])
    (tmp_path / "groundtruth.txt").unlink()
    assert TumRgbdSequence(tmp_path)[0].T_world_camera_gt is None


def _brute_force_associate(a, b, max_dt):
    candidates = []
    for i, t in enumerate(a):
        j = int(np.argmin(np.abs(b - t)))
        if abs(b[j] - t) <= max_dt:
            candidates.append((i, j, abs(b[j] - t)))
    pairs = []
    for j in {c[1] for c in candidates}:
        best = min((c for c in candidates if c[1] == j), key=lambda c: (c[2], c[0]))
        pairs.append((best[0], best[1]))
    return sorted(pairs)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 400), min_size=0, max_size=30),
       st.lists(st.integers(0, 400), min_size=0, max_size=30, unique=True))
def test_associate_matches_brute_force(a_ms, b_ms):
    # integer milliseconds avoid ties decided by float rounding
    a = np.array(sorted(set(a_ms)), dtype=float) / 1000 + 0.0001
    b = np.array(b_ms, dtype=float) / 1000
    pairs = associate(a, b, 0.02)
    reference = _brute_force_associate(a, b, 0.02) if len(b) else []
    assert [tuple(p) for p in pairs.tolist()] == reference


def test_missing_association_file_is_named(tmp_path, rng):
    _write_sequence(tmp_path, rng, [1.0], [1.0])
    (tmp_path / "depth.txt").unlink()
    with pytest.raises(FormatError, match="depth.txt.*not found"):
        TumRgbdSequence(tmp_path)


def test_missing_camera_file_is_named(tmp_path, rng):
    _write_sequence(tmp_path, rng, [1.0], [1.0])
    (tmp_path / "camera.txt").unlink()
    with pytest.raises(FormatError, match="camera.txt"):
        TumRgbdSequence(tmp_path)
    assert len(TumRgbdSequence(tmp_path, intrinsics=SMALL)) == 1


def test_bad_association_line(tmp_path, rng):
    _write_sequence(tmp_path, rng, [1.0], [1.0])
    (tmp_path / "rgb.txt").write_text("1.0 rgb/a.png extra\n")
    with pytest.raises(FormatError, match=r"rgb.txt:1"):
        TumRgbdSequence(tmp_path)


@pytest.mark.parametrize("bad", ["uint8", "rgb16", "size", "corrupt", "missing"])
def test_bad_depth_image_is_named(tmp_path, rng, bad):
    _write_sequence(tmp_path, rng, [1.0], [1.0])
    path = tmp_path / "depth" / "1.000000.png"
    if bad == "uint8":
        cv2.imwrite(str(path), np.zeros((SMALL.height, SMALL.width), np.uint8))
        message = "uint16"
    elif bad == "rgb16":
        cv2.imwrite(str(path), np.zeros((SMALL.height, SMALL.width, 3), np.uint16))
        message = "single-channel"
    elif bad == "size":
        cv2.imwrite(str(path), np.zeros((SMALL.height + 1, SMALL.width), np.uint16))
        message = "32x24"
    elif bad == "corrupt":
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
        message = "cannot decode"
    else:
        path.unlink()
        message = "not found"
    sequence = TumRgbdSequence(tmp_path)
    with pytest.raises(ImageError, match=message) as info:
        sequence[0]
    assert str(path) in str(info.value)


def test_bad_rgb_image_is_named(tmp_path, rng):
    _write_sequence(tmp_path, rng, [1.0], [1.0])
    path = tmp_path / "rgb" / "1.000000.png"
    cv2.imwrite(str(path), np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(ImageError, match="5x5") as info:
        TumRgbdSequence(tmp_path)[0]
    assert str(path) in str(info.value)


# ---------------------------------------------------------------- back-projection
def test_backproject_matches_the_pinhole_model(rng):
    depth = rng.uniform(0.5, 5.0, (SMALL.height, SMALL.width)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[0, 0] = np.nan
    for stride in (1, 3):
        points = backproject(depth, SMALL, stride=stride)
        rows, cols = np.nonzero(np.isfinite(depth[::stride, ::stride])
                                & (depth[::stride, ::stride] > 0))
        assert points.dtype == np.float32 and points.shape == (rows.size, 3)
        z = depth[rows * stride, cols * stride]
        np.testing.assert_allclose(points[:, 2], z)
        # reprojection gives back the pixel: K p / z = (u, v, 1)
        projected = (SMALL.K @ points.T.astype(np.float64)).T
        np.testing.assert_allclose(projected[:, 0] / projected[:, 2], cols * stride, atol=1e-4)
        np.testing.assert_allclose(projected[:, 1] / projected[:, 2], rows * stride, atol=1e-4)


def test_backproject_plane_is_planar():
    # a fronto-parallel wall at 2 m: every point has z = 2 and x spans (u - cx) * 2 / fx
    depth = np.full((SMALL.height, SMALL.width), 2.0, np.float32)
    points = backproject(depth, SMALL)
    np.testing.assert_allclose(points[:, 2], 2.0)
    assert points[:, 0].min() == pytest.approx(-15.5 * 2 / 40)
    assert points[:, 1].max() == pytest.approx(11.5 * 2 / 42)


# ---------------------------------------------------------------- voxel filter
def _brute_force_voxel_filter(points, size):
    best = {}
    for index, p in enumerate(points.astype(np.float64)):
        key = tuple(np.floor(p / size).astype(int))
        dist = np.sum((p / size - np.array(key) - 0.5) ** 2)
        if key not in best or dist < best[key][0]:
            best[key] = (dist, index)
    return {key: points[index] for key, (_, index) in best.items()}


@pytest.mark.parametrize("size", [0.05, 0.3])
def test_voxel_filter_keeps_the_point_nearest_each_centre(rng, size):
    points = rng.uniform(-0.4, 0.6, (600, 3)).astype(np.float32)
    points[:50] = np.round(points[:50] / size) * size   # points exactly on voxel faces
    filtered = voxel_filter(points, size)
    reference = _brute_force_voxel_filter(points, size)
    assert filtered.shape == (len(reference), 3) and filtered.dtype == np.float32
    keys = [tuple(np.floor(p.astype(np.float64) / size).astype(int)) for p in filtered]
    assert len(set(keys)) == len(keys)                          # one point per voxel
    for key, point in zip(keys, filtered):
        np.testing.assert_array_equal(point, reference[key])    # the nearest to the centre


def test_voxel_filter_differs_from_open3d_centroids(rng):
    import open3d as o3d

    points = np.array([[0.001, 0.001, 0.001], [0.021, 0.021, 0.021], [0.01, 0.01, 0.01]])
    np.testing.assert_allclose(voxel_filter(points, 0.05), [[0.021] * 3], rtol=1e-6)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    centroids = np.asarray(cloud.voxel_down_sample(0.05).points)
    # Open3D returns centroids (not input points), hence perception.rgbd.voxel_filter
    assert not any(np.allclose(c, p) for c in centroids for p in points)


def test_voxel_filter_input_checks():
    assert voxel_filter(np.zeros((0, 3)), 0.05).shape == (0, 3)
    assert voxel_filter(np.array([[np.nan, 0, 0], [0.01, 0.01, 0.01]]), 0.05).shape == (1, 3)
    with pytest.raises(PerceptionError):
        voxel_filter(np.zeros((4, 2)))
    with pytest.raises(PerceptionError):
        voxel_filter(np.zeros((4, 3)), 0.0)


def test_voxel_filter_property_against_itertools_reference():
    # every point of a small lattice at voxel centres +- offsets: the centre itself wins
    size = 0.1
    centres = np.array(list(itertools.product([0.05, 0.15], repeat=3)))
    jitter = np.array([[0.03, 0, 0], [0, -0.02, 0.01], [0, 0, 0]])
    points = (centres[:, None, :] + jitter[None]).reshape(-1, 3)
    filtered = voxel_filter(points, size)
    np.testing.assert_allclose(np.sort(filtered, axis=0), np.sort(centres, axis=0), atol=1e-7)


def test_resized_intrinsics_keep_pixel_centres_and_project_alike():
    from perception.rgbd import CameraIntrinsics

    intr = CameraIntrinsics(525.0, 520.0, 319.5, 239.5, 640, 480)
    half = intr.resized(320, 240)
    # a pixel's centre (u, v) at full size lies at ((u + 0.5) / 2 - 0.5, ...) at half size
    point = np.array([0.3, -0.2, 2.0])
    uv_full = (intr.K @ point)[:2] / point[2]
    uv_half = (half.K @ point)[:2] / point[2]
    np.testing.assert_allclose(uv_half, (uv_full + 0.5) / 2 - 0.5)
    assert (half.width, half.height, half.depth_scale) == (320, 240, intr.depth_scale)
    assert half.resized(640, 480) == intr


def test_undistorter_puts_a_point_where_the_pinhole_camera_sees_it():
    """A dot drawn where the distorted camera images a 3-D point lands, after undistortion,
    on the pinhole projection of that point; depth is resampled without new values."""
    from perception.rgbd import CameraIntrinsics, RgbdFrame, Undistorter

    intr = CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
    D = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])  # TUM fr1
    P = np.array([[0.45, -0.3, 1.2]])
    uv_pinhole = (intr.K @ (P[0] / P[0, 2]))[:2]
    uv_distorted = cv2.projectPoints(P, np.zeros(3), np.zeros(3), intr.K, D)[0].reshape(2)
    assert np.linalg.norm(uv_distorted - uv_pinhole) > 5  # the lens matters here
    rgb = np.zeros((480, 640, 3), np.uint8)
    cv2.circle(rgb, tuple(int(round(v)) for v in uv_distorted), 3, (255, 255, 255), -1)
    depth = np.where(rgb[..., 0] > 0, 2.0, 0.0).astype(np.float32)
    frame = RgbdFrame(0, 0.0, rgb, depth)
    out = Undistorter(intr, D)(frame)
    rows, cols = np.nonzero(out.rgb[..., 0] > 128)
    np.testing.assert_allclose([cols.mean(), rows.mean()], uv_pinhole, atol=1.0)
    assert set(np.unique(out.depth_m)) <= {0.0, 2.0}
    assert Undistorter(intr, (0, 0, 0, 0))(frame) is frame  # no distortion: no copy


@pytest.mark.parametrize("bad", [(0.1, 0.2), (0.1, 0.2, 0.0, 0.0, float("nan")), (1e9, 0, 0, 0)])
def test_bad_distortion_is_refused(bad):
    from perception.rgbd import check_distortion

    with pytest.raises(PerceptionError, match="distortion"):
        check_distortion(bad)


def test_a_sequence_with_distortion_reads_undistorted_frames(shared_data):
    """TumRgbdSequence(distortion=...) hands out the undistorted frames (the wiring of
    vpslam --distortion), and without it the raw ones."""
    from perception.rgbd import CameraIntrinsics, TumRgbdSequence, Undistorter

    seq_dir = shared_data / "rgbd" / "tum_fr1_rpy"
    if not seq_dir.is_dir():
        pytest.skip("../shared/data/rgbd is missing")
    intr = CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, 5000.0)
    D = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    raw = TumRgbdSequence(seq_dir, intrinsics=intr)[3]
    undistorted = TumRgbdSequence(seq_dir, intrinsics=intr, distortion=D)[3]
    expected = Undistorter(intr, D)(raw)
    np.testing.assert_array_equal(undistorted.rgb, expected.rgb)
    np.testing.assert_array_equal(undistorted.depth_m, expected.depth_m)
    assert not np.array_equal(undistorted.rgb, raw.rgb)
