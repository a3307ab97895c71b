"""SemanticCloud: PLY round trips through open3d.t, label-only files, RGB-D and map sources."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.errors import FormatError
from perception.errors import PerceptionError
from perception.semantic_cloud import SemanticCloud


def random_cloud(rng, n=50, c=4, colors=True, names=None) -> SemanticCloud:
    probs = rng.dirichlet(np.ones(c), size=n).astype(np.float32)
    return SemanticCloud(rng.normal(size=(n, 3)), probs,
                         rng.uniform(0, 1, (n, 3)) if colors else None, names)


@settings(max_examples=15, deadline=None)
@given(n=st.integers(1, 60), c=st.integers(1, 12), seed=st.integers(0, 2 ** 31),
       ascii=st.booleans(), colors=st.booleans())
def test_ply_round_trip(tmp_path_factory, n, c, seed, ascii, colors):
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng, n, c, colors)
    path = tmp_path_factory.mktemp("ply") / "cloud.ply"
    cloud.write_ply(path, ascii=ascii)
    back = SemanticCloud.read_ply(path)
    tol = 1e-5 if ascii else 0
    np.testing.assert_allclose(back.points, cloud.points.astype(np.float32), atol=tol + 1e-6)
    np.testing.assert_allclose(back.probs, cloud.probs, atol=tol + 1e-6)
    np.testing.assert_array_equal(back.labels, cloud.labels)
    assert back.n_classes == c
    assert (back.colors is None) == (not colors)


def test_ply_header_has_int32_label_and_float_probs(tmp_path, rng):
    path = tmp_path / "c.ply"
    random_cloud(rng, 5, 3, names=("floor", "wall", "tv")).write_ply(path)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "property int label" in header
    for c in range(3):
        assert f"property float prob_{c}" in header
    assert SemanticCloud.read_ply(path).class_names == ("floor", "wall", "tv")


def test_label_only_ply_loads_as_one_hot(tmp_path):
    path = tmp_path / "labels.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                    "property float y\nproperty float z\nproperty int label\nend_header\n"
                    "0 0 0 2\n1 0 0 0\n0 1 0 1\n")
    cloud = SemanticCloud.read_ply(path)
    np.testing.assert_array_equal(cloud.labels, [2, 0, 1])
    np.testing.assert_array_equal(cloud.probs, np.eye(3)[[2, 0, 1]])
    assert SemanticCloud.read_ply(path, n_classes=5).n_classes == 5
    with pytest.raises(FormatError, match="n_classes"):
        SemanticCloud.read_ply(path, n_classes=2)


def test_bad_files_raise_format_error(tmp_path):
    garbage = tmp_path / "g.ply"
    garbage.write_bytes(b"not a ply at all")
    with pytest.raises(FormatError, match="magic"):
        SemanticCloud.read_ply(garbage)
    plain = tmp_path / "p.ply"
    plain.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                     "property float y\nproperty float z\nend_header\n0 0 0\n")
    with pytest.raises(FormatError, match="label"):
        SemanticCloud.read_ply(plain)
    truncated = tmp_path / "t.ply"
    truncated.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n")
    with pytest.raises(FormatError):
        SemanticCloud.read_ply(truncated)
    with pytest.raises(FileNotFoundError):
        SemanticCloud.read_ply(tmp_path / "missing.ply")


def test_invalid_clouds_are_rejected():
    with pytest.raises(PerceptionError, match="probs"):
        SemanticCloud(np.zeros((3, 3)), np.ones((2, 2)))
    with pytest.raises(PerceptionError, match="all-zero"):
        SemanticCloud(np.zeros((1, 3)), np.zeros((1, 2)))
    with pytest.raises(PerceptionError, match="NaN"):
        SemanticCloud(np.full((1, 3), np.nan), np.ones((1, 2)))
    with pytest.raises(PerceptionError, match="names"):
        SemanticCloud(np.zeros((1, 3)), np.ones((1, 2)), class_names=("a",))


def test_from_rgbd_with_a_pluggable_segmenter():
    h, w, c = 6, 8, 3
    K = np.array([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]])
    depth = np.full((h, w), 2.0, dtype=np.float32)
    depth[0, 0] = 0.0  # invalid
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:, : w // 2] = 255

    def segmenter(image):  # bright pixels are class 1, the rest class 2
        probs = np.zeros(image.shape[:2] + (c,), np.float32)
        bright = image[..., 0] > 128
        probs[bright, 1] = 1.0
        probs[~bright, 2] = 1.0
        return probs

    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    cloud = SemanticCloud.from_rgbd(rgb, depth, K, segmenter=segmenter, T_world_camera=T)
    assert len(cloud) == h * w - 1
    np.testing.assert_allclose(cloud.points[:, 2], 5.0)
    left = cloud.points[:, 0] - 1.0 < 0
    assert np.all(cloud.labels[left] == 1) and np.all(cloud.labels[~left] == 2)
    with pytest.raises(PerceptionError, match="segmenter"):
        SemanticCloud.from_rgbd(rgb, depth, K)


def test_from_semantic_octree_and_voxel_fusion(rng):
    points = rng.uniform(0, 1, (500, 3))
    labels = (points[:, 0] > 0.5).astype(int)
    probs = np.eye(2)[labels]

    class FakeTree:  # the duck type of mapping.SemanticOcTree
        def occupied_voxels(self):
            return points[:10], probs[:10]

    cloud = SemanticCloud.from_semantic_octree(FakeTree(), ("a", "b"))
    assert len(cloud) == 10 and cloud.class_names == ("a", "b")
    fused = SemanticCloud.fuse_voxels(points, probs, 0.25)
    assert len(fused) <= 64
    # voxels never straddle x = 0.5, so fused labels stay pure
    np.testing.assert_array_equal(fused.labels, (fused.points[:, 0] > 0.5).astype(int))
    np.testing.assert_allclose(fused.probs.sum(axis=1), 1.0, rtol=1e-6)


def test_real_semantic_octree_if_present(rng):
    mapping = pytest.importorskip("mapping")
    try:
        tree_cls = mapping.SemanticOcTree
    except (AttributeError, ImportError):
        pytest.skip("mapping.SemanticOcTree not written yet")
    tree = tree_cls(0.1, 3)
    pts = np.c_[rng.uniform(0, 1, 200), rng.uniform(0, 1, 200), np.full(200, 1.0)]
    tree.insert_point_cloud(pts, np.zeros(3), labels=np.full(200, 2))
    cloud = SemanticCloud.from_semantic_octree(tree)
    assert len(cloud) > 0 and np.all(cloud.labels == 2)


def test_covariances_are_cached(rng):
    cloud = random_cloud(rng, 100)
    first = cloud.covariances()
    assert cloud.covariances() is first
    assert cloud.covariances(k=10) is not first
