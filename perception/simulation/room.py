"""A household room for the robot-headset calibration experiment of Nakamura et al.

World (robot map) frame: z up, the floor at z = 0, the room spans [0, W] x [0, D] x [0, H].
Furniture as in the paper's four places: a TV corner (TV on a low cabinet, a sofa), a work
desk with a chair, a bookshelf with books, a dining table with chairs. Every surface carries
one class (:data:`CLASS_NAMES`).

- The robot's "3D Semantic Map": RGB-D views from a robot camera at ~1 m, ray cast with
  :class:`open3d.t.geometry.RaycastingScene`, fused into the semantic octree
  (:class:`mapping.SemanticOcTree` when available, else voxel fusion of labelled points).
- The headset clouds: the four viewpoints (``VIEWPOINTS``) ray cast from a head at ~1.6 m,
  as the HoloLens obtains depth from its spatial mesh, expressed in the headset's own world
  frame ``T_map_headset^-1 * p`` (optionally left-handed: z flipped, as in Unity).
- Labels: the true class with probability ``label_accuracy``, else a uniformly random other
  class; probabilities are calibrated soft scores (``acc`` on the observed class, the rest
  shared equally).
- Randomness: depth noise and label noise come from separate streams of one seed
  (:func:`random_streams`), so the map's and the headset's points are the same for every
  label accuracy; only the labels differ.

In memory::

    room = build_room()
    robot_map = robot_semantic_map(room, RoomConfig())
    headset, T_map_headset = headset_cloud(room, "desk", RoomConfig(label_accuracy=0.9))

On disk: :func:`simulate_room` writes ``robot_map.ply``, ``headset_<view>.ply``,
``T_map_headset_<view>.txt`` (4x4, the ground truth T_target_source for
``octofactor register headset_<view>.ply robot_map.ply``) and ``classes.txt``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from estimation.fileio import atomic_write
from estimation.registration.transform_file import write_transform
from perception.errors import PerceptionError
from perception.semantic_cloud import SemanticCloud

CLASS_NAMES = ("floor", "wall", "ceiling", "tv", "cabinet", "sofa", "desk", "chair",
               "shelf", "books", "table")
CLASS = {name: i for i, name in enumerate(CLASS_NAMES)}

# name -> (eye position, look-at point) of the headset, in the room frame
VIEWPOINTS = {
    "tv": ((2.2, 2.2, 1.6), (0.8, 4.6, 0.8)),
    "desk": ((3.6, 2.6, 1.6), (5.4, 4.2, 0.8)),
    "shelf": ((3.0, 2.3, 1.6), (3.1, 4.8, 1.0)),
    "dining": ((1.8, 2.4, 1.6), (3.5, 1.0, 0.6)),
}

# the left-handed headset frame (Unity/HoloLens) is the right-handed one with z negated
LEFT_HANDED_FLIP = np.diag([1.0, 1.0, -1.0, 1.0])


@dataclass(frozen=True)
class RoomConfig:
    """Everything that defines a simulated room data set (deterministic for ``seed``).

    Attributes
    ----------
    seed : int
    width, depth, height : room size (m)
    label_accuracy : probability that a headset point keeps its true class
    robot_label_accuracy : the same for the robot's map
    robot_voxel : resolution (m) of the robot's semantic map
    headset_voxel : voxel filter (m) of the headset clouds (0 = none)
    image_width, image_height, focal : pinhole of both cameras (pixels)
    depth_noise : depth noise sigma at 1 m (m); grows with z^2
    headset_offset_m, headset_offset_deg : size of the ground-truth T_map_headset
    left_handed : write headset clouds in a left-handed frame (z flipped)
    """

    seed: int = 0
    width: float = 6.0
    depth: float = 5.0
    height: float = 2.6
    label_accuracy: float = 0.9
    robot_label_accuracy: float = 0.95
    robot_voxel: float = 0.03
    headset_voxel: float = 0.02
    image_width: int = 320
    image_height: int = 240
    focal: float = 240.0
    depth_noise: float = 0.0015
    headset_offset_m: float = 1.5
    headset_offset_deg: float = 60.0
    left_handed: bool = False

    def __post_init__(self):
        if not 0.0 <= self.label_accuracy <= 1.0 or not 0.0 <= self.robot_label_accuracy <= 1.0:
            raise PerceptionError("label accuracies must be in [0, 1]")
        numbers = [v for v in vars(self).values() if isinstance(v, (int, float))]
        if not all(np.isfinite(numbers)):
            raise PerceptionError("room parameters must be finite numbers (no NaN or inf)")
        if not self.focal > 0 or min(self.image_width, self.image_height) < 1:
            raise PerceptionError(f"focal must be > 0 and the image at least 1x1, got focal "
                                  f"{self.focal}, {self.image_width}x{self.image_height}")
        if min(self.width, self.depth, self.height) <= 0.5:
            raise PerceptionError("room must be larger than 0.5 m in every direction")


@dataclass(frozen=True)
class Room:
    """The room's geometry: one Open3D triangle mesh per class and the ray-casting scene."""

    meshes: dict           # class name -> o3d.geometry.TriangleMesh
    scene: object          # o3d.t.geometry.RaycastingScene
    geometry_class: np.ndarray  # geometry id -> class index
    config: RoomConfig

    def mesh(self):
        """Return all surfaces as one legacy TriangleMesh with a colour per class."""
        import open3d as o3d

        out = o3d.geometry.TriangleMesh()
        palette = _palette(len(CLASS_NAMES))
        for name, mesh in self.meshes.items():
            m = o3d.geometry.TriangleMesh(mesh)
            m.paint_uniform_color(palette[CLASS[name]])
            out += m
        return out


