"""Semantic point clouds: points with per-point class probabilities (the paper's "Semantic
Point Cloud"), their PLY files, and how to make them from RGB-D frames or a semantic map.

PLY layout (read and written through ``open3d.t``): ``x y z`` float32, optional
``red green blue`` float32 in [0, 1], ``label`` int32 (argmax class) and ``prob_0 ..
prob_{C-1}`` float32. Open3D's PLY writer rejects int64/uint32 attributes and its PCD
writer drops multi-column attributes, hence one float32 column per class.

Other tools' labelled clouds load too: a PLY with an integer label column (any PLY integer
type, e.g. ScanNet's ``ushort label``, or a float column holding whole numbers, e.g.
CloudCompare's ``scalar_label``; the names in :data:`LABEL_PROPERTIES`) gets one-hot
probabilities over the label values it holds (``label_ids``), and 8-bit colours are scaled to
[0, 1]. Two such clouds are put on one class list by :func:`common_classes`.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimation.errors import FormatError
from estimation.fileio import atomic_path, atomic_write, library_path, read_input_bytes
from perception.errors import PerceptionError

#: most classes a semantic cloud may have (labels in a PLY file are bounded by it before the
#: one-hot probabilities are allocated)
MAX_CLASSES = 1024
#: vertex properties read as the class label of a label-only PLY, the first one present
#: (names compared without case): ours and ScanNet's, then names other tools give the column
LABEL_PROPERTIES = ("label", "class", "semantic", "semantic_label", "class_id", "label_id",
                    "category_id", "scalar_label")

Segmenter = Callable[[np.ndarray], np.ndarray]  # (H, W, 3) uint8 RGB -> (H, W, C) probabilities


@dataclass(frozen=True)
class SemanticCloud:
    """A point cloud whose points carry class probabilities.

    Attributes
    ----------
    points : (N, 3) float64 coordinates in the cloud's frame
    probs : (N, C) float32 class probabilities (rows sum to 1)
    colors : (N, 3) float32 RGB in [0, 1], or None
    class_names : tuple of C names, or None
    label_ids : tuple of C label values, or None: the label each probability column stands
        for (a label-only PLY's values; None: the column index)
    labels : (N,) argmax class, as its label value where ``label_ids`` is given (derived)
    """

    points: np.ndarray
    probs: np.ndarray
    colors: np.ndarray | None = None
    class_names: tuple[str, ...] | None = None
    label_ids: tuple[int, ...] | None = None
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        points = np.ascontiguousarray(np.asarray(self.points, dtype=np.float64).reshape(-1, 3))
        probs = np.asarray(self.probs, dtype=np.float32)
        if probs.ndim != 2 or len(probs) != len(points):
            raise PerceptionError(
                f"probs must be (N, C) with N={len(points)}, got shape {probs.shape}")
        if probs.shape[1] < 1:
            raise PerceptionError("a semantic cloud needs at least one class")
        finite = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(probs), axis=1)
        if not np.all(finite):
            raise PerceptionError(f"semantic cloud has NaN or inf values (point "
                                  f"{int(np.argmin(finite))})")
        if np.any(probs < 0):
            raise PerceptionError("class probabilities must be non-negative")
        sums = probs.sum(axis=1, keepdims=True)
        if np.any(sums <= 0):
            raise PerceptionError("a point has all-zero class probabilities")
        probs = np.ascontiguousarray(probs / sums)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "probs", probs)
        if self.colors is not None:
            colors = np.asarray(self.colors, dtype=np.float32).reshape(-1, 3)
            if len(colors) != len(points):
                raise PerceptionError(f"{len(points)} points but {len(colors)} colours")
            object.__setattr__(self, "colors", colors)
        if self.class_names is not None:
            names = tuple(str(n) for n in self.class_names)
            if len(names) != probs.shape[1]:
                raise PerceptionError(f"{probs.shape[1]} classes but {len(names)} class names")
            object.__setattr__(self, "class_names", names)
        if self.label_ids is not None:
            ids = tuple(int(i) for i in self.label_ids)
            if len(ids) != probs.shape[1] or len(set(ids)) != len(ids):
                raise PerceptionError(f"{probs.shape[1]} classes need as many distinct label "
                                      f"ids, got {len(ids)} ({len(set(ids))} distinct)")
            object.__setattr__(self, "label_ids", ids)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def n_classes(self) -> int:
        return self.probs.shape[1]

    @property
    def labels(self) -> np.ndarray:
        """(N,) int32 argmax class of every point (its label value where ``label_ids`` is
        given; int64 if a value does not fit in int32)."""
        best = self.probs.argmax(axis=1)
        if self.label_ids is None:
            return best.astype(np.int32)
        ids = np.asarray(self.label_ids, dtype=np.int64)
        fits = ids.min() >= np.iinfo(np.int32).min and ids.max() <= np.iinfo(np.int32).max
        return ids[best].astype(np.int32 if fits else np.int64)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_labels(cls, points: np.ndarray, labels: np.ndarray, n_classes: int | None = None,
                    colors: np.ndarray | None = None,
                    class_names: tuple[str, ...] | None = None) -> SemanticCloud:
        """Return a cloud with one-hot probabilities from integer ``labels``."""
        labels = np.asarray(labels).reshape(-1)
        if len(labels) and labels.min() < 0:
            raise PerceptionError("labels must be non-negative")
        if n_classes is None:
            n_classes = int(labels.max()) + 1 if len(labels) else 1
        _check_class_count(n_classes)
        if len(labels) and labels.max() >= n_classes:
            raise PerceptionError(f"label {int(labels.max())} >= n_classes {n_classes}")
        return cls(points, _one_hot(labels, n_classes), colors, class_names)

    @classmethod
    def from_rgbd(cls, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray,
                  segmenter: Segmenter | None = None, probs_image: np.ndarray | None = None,
                  T_world_camera: np.ndarray | None = None, stride: int = 1,
                  min_depth: float = 0.1, max_depth: float = 8.0,
                  class_names: tuple[str, ...] | None = None) -> SemanticCloud:
        """Return the semantic cloud of one RGB-D frame (camera frame unless a pose is given).

        Either ``segmenter`` (a callable RGB image -> (H, W, C) probabilities: the pluggable
        segmentation network, none ships) or a precomputed ``probs_image`` gives the classes.
        Pixels with depth outside [min_depth, max_depth] are dropped.
        """
        rgb = np.asarray(rgb)
        depth = np.asarray(depth_m, dtype=np.float64)
        if depth.ndim != 2:
            raise PerceptionError(f"depth must be (H, W), got {depth.shape}")
        if probs_image is None:
            if segmenter is None:
                raise PerceptionError("give a segmenter or a probability image")
            probs_image = segmenter(rgb)
        probs_image = np.asarray(probs_image, dtype=np.float32)
        if probs_image.ndim != 3 or probs_image.shape[:2] != depth.shape:
            raise PerceptionError(
                f"probability image must be (H, W, C) with (H, W)={depth.shape}, "
                f"got {probs_image.shape}")
        h, w = depth.shape
        v, u = np.mgrid[0:h:stride, 0:w:stride]
        z = depth[v, u]
        ok = np.isfinite(z) & (z >= min_depth) & (z <= max_depth)
        u, v, z = u[ok], v[ok], z[ok]
        K = np.asarray(K, dtype=float)
        points = np.c_[(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z]
        if T_world_camera is not None:
            T = np.asarray(T_world_camera, dtype=float)
            points = points @ T[:3, :3].T + T[:3, 3]
        colors = None
        if rgb.ndim == 3 and rgb.shape[:2] == depth.shape:
            colors = rgb[v, u, :3].astype(np.float32) / 255.0
        return cls(points, probs_image[v, u], colors, class_names)

    @classmethod
    def from_semantic_octree(cls, tree, class_names: tuple[str, ...] | None = None
                             ) -> SemanticCloud:
        """Return the occupied voxel centres of a semantic octree with their class probabilities.

        ``tree`` is a :class:`mapping.SemanticOcTree` (or anything with
        ``occupied_voxels() -> (centres (M, 3), probs (M, C))``): the robot's "3D Semantic Map".
        """
        centres, probs = tree.occupied_voxels()
        return cls(np.asarray(centres), np.asarray(probs), None, class_names)

    @classmethod
    def fuse_voxels(cls, points: np.ndarray, probs: np.ndarray, voxel_size: float,
                    class_names: tuple[str, ...] | None = None) -> SemanticCloud:
        """Return one point per voxel (the voxel's mean point) with averaged class probabilities.

        The fall-back robot map when no semantic octree is used: averaging the per-view
        probabilities is the maximum-likelihood fusion of independent categorical votes.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        probs = np.asarray(probs, dtype=np.float64)
        if len(points) == 0:
            raise PerceptionError("no points to fuse")
        keys = np.floor(points / voxel_size).astype(np.int64)
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        m = len(counts)
        sum_points = np.zeros((m, 3))
        np.add.at(sum_points, inverse, points)
        sum_probs = np.zeros((m, probs.shape[1]))
        np.add.at(sum_probs, inverse, probs)
        return cls(sum_points / counts[:, None], sum_probs / counts[:, None], None, class_names)

    # -- operations ---------------------------------------------------------------------------
    def transformed(self, T: np.ndarray) -> SemanticCloud:
        """Return the cloud with points mapped by the 4x4 ``T`` (T_new_old)."""
        T = np.asarray(T, dtype=float)
        return SemanticCloud(self.points @ T[:3, :3].T + T[:3, 3], self.probs, self.colors,
                             self.class_names, self.label_ids)

    def select(self, rows: np.ndarray) -> SemanticCloud:
        """Return the sub-cloud of the given row indices or boolean mask."""
        colors = None if self.colors is None else self.colors[rows]
        return SemanticCloud(self.points[rows], self.probs[rows], colors, self.class_names,
                             self.label_ids)

    def subsample(self, n: int, rng: np.random.Generator) -> SemanticCloud:
        """Return ``n`` points drawn without replacement (all points when n >= N)."""
        if n >= len(self):
            return self
        return self.select(np.sort(rng.choice(len(self), size=n, replace=False)))

    def covariances(self, k: int = 20, epsilon: float = 1e-3) -> np.ndarray:
        """Return the (N, 3, 3) GICP per-point covariances (computed once, then cached)."""
        key = ("cov", int(k), float(epsilon))
        if key not in self._cache:
            from estimation.registration import point_covariances

            self._cache[key] = point_covariances(self.points, k, epsilon)
        return self._cache[key]

    def to_scan(self):
        """Return an :class:`estimation.Scan` (float32 points, labels, probs) for a PoseGraph."""
        from estimation.pose_graph import Scan

        return Scan(self.points.astype(np.float32), self.labels, self.probs)

    # -- files --------------------------------------------------------------------------------
    def write_ply(self, path: str | os.PathLike, ascii: bool = False) -> None:
        """Write the cloud as PLY (x y z, colours, int32 label, float32 prob_i), atomically."""
        import open3d as o3d

        pcd = o3d.t.geometry.PointCloud()
        pcd.point.positions = o3d.core.Tensor(self.points.astype(np.float32))
        if self.colors is not None:
            pcd.point.colors = o3d.core.Tensor(self.colors.astype(np.float32))
        labels = self.labels
        if labels.dtype != np.int32:
            raise PerceptionError(f"{path}: label ids beyond int32 cannot be written (Open3D's "
                                  "PLY writer takes int32 labels)")
        pcd.point.label = o3d.core.Tensor(labels.reshape(-1, 1))
        # a label-only cloud's labels are its label values, written as the label column alone
        # (prob_i columns would number the classes anew); other clouds write prob_i too
        one_hot = self.label_ids is not None and np.all(self.probs.max(axis=1) == 1.0)
        if self.label_ids is not None and not one_hot:
            raise PerceptionError(f"{path}: class probabilities over label ids "
                                  f"{self.label_ids[:4]}... cannot be written as prob_i columns")
        for c in range(0 if one_hot else self.n_classes):
            pcd.point[f"prob_{c}"] = o3d.core.Tensor(
                np.ascontiguousarray(self.probs[:, c:c + 1]))
        path = Path(path)
        # Open3D writes by file name and picks the format from the suffix
        library_path(path, "Open3D")  # the temporary file's name contains it
        with atomic_path(path, suffix=".ply") as tmp_path:
            if not o3d.t.io.write_point_cloud(str(tmp_path), pcd, write_ascii=ascii):
                raise PerceptionError(f"{path}: Open3D could not write the PLY")
        if self.class_names is not None:
            with atomic_write(path.with_suffix(".classes.txt"), "w") as handle:
                handle.write("\n".join(self.class_names) + "\n")

    @classmethod
    def read_ply(cls, path: str | os.PathLike, n_classes: int | None = None) -> SemanticCloud:
        """Return the cloud stored in a PLY file (see the module docstring for the layout).

        A label-only file (see the module docstring) gets one column per label value it
        holds (``label_ids``); ``n_classes`` instead numbers its labels as the columns
        0..n_classes-1 (ids None, as a probability file's). Raises :class:`FormatError` for
        files that are not semantic PLYs.
        """
        from estimation.ply import check_ply, read_ply_quietly

        path = Path(path)
        header = check_ply(path)
        vertex = header.element("vertex")
        if vertex is None or vertex.count == 0 or \
                not {"x", "y", "z"} <= set(header.vertex_properties):
            raise FormatError(path, "PLY has no vertices with x, y, z")
        pcd = read_ply_quietly(path)
        attrs = set(pcd.point)
        if "positions" in attrs and pcd.point.positions.shape[0] != vertex.count:
            raise FormatError(path, f"Open3D read {pcd.point.positions.shape[0]} of the "
                              f"{vertex.count} vertices the header claims")
        if "positions" not in attrs or pcd.point.positions.shape[0] == 0:
            raise FormatError(path, "PLY has no vertices with x, y, z")
        points = pcd.point.positions.numpy().astype(np.float64)
        colors = None
        if "colors" in attrs:
            colors = pcd.point.colors.numpy()
            # 8-bit (and 16-bit) colour channels as [0, 1], as ours are written
            scale = np.iinfo(colors.dtype).max if colors.dtype.kind in "iu" else 1.0
            colors = colors.astype(np.float32) / np.float32(scale)
        label_ids = None
        prob_names = sorted((a for a in attrs if a.startswith("prob_")),
                            key=lambda a: int(a[5:]) if a[5:].isdigit() else -1)
        if prob_names:
            expected = [f"prob_{c}" for c in range(len(prob_names))]
            if prob_names != expected:
                raise FormatError(path, f"probability columns {prob_names} are not "
                                        f"prob_0..prob_{len(prob_names) - 1}")
            probs = np.hstack([pcd.point[a].numpy().reshape(-1, 1) for a in prob_names])
            if n_classes is not None and n_classes != probs.shape[1]:
                raise FormatError(path, f"file has {probs.shape[1]} classes, expected "
                                        f"{n_classes}")
            if not np.all(np.isfinite(probs)) or np.any(probs < 0) or \
                    np.any(probs.sum(axis=1) <= 0):
                raise FormatError(path, "invalid class probabilities (negative, NaN or all zero)")
        elif (label_name := _label_property(header.vertex_properties)) is not None:
            probs, label_ids = _one_hot_from_file(path, header, label_name, n_classes)
        else:
            raise FormatError(path, "PLY has neither a label column (" +
                              ", ".join(LABEL_PROPERTIES) + ") nor prob_i properties")
        names = None
        names_path = path.with_suffix(".classes.txt")
        if names_path.is_file():
            try:
                text = read_input_bytes(names_path, max_bytes=1 << 20).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise FormatError(names_path, "class names are not UTF-8 text",
                                  offset=exc.start) from None
            lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
            if label_ids is not None and min(label_ids) >= 0 and max(label_ids) < len(lines):
                names = tuple(lines[i] for i in label_ids)  # a name per label value
            elif len(lines) == probs.shape[1]:
                names = tuple(lines)
        try:
            return cls(points, probs, colors, names, label_ids)
        except PerceptionError as exc:
            raise FormatError(path, str(exc)) from None


def _label_property(properties: tuple[str, ...]) -> str | None:
    """Return the vertex property that holds the labels (:data:`LABEL_PROPERTIES`), or None."""
    by_name = {name.lower(): name for name in properties}
    return next((by_name[n] for n in LABEL_PROPERTIES if n in by_name), None)


def _one_hot_from_file(path: Path, header, name: str, n_classes: int | None
                       ) -> tuple[np.ndarray, tuple[int, ...] | None]:
    """Return (one-hot probabilities, label ids or None) of the label column ``name``.

    Without ``n_classes`` the columns are the label values the file holds, in increasing
    order (``label_ids``): any integers, at most MAX_CLASSES distinct ones. With it, the
    labels are the column indices 0..n_classes-1 (ids None), as a probability file's are.
    """
    from estimation.ply import read_vertex_property

    raw = read_vertex_property(path, header, name)
    if raw.dtype.kind == "f":
        whole = np.isfinite(raw) & (raw == np.round(raw)) & (np.abs(raw) < 2.0 ** 53)
        if not np.all(whole):
            bad = int(np.argmin(whole))
            raise FormatError(path, f"label column {name!r} holds {float(raw[bad])} at vertex "
                              f"{bad}: labels must be whole numbers")
    labels = raw.astype(np.int64)
    if n_classes is not None:
        c = _check_class_count(int(n_classes))
        if labels.min() < 0 or labels.max() >= c:
            bad = int(np.argmin(labels) if labels.min() < 0 else np.argmax(labels))
            raise FormatError(path, f"label {int(labels[bad])} at vertex {bad} is outside "
                              f"0..n_classes-1 = 0..{c - 1}")
        ids, column = None, labels
    else:
        values, column = np.unique(labels, return_inverse=True)
        if len(values) > MAX_CLASSES:
            raise FormatError(path, f"{len(values)} distinct labels: more than the "
                              f"{MAX_CLASSES}-class limit")
        ids = tuple(int(v) for v in values)
        c = len(values)
    return _one_hot(column, c), ids


def _check_class_count(n_classes: int) -> int:
    """Return ``n_classes`` if 1..MAX_CLASSES (checked before any one-hot allocation)."""
    if not 1 <= n_classes <= MAX_CLASSES:
        raise PerceptionError(f"n_classes must be 1..{MAX_CLASSES}, got {n_classes}")
    return n_classes


def _one_hot(column: np.ndarray, n_classes: int) -> np.ndarray:
    """Return (N, n_classes) float32 one-hot probabilities of the class indices ``column``."""
    column = np.asarray(column).reshape(-1).astype(np.int64)
    probs = np.zeros((len(column), n_classes), dtype=np.float32)
    probs[np.arange(len(column)), column] = 1.0
    return probs


def common_classes(a: SemanticCloud, b: SemanticCloud) -> tuple[SemanticCloud, SemanticCloud]:
    """Return ``a`` and ``b`` with their probability columns on one class list.

    Clouds read from label-only files carry the label values their columns stand for
    (``label_ids``), and one half of a room may lack labels the other holds: both then get
    the union of the two value lists (absent classes a zero column). A cloud without ids
    numbers its classes 0..C-1; two such clouds must have the same C.
    """
    if a.label_ids is None and b.label_ids is None:
        if a.n_classes != b.n_classes:
            raise PerceptionError(f"one cloud has {a.n_classes} classes, the other "
                                  f"{b.n_classes}: the same label set is needed")
        return a, b
    ids_a = a.label_ids if a.label_ids is not None else tuple(range(a.n_classes))
    ids_b = b.label_ids if b.label_ids is not None else tuple(range(b.n_classes))
    union = tuple(sorted(set(ids_a) | set(ids_b)))
    for cloud, ids in ((a, ids_a), (b, ids_b)):
        if cloud.label_ids is None and union != ids:
            raise PerceptionError(f"a cloud with {cloud.n_classes} numbered classes cannot share "
                                  f"a class list with label values {union[:6]}...")
    if len(union) > MAX_CLASSES:
        raise PerceptionError(f"{len(union)} distinct labels in the two clouds: more than the "
                              f"{MAX_CLASSES}-class limit")

    def widened(cloud: SemanticCloud, ids: tuple[int, ...]) -> SemanticCloud:
        if ids == union:
            return cloud
        probs = np.zeros((len(cloud), len(union)), dtype=np.float32)
        probs[:, np.searchsorted(union, ids)] = cloud.probs
        return SemanticCloud(cloud.points, probs, cloud.colors, None, union)

    return widened(a, ids_a), widened(b, ids_b)