def _palette(n: int) -> np.ndarray:
    hues = np.linspace(0, 1, n, endpoint=False)
    return np.stack([0.5 + 0.5 * np.cos(2 * np.pi * (hues - k / 3)) for k in range(3)], axis=1)


def _box(lo, hi):
    import open3d as o3d

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return o3d.geometry.TriangleMesh.create_box(*(hi - lo)).translate(lo)


def build_room(config: RoomConfig | None = None) -> Room:
    """Return the room meshes and their ray-casting scene."""
    import open3d as o3d

    cfg = config or RoomConfig()
    W, D, H = cfg.width, cfg.depth, cfg.height
    t = 0.1  # wall thickness, outside the room
    parts: dict[str, list] = {name: [] for name in CLASS_NAMES}
    parts["floor"].append(_box((-t, -t, -t), (W + t, D + t, 0.0)))
    parts["ceiling"].append(_box((-t, -t, H), (W + t, D + t, H + t)))
    parts["wall"] += [_box((-t, -t, 0), (0, D + t, H)), _box((W, -t, 0), (W + t, D + t, H)),
                      _box((0, -t, 0), (W, 0, H)), _box((0, D, 0), (W, D + t, H))]
    # TV corner: cabinet, TV, sofa
    parts["cabinet"].append(_box((0.2, D - 0.45, 0), (1.6, D - 0.05, 0.5)))
    parts["tv"].append(_box((0.35, D - 0.2, 0.55), (1.45, D - 0.12, 1.2)))
    parts["sofa"] += [_box((0.3, D - 2.6, 0), (1.9, D - 1.8, 0.42)),
                      _box((0.3, D - 2.6, 0.42), (1.9, D - 2.4, 0.85))]
    # work desk with a chair and a monitor-like box counted as desk
    parts["desk"] += [_box((W - 0.75, D - 1.8, 0.70), (W - 0.05, D - 0.4, 0.75))]
    parts["desk"] += [_box((W - 0.75 + dx, D - 1.8 + dy, 0), (W - 0.7 + dx, D - 1.75 + dy, 0.70))
                      for dx in (0.0, 0.65) for dy in (0.0, 1.35)]
    parts["desk"].append(_box((W - 0.35, D - 1.3, 0.75), (W - 0.3, D - 0.8, 1.1)))
    parts["chair"] += [_box((W - 1.35, D - 1.3, 0.42), (W - 0.9, D - 0.85, 0.47)),
                       _box((W - 1.4, D - 1.3, 0.47), (W - 1.35, D - 0.85, 0.95))]
    # bookshelf: frame, boards and rows of books
    x0, x1, y0, y1 = 2.5, 3.8, D - 0.35, D - 0.02
    parts["shelf"] += [_box((x0, y0, 0), (x0 + 0.03, y1, 1.9)),
                       _box((x1 - 0.03, y0, 0), (x1, y1, 1.9))]
    parts["shelf"] += [_box((x0, y0, z), (x1, y1, z + 0.03)) for z in (0.0, 0.45, 0.9, 1.35, 1.87)]
    rng = np.random.default_rng(cfg.seed)
    for z in (0.03, 0.48, 0.93, 1.38):
        x = x0 + 0.05
        while x < x1 - 0.15:
            w = rng.uniform(0.03, 0.08)
            h = rng.uniform(0.2, 0.38)
            depth_offset = rng.uniform(0.0, 0.08)
            parts["books"].append(_box((x, y0 + depth_offset, z), (x + w, y1 - 0.02, z + h)))
            x += w + rng.uniform(0.0, 0.05)
    # dining table with legs and four chairs
    cx, cy = 3.5, 1.1
    parts["table"].append(_box((cx - 0.7, cy - 0.45, 0.72), (cx + 0.7, cy + 0.45, 0.76)))
    parts["table"] += [_box((cx + sx * 0.62 - 0.03, cy + sy * 0.38 - 0.03, 0),
                            (cx + sx * 0.62 + 0.03, cy + sy * 0.38 + 0.03, 0.72))
                       for sx in (-1, 1) for sy in (-1, 1)]
    for sx in (-0.35, 0.35):
        for sy, back in ((-0.75, -1), (0.75, 1)):
            px, py = cx + sx, cy + sy
            parts["chair"].append(_box((px - 0.2, py - 0.2, 0.42), (px + 0.2, py + 0.2, 0.46)))
            by = py + back * 0.2
            parts["chair"].append(_box((px - 0.2, min(by, by + back * 0.04), 0.46),
                                       (px + 0.2, max(by, by + back * 0.04), 0.9)))
    scene = o3d.t.geometry.RaycastingScene()
    meshes, geometry_class = {}, []
    for name, boxes in parts.items():
        if not boxes:
            continue
        mesh = o3d.geometry.TriangleMesh()
        for b in boxes:
            mesh += b
        meshes[name] = mesh
        gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        while len(geometry_class) <= gid:
            geometry_class.append(-1)
        geometry_class[gid] = CLASS[name]
    return Room(meshes, scene, np.asarray(geometry_class), cfg)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Return T_world_camera (4x4) of a camera at ``eye`` looking at ``target``.

    Camera frame: x right, y down, z forward.
    """
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise PerceptionError("look_at: viewing direction parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, y, z]
    T[:3, 3] = eye
    return T


def random_streams(entropy: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Return independent (geometry, labels) generators for one seed.

    Depth noise and label noise draw from separate streams (two ``SeedSequence`` children),
    so the geometry of a view is the same for every label accuracy: only the labels change.
    """
    geometry, labels = np.random.SeedSequence(entropy).spawn(2)
    return np.random.default_rng(geometry), np.random.default_rng(labels)


def render_view(room: Room, T_world_camera: np.ndarray, rng: np.random.Generator,
                label_accuracy: float, label_rng: np.random.Generator | None = None
                ) -> SemanticCloud:
    """Return the noisy labelled points (world frame) one camera sees by ray casting.

    ``rng`` draws the depth noise, ``label_rng`` (default: ``rng``) the label noise; give
    separate streams (:func:`random_streams`) to keep the points independent of
    ``label_accuracy``.
    """
    import open3d as o3d

    cfg = room.config
    w, h, f = cfg.image_width, cfg.image_height, cfg.focal
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    extrinsic = np.linalg.inv(T_world_camera)
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(K), o3d.core.Tensor(extrinsic), w, h)
    hit = room.scene.cast_rays(rays)
    t_hit = hit["t_hit"].numpy().reshape(-1)
    gid = hit["geometry_ids"].numpy().reshape(-1)
    rays_np = rays.numpy().reshape(-1, 6)
    ok = np.isfinite(t_hit) & (gid != o3d.t.geometry.RaycastingScene.INVALID_ID)
    rays_np, t_hit, gid = rays_np[ok], t_hit[ok], gid[ok].astype(np.int64)
    direction = rays_np[:, 3:]
    points = rays_np[:, :3] + direction * t_hit[:, None]
    # depth noise along the ray, sigma = depth_noise * z^2 (structured-light like)
    z = (points - T_world_camera[:3, 3]) @ T_world_camera[:3, 2]
    unit = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    points = points + unit * (rng.normal(size=len(z)) * cfg.depth_noise * z ** 2)[:, None]
    labels = noisy_labels(room.geometry_class[gid], label_accuracy, len(CLASS_NAMES),
                          rng if label_rng is None else label_rng)
    return labels_to_cloud(points, labels, label_accuracy)


def noisy_labels(labels: np.ndarray, accuracy: float, n_classes: int,
                 rng: np.random.Generator) -> np.ndarray:
    """Return ``labels`` with each one replaced, with probability 1 - accuracy, by another class."""
    labels = np.asarray(labels, dtype=np.int64).copy()
    flip = rng.random(len(labels)) >= accuracy
    if n_classes > 1:
        shift = rng.integers(1, n_classes, size=int(flip.sum()))
        labels[flip] = (labels[flip] + shift) % n_classes
    return labels


def labels_to_cloud(points: np.ndarray, labels: np.ndarray, accuracy: float) -> SemanticCloud:
    """Return a cloud with calibrated soft scores: ``accuracy`` on the observed label."""
    c = len(CLASS_NAMES)
    acc = min(max(accuracy, 1.0 / c), 1.0)
    probs = np.full((len(labels), c), (1.0 - acc) / (c - 1), dtype=np.float32)
    probs[np.arange(len(labels)), labels] = acc
    return SemanticCloud(points, probs, None, CLASS_NAMES)


def robot_views(config: RoomConfig) -> list[np.ndarray]:
    """Return the robot camera poses T_world_camera (a loop around the room at ~1 m)."""
    W, D = config.width, config.depth
    poses = []
    centre = np.array([W / 2, D / 2, 1.0])
    for angle in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        eye = centre + np.array([0.8 * np.cos(angle), 0.6 * np.sin(angle), 0.0])
        target = centre + np.array([3.0 * np.cos(angle), 3.0 * np.sin(angle), -0.4])
        poses.append(look_at(eye, target))
    # the robot also looks at each place from its head height (HSR: up to ~1.3 m) and from
    # both sides, so that the map covers what the headset sees from above
    for eye, target in VIEWPOINTS.values():
        for dx, dy, z in ((0.0, 0.0, 1.0), (0.5, -0.3, 1.3), (-0.5, 0.3, 1.3)):
            poses.append(look_at((eye[0] + dx, eye[1] + dy, z), target))
    return poses


def robot_semantic_map(room: Room, config: RoomConfig | None = None,
                       use_octree: bool = True) -> SemanticCloud:
    """Return the robot's 3-D semantic map (world frame) fused from its RGB-D views.

    Uses :class:`mapping.SemanticOcTree` when the mapping package provides it (and
    ``use_octree``), otherwise voxel fusion of the labelled points at the same resolution.
    """
    cfg = config or room.config
    rng, label_rng = random_streams(cfg.seed + 1)
    views = [(T, render_view(room, T, rng, cfg.robot_label_accuracy, label_rng))
             for T in robot_views(cfg)]
    tree = None
    if use_octree:
        try:
            from mapping import SemanticOcTree  # written by the mapping package
        except (ImportError, AttributeError, ModuleNotFoundError):
            SemanticOcTree = None
        if SemanticOcTree is not None:
            tree = SemanticOcTree(cfg.robot_voxel, len(CLASS_NAMES))
            for T, cloud in views:
                tree.insert_point_cloud(cloud.points, T[:3, 3], probs=cloud.probs)
            fused = SemanticCloud.from_semantic_octree(tree, CLASS_NAMES)
            return fused
    points = np.vstack([c.points for _, c in views])
    probs = np.vstack([c.probs for _, c in views])
    return SemanticCloud.fuse_voxels(points, probs, cfg.robot_voxel, CLASS_NAMES)


def ground_truth_offset(config: RoomConfig, view: str) -> np.ndarray:
    """Return T_map_headset: where the headset's own world frame sits in the robot map."""
    rng = np.random.default_rng(config.seed * 1000 + sorted(VIEWPOINTS).index(view) + 7)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    # the headset's frame is gravity aligned in practice: mostly a yaw, a little tilt
    axis = axis * np.array([0.15, 0.15, 1.0])
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(config.headset_offset_deg) * rng.uniform(0.5, 1.0)
    shift = rng.normal(size=3)
    shift *= config.headset_offset_m / np.linalg.norm(shift)
    return gtsam.Pose3(gtsam.Rot3.Rodrigues(axis * angle), shift).matrix()


def headset_cloud(room: Room, view: str, config: RoomConfig | None = None
                  ) -> tuple[SemanticCloud, np.ndarray]:
    """Return (headset cloud in the headset frame, T_map_headset) for one viewpoint.

    With ``config.left_handed`` the cloud is in the left-handed frame (z negated) and the
    returned T still maps the right-handed headset frame into the map: convert with
    :data:`LEFT_HANDED_FLIP` first (what ``octofactor calibrate --left-handed`` does).
    """
    cfg = config or room.config
    if view not in VIEWPOINTS:
        raise PerceptionError(f"unknown viewpoint {view!r}; choose from {sorted(VIEWPOINTS)}")
    rng, label_rng = random_streams(cfg.seed * 100 + sorted(VIEWPOINTS).index(view))
    eye, target = VIEWPOINTS[view]
    cloud = render_view(room, look_at(eye, target), rng, cfg.label_accuracy, label_rng)
    if cfg.headset_voxel > 0:
        cloud = SemanticCloud.fuse_voxels(cloud.points, cloud.probs, cfg.headset_voxel,
                                          CLASS_NAMES)
    T_map_headset = ground_truth_offset(cfg, view)
    cloud = cloud.transformed(np.linalg.inv(T_map_headset))
    if cfg.left_handed:
        cloud = cloud.transformed(LEFT_HANDED_FLIP)
    return cloud, T_map_headset


def simulate_room(out_dir: str | os.PathLike, config: RoomConfig | None = None,
                  views: tuple[str, ...] | None = None) -> dict:
    """Write the room data set to ``out_dir``; return {name: path} of what was written."""
    cfg = config or RoomConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    room = build_room(cfg)
    written = {}
    robot_map = robot_semantic_map(room, cfg)
    robot_map.write_ply(out / "robot_map.ply")
    written["robot_map"] = out / "robot_map.ply"
    for view in views or tuple(VIEWPOINTS):
        cloud, T = headset_cloud(room, view, cfg)
        cloud.write_ply(out / f"headset_{view}.ply")
        write_transform(out / f"T_map_headset_{view}.txt", T)
        written[f"headset_{view}"] = out / f"headset_{view}.ply"
        written[f"T_map_headset_{view}"] = out / f"T_map_headset_{view}.txt"
    with atomic_write(out / "classes.txt", "w") as handle:
        handle.write("\n".join(CLASS_NAMES) + "\n")
    written["classes"] = out / "classes.txt"
    return written
