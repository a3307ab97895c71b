"""RGB-D frames: camera files, the TUM RGB-D sequence layout, back-projection and the voxel filter.

The TUM RGB-D layout (Sturm et al., IROS 2012) is a folder with ``rgb.txt`` and ``depth.txt``
(``timestamp relative/path.png`` per line, ``#`` comments), optional ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``: translation in metres, unit quaternion in x y z w order,
the pose ``T_world_camera``), colour PNGs and 16-bit depth PNGs whose value / ``depth_scale``
(5000 for TUM) is the depth in metres, 0 meaning "no measurement". octofactor adds a small camera
file, ``camera.txt`` (format in docs/camera_file.md), so a sequence carries its own intrinsics.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import gtsam
import numpy as np

from estimation.errors import FormatError
from estimation.fileio import atomic_write, check_input_file, read_input_bytes
from perception.errors import ImageError, PerceptionError
from perception.image_header import decode

CAMERA_FILE_NAME = "camera.txt"
#: largest image file read (bytes): a 4K 16-bit PNG is ~25 MB
MAX_IMAGE_FILE_BYTES = 256 << 20
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")


@dataclass(frozen=True)
class CameraIntrinsics:
    """A pinhole camera (no distortion) and the scale of its depth images.

    Attributes
    ----------
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (pixel centres at integer coordinates).
    width, height : int
        Image size in pixels.
    depth_scale : float
        Depth PNG value per metre (TUM: 5000, i.e. 0.2 mm steps).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 5000.0

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy", "depth_scale"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.number)) or not np.isfinite(value):
                raise PerceptionError(f"{name} must be a finite number, got {value!r}")
        for name in ("fx", "fy", "depth_scale"):
            if not getattr(self, name) > 0:
                raise PerceptionError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise PerceptionError(f"{name} must be a positive integer, got {value!r}")

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual symbol for the camera matrix
        """The 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> CameraIntrinsics:
        """Return the intrinsics of the same camera with images resized to width x height.

        Pixel centres stay at integer coordinates: x' = (x + 0.5) s - 0.5 per axis.
        """
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, width=width, height=height)


def read_camera_file(path: str | os.PathLike) -> CameraIntrinsics:
    """Return the intrinsics stored in a camera file (see docs/camera_file.md).

    Raises
    ------
    FormatError
        The file is missing, has not exactly one data line of seven numbers, or holds
        non-positive focal lengths, sizes or depth scale.
    """
    path = Path(path)
    try:
        check_input_file(path, max_bytes=1 << 20)
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FormatError(path, "camera file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(path, f"cannot read camera file: {exc}") from None
    rows = [(number, line.split("#", 1)[0].split()) for number, line in
            enumerate(text.splitlines(), start=1)]
    rows = [(number, fields) for number, fields in rows if fields]
    if len(rows) != 1:
        raise FormatError(path, f"expected one data line '{' '.join(_CAMERA_KEYS)}', "
                                f"found {len(rows)}")
    number, fields = rows[0]
    if len(fields) != len(_CAMERA_KEYS):
        raise FormatError(path, f"expected {len(_CAMERA_KEYS)} numbers "
                                f"({' '.join(_CAMERA_KEYS)}), found {len(fields)}", line=number)
    try:
        values = [float(field) for field in fields]
    except ValueError:
        raise FormatError(path, "camera parameters must be numbers", line=number) from None
    fx, fy, cx, cy, width, height, depth_scale = values
    if not all(np.isfinite(values)) or min(fx, fy, width, height, depth_scale) <= 0:
        raise FormatError(path, "fx, fy, width, height and depth_scale must be positive "
                                "and every value finite", line=number)
    if width != int(width) or height != int(height):
        raise FormatError(path, "width and height must be integers", line=number)
    return CameraIntrinsics(fx, fy, cx, cy, int(width), int(height), depth_scale)


def write_camera_file(path: str | os.PathLike, intr: CameraIntrinsics) -> None:
    """Write ``intr`` as a camera file (atomically; format in docs/camera_file.md)."""
    with atomic_write(path, "w") as handle:
        handle.write("# octofactor camera file: pinhole, no distortion; "
                     "pixel centres at integers\n")
        handle.write("# depth_scale: depth PNG value per metre (TUM: 5000)\n")
        handle.write("# " + " ".join(_CAMERA_KEYS) + "\n")
        handle.write(f"{intr.fx!r} {intr.fy!r} {intr.cx!r} {intr.cy!r} {intr.width:d} "
                     f"{intr.height:d} {intr.depth_scale!r}\n")


@dataclass(frozen=True)
class RgbdFrame:
    """One associated colour + depth pair of a sequence.

    Attributes
    ----------
    index : int
        Position in the sequence (0-based).
    timestamp : float
        The colour image's timestamp in seconds.
    rgb : np.ndarray
        (H, W, 3) uint8, channel order R G B.
    depth_m : np.ndarray
        (H, W) float32 depth along the optical axis in metres; 0 where there is no measurement.
    T_world_camera_gt : gtsam.Pose3 or None
        Ground-truth pose at ``timestamp`` (interpolated), None without ground truth.
    rgb_path, depth_path : pathlib.Path or None
        Where the images came from (None for frames made in memory).
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth_m: np.ndarray
    T_world_camera_gt: gtsam.Pose3 | None = None
    rgb_path: Path | None = None
    depth_path: Path | None = None


def resize_frame(frame: RgbdFrame, width: int, height: int) -> RgbdFrame:
    """Return ``frame`` with its images resized to width x height (colour by area averaging,
    depth by nearest neighbour so that no depth is invented across edges)."""
    if frame.rgb.shape[1] == width and frame.rgb.shape[0] == height:
        return frame
    import cv2

    rgb = cv2.resize(frame.rgb, (width, height), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(frame.depth_m, (width, height), interpolation=cv2.INTER_NEAREST)
    return replace(frame, rgb=rgb, depth_m=depth)


def read_timestamp_list(path: str | os.PathLike) -> tuple[np.ndarray, list[str]]:
    """Return (timestamps (N,) float64, file names) of a TUM ``rgb.txt`` / ``depth.txt``."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "association file not found")
    stamps: list[float] = []
    names: list[str] = []
    check_input_file(path)
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split("#", 1)[0].split()
            if not fields:
                continue
            if len(fields) != 2:
                raise FormatError(path, f"expected 'timestamp filename', found {len(fields)} "
                                        "fields", line=number)
            try:
                stamp = float(fields[0])
            except ValueError:
                raise FormatError(path, f"bad timestamp {fields[0]!r}", line=number) from None
            if not np.isfinite(stamp):
                raise FormatError(path, "timestamp is not finite", line=number)
            stamps.append(stamp)
            names.append(fields[1])
    return np.asarray(stamps, dtype=np.float64), names


def read_groundtruth(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Return (timestamps (N,), poses (N,7) tx ty tz qx qy qz qw) of a TUM ground-truth file,
    sorted by time (parsing and its errors: :func:`estimation.io.read_tum_arrays`)."""
    from estimation.io import read_tum_arrays

    stamps, poses = read_tum_arrays(path)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], poses[order]


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt: float) -> np.ndarray:
    """Return (M, 2) index pairs (i into a, j into b): nearest timestamps within ``max_dt``.

    Each b is used at most once (the a closest to it wins), so pairs are one-to-one like
    TUM's ``associate.py``; pairs come sorted by a's timestamp.
    """
    stamps_a = np.asarray(stamps_a, dtype=np.float64)
    stamps_b = np.asarray(stamps_b, dtype=np.float64)
    if stamps_a.size == 0 or stamps_b.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    order_b = np.argsort(stamps_b, kind="stable")
    sorted_b = stamps_b[order_b]
    right = np.clip(np.searchsorted(sorted_b, stamps_a), 0, sorted_b.size - 1)
    left = np.clip(right - 1, 0, sorted_b.size - 1)
    take_left = np.abs(stamps_a - sorted_b[left]) <= np.abs(sorted_b[right] - stamps_a)
    nearest = np.where(take_left, left, right)
    dt = np.abs(sorted_b[nearest] - stamps_a)
    index_a = np.flatnonzero(dt <= max_dt)
    index_b = nearest[index_a]
    # one-to-one: for each b keep the closest a (lexsort: by b, then by dt)
    order = np.lexsort((dt[index_a], index_b))
    index_a, index_b = index_a[order], index_b[order]
    first = np.ones(index_b.size, dtype=bool)
    first[1:] = index_b[1:] != index_b[:-1]
    pairs = np.stack([index_a[first], order_b[index_b[first]]], axis=1)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: float,
                      max_gap: float) -> gtsam.Pose3 | None:
    """Return the pose at ``query``: slerp/lerp between the bracketing samples, else None.

    Outside the sampled interval, the nearest sample is used when it is within ``max_gap``
    seconds; a bracketing pair further apart than ``max_gap`` on both sides also gives None
    (the ground truth has a hole there).
    """
    if stamps.size == 0:
        return None
    right = int(np.searchsorted(stamps, query))
    if right == 0 or right == stamps.size:
        nearest = 0 if right == 0 else stamps.size - 1
        if abs(stamps[nearest] - query) > max_gap:
            return None
        return _pose_from_row(poses[nearest])
    left = right - 1
    t0, t1 = stamps[left], stamps[right]
    if min(query - t0, t1 - query) > max_gap:
        return None
    alpha = 0.0 if t1 == t0 else (query - t0) / (t1 - t0)
    pose0, pose1 = _pose_from_row(poses[left]), _pose_from_row(poses[right])
    rotation = pose0.rotation().slerp(alpha, pose1.rotation())
    translation = (1 - alpha) * poses[left, :3] + alpha * poses[right, :3]
    return gtsam.Pose3(rotation, translation)


def _pose_from_row(row: np.ndarray) -> gtsam.Pose3:
    tx, ty, tz, qx, qy, qz, qw = row
    return gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.array([tx, ty, tz]))


def first_image_size(paths) -> tuple[int, int] | None:
    """(width, height) of the first readable image among ``paths``, None if none is.

    Only the header is needed, but OpenCV has no header-only reader; these are the few
    first images of a sequence."""
    import cv2

    for path in paths:
        try:
            image = decode(path, _read_bytes(path), cv2.IMREAD_UNCHANGED)
        except ImageError:
            continue
        if image is not None and image.ndim >= 2:
            return int(image.shape[1]), int(image.shape[0])
    return None


def listed_image_size(seq_dir: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of the first colour image that ``seq_dir/rgb.txt`` lists (FormatError
    naming the list or the image when there is none)."""
    seq_dir = Path(seq_dir)
    _, names = read_timestamp_list(seq_dir / "rgb.txt")
    if not names:
        raise FormatError(seq_dir / "rgb.txt", "no images listed")
    size = first_image_size([seq_dir / names[0]])
    if size is None:
        raise FormatError(seq_dir / names[0], "cannot read the image")
    return size


def check_distortion(distortion) -> tuple[float, ...] | None:
    """The lens distortion as a tuple (OpenCV order k1, k2, p1, p2[, k3[, k4, k5, k6]]), None
    for none; PerceptionError when it is not 4, 5 or 8 finite numbers of plausible size."""
    if distortion is None:
        return None
    values = tuple(float(v) for v in distortion)
    if len(values) not in (4, 5, 8) or not all(np.isfinite(v) and abs(v) < 100 for v in values):
        raise PerceptionError(f"distortion must be 4, 5 or 8 finite coefficients (OpenCV: "
                              f"k1,k2,p1,p2[,k3[,k4,k5,k6]]), got {distortion!r}")
    return values if any(values) else None


class Undistorter:
    """Removes the lens distortion of RGB-D frames, keeping the pinhole camera matrix.

    Colour is resampled bilinearly; depth with the nearest neighbour, so that no depth is
    invented across an edge (an invalid 0 stays invalid). The depth image must be registered
    to the colour camera (TUM, OpenNI), so the colour camera's distortion applies to both.
    """

    def __init__(self, intr: CameraIntrinsics, distortion):
        import cv2

        self.distortion = check_distortion(distortion)
        self._maps = None
        if self.distortion is not None:
            self._maps = cv2.initUndistortRectifyMap(
                intr.K, np.array(self.distortion), None, intr.K, (intr.width, intr.height),
                cv2.CV_32FC1)

    def __call__(self, frame: RgbdFrame) -> RgbdFrame:
        if self._maps is None:
            return frame
        import cv2

        map_x, map_y = self._maps
        if frame.rgb.shape[:2] != map_x.shape or frame.depth_m.shape != map_x.shape:
            raise PerceptionError(f"frame {frame.index}: rgb {frame.rgb.shape[:2]} / depth "
                                  f"{frame.depth_m.shape} do not match the camera's "
                                  f"{map_x.shape} that the distortion maps were made for")
        rgb = cv2.remap(frame.rgb, map_x, map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT)
        depth = cv2.remap(frame.depth_m, map_x, map_y, cv2.INTER_NEAREST,
                          borderMode=cv2.BORDER_CONSTANT)
        return replace(frame, rgb=rgb, depth_m=depth)


class TumRgbdSequence:
    """The associated frames of a TUM-layout RGB-D folder, read lazily.

    Parameters
    ----------
    seq_dir : path
        Folder holding rgb.txt, depth.txt, optional groundtruth.txt and the images.
    intrinsics : CameraIntrinsics, optional
        Default: read ``seq_dir/camera.txt``; a FormatError names it when it is missing.
    max_dt : float
        Largest |t_rgb - t_depth| (s) for a colour/depth pair (nearest timestamps).
    gt_max_gap : float
        Ground-truth samples further than this (s) from the frame time give no pose (None).
    distortion : sequence of float, optional
        The colour camera's lens distortion (OpenCV order k1, k2, p1, p2[, k3]; TUM publishes
        them per sensor): frames are undistorted on reading (:class:`Undistorter`) and keep
        ``intrinsics`` as their pinhole camera.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    timestamps : np.ndarray
        (N,) colour timestamps of the associated frames.
    """

    def __init__(self, seq_dir: str | os.PathLike, intrinsics: CameraIntrinsics | None = None,
                 max_dt: float = 0.02, gt_max_gap: float = 0.1, distortion=None):
        self.seq_dir = Path(seq_dir)
        if not self.seq_dir.is_dir():
            raise FormatError(self.seq_dir, "sequence folder not found")
        self.intrinsics = (read_camera_file(self.seq_dir / CAMERA_FILE_NAME)
                           if intrinsics is None else intrinsics)
        rgb_stamps, rgb_names = read_timestamp_list(self.seq_dir / "rgb.txt")
        depth_stamps, depth_names = read_timestamp_list(self.seq_dir / "depth.txt")
        pairs = associate(rgb_stamps, depth_stamps, max_dt)
        self.timestamps = rgb_stamps[pairs[:, 0]]
        self._rgb_paths = [self.seq_dir / rgb_names[i] for i in pairs[:, 0]]
        self._depth_paths = [self.seq_dir / depth_names[j] for j in pairs[:, 1]]
        gt_path = self.seq_dir / "groundtruth.txt"
        if gt_path.is_file():
            gt_stamps, gt_poses = read_groundtruth(gt_path)
        else:
            gt_stamps, gt_poses = np.zeros(0), np.zeros((0, 7))
        self._gt = (gt_stamps, gt_poses)
        self.gt_max_gap = gt_max_gap
        self.distortion = check_distortion(distortion)
        self._undistort = None  # built on the first frame (needs OpenCV)

    def __len__(self) -> int:
        return len(self._rgb_paths)

    def groundtruth_at(self, stamp: float) -> gtsam.Pose3 | None:
        """The ground-truth pose at ``stamp`` (interpolated), None outside or without it."""
        return interpolate_poses(*self._gt, float(stamp), self.gt_max_gap)

    def groundtruth_arrays(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(timestamps (M,), T_world_camera (M, 4, 4)) of groundtruth.txt, None without it."""
        stamps, poses = self._gt
        if len(stamps) == 0:
            return None
        T = np.array([_pose_from_row(row).matrix() for row in poses])
        return stamps.copy(), T

    def first_image_size(self) -> tuple[int, int] | None:
        """(width, height) of the first readable colour image, None if none can be read."""
        return first_image_size(self._rgb_paths[:10])

    def __iter__(self) -> Iterator[RgbdFrame]:
        for index in range(len(self)):
            yield self[index]

    def __getitem__(self, index: int) -> RgbdFrame:
        """Return frame ``index``, reading both images (errors name the bad file)."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range (sequence has {len(self)})")
        index %= len(self)
        rgb_path, depth_path = self._rgb_paths[index], self._depth_paths[index]
        stamp = float(self.timestamps[index])
        frame = RgbdFrame(
            index=index, timestamp=stamp,
            rgb=read_rgb(rgb_path, self.intrinsics),
            depth_m=read_depth(depth_path, self.intrinsics),
            T_world_camera_gt=interpolate_poses(*self._gt, stamp, self.gt_max_gap),
            rgb_path=rgb_path, depth_path=depth_path)
        if self.distortion is None:
            return frame
        if self._undistort is None:
            self._undistort = Undistorter(self.intrinsics, self.distortion)
        return self._undistort(frame)


def read_rgb(path: str | os.PathLike, intr: CameraIntrinsics | None = None) -> np.ndarray:
    """Return the colour image at ``path`` as (H, W, 3) uint8 RGB (grey images are expanded)."""
    import cv2

    data = _read_bytes(path)
    image = decode(path, data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(path, "cannot decode the colour image (corrupt or not an image)")
    if image.dtype != np.uint8:
        raise ImageError(path, f"colour image must be 8-bit, found {image.dtype}")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    _check_size(path, image, intr)
    return image


def read_depth(path: str | os.PathLike, intr: CameraIntrinsics) -> np.ndarray:
    """Return the depth PNG at ``path`` as (H, W) float32 metres (value / depth_scale; 0 = none).

    Raises ImageError naming the file when it is unreadable, not single-channel uint16, or
    not ``intr.width`` x ``intr.height``.
    """
    import cv2

    data = _read_bytes(path)
    image = decode(path, data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(path, "cannot decode the depth image (corrupt or not an image)")
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ImageError(path, "depth image must be single-channel uint16, found "
                               f"{image.dtype} with shape {image.shape}")
    _check_size(path, image, intr)
    return image.astype(np.float32) / np.float32(intr.depth_scale)


def _read_bytes(path: str | os.PathLike) -> bytes:
    try:
        return read_input_bytes(path, max_bytes=MAX_IMAGE_FILE_BYTES)
    except FormatError as exc:
        raise ImageError(path, exc.reason) from None
    except FileNotFoundError:
        raise ImageError(path, "image file not found") from None
    except OSError as exc:
        raise ImageError(path, f"cannot read image: {exc.strerror}") from None


def _check_size(path, image: np.ndarray, intr: CameraIntrinsics | None) -> None:
    if intr is not None and image.shape[:2] != (intr.height, intr.width):
        raise ImageError(path, f"image is {image.shape[1]}x{image.shape[0]}, the camera file "
                               f"says {intr.width}x{intr.height}")


def encode_depth_png(depth_m: np.ndarray, depth_scale: float = 5000.0) -> bytes:
    """Return PNG bytes of a uint16 depth image (round(depth * scale); 0 for invalid/too far)."""
    import cv2

    depth = np.asarray(depth_m, dtype=np.float64)
    scaled = np.rint(np.where(np.isfinite(depth) & (depth > 0), depth, 0.0) * depth_scale)
    scaled[scaled > np.iinfo(np.uint16).max] = 0  # beyond the format's range: no measurement
    ok, buf = cv2.imencode(".png", scaled.astype(np.uint16))
    if not ok:
        raise PerceptionError("OpenCV could not encode the depth PNG")
    return buf.tobytes()


def encode_rgb_png(rgb: np.ndarray) -> bytes:
    """Return PNG bytes of an (H, W, 3) uint8 RGB image."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise PerceptionError("OpenCV could not encode the colour PNG")
    return buf.tobytes()


def backproject(depth_m: np.ndarray, intr: CameraIntrinsics, stride: int = 1) -> np.ndarray:
    """Return the (N, 3) float32 camera-frame points of every valid depth pixel.

    Pixel (u, v) with depth z maps to ((u - cx) z / fx, (v - cy) z / fy, z); pixels with
    z <= 0 or non-finite z are skipped. ``stride`` keeps every stride-th row and column.
    Points come in row-major pixel order.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise PerceptionError(f"depth must be a 2-D image, got shape {depth.shape}")
    if stride < 1:
        raise PerceptionError(f"stride must be >= 1, got {stride}")
    sub = depth[::stride, ::stride]
    rows, cols = np.nonzero(np.isfinite(sub) & (sub > 0))
    z = sub[rows, cols]
    u = (cols * stride).astype(np.float32)
    v = (rows * stride).astype(np.float32)
    x = (u - np.float32(intr.cx)) * z / np.float32(intr.fx)
    y = (v - np.float32(intr.cy)) * z / np.float32(intr.fy)
    return np.stack([x, y, z], axis=1).astype(np.float32, copy=False)


def voxel_filter(points: np.ndarray, voxel_size: float = 0.05) -> np.ndarray:
    """Return one point per occupied voxel: the input point nearest that voxel's centre.

    The paper's 5 cm grid filter keeps measured points. Open3D's ``voxel_down_sample``
    returns the centroid of each voxel's points (on a grid anchored at the cloud's minimum
    bound), which is not a measured point, hence this filter. Voxels are the cells
    ``floor(p / voxel_size)`` of a grid anchored at the origin; ties go to the earlier point.
    Output is (M, 3) float32 ordered by voxel key (x, then y, then z).
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PerceptionError(f"points must be (N, 3), got shape {points.shape}")
    if not voxel_size > 0:
        raise PerceptionError(f"voxel_size must be positive, got {voxel_size}")
    finite = np.all(np.isfinite(points), axis=1)
    points = points[finite].astype(np.float32, copy=False)
    if points.shape[0] == 0:
        return np.zeros((0, 3), dtype=np.float32)
    scaled = points.astype(np.float64) / voxel_size
    keys = np.floor(scaled)
    dist2 = np.sum((scaled - keys - 0.5) ** 2, axis=1)
    keys = keys.astype(np.int64)
    # sort by voxel key, then by distance to the centre: the first of each run wins
    order = np.lexsort((dist2, keys[:, 2], keys[:, 1], keys[:, 0]))
    sorted_keys = keys[order]
    first = np.ones(order.size, dtype=bool)
    first[1:] = np.any(sorted_keys[1:] != sorted_keys[:-1], axis=1)
    return points[order[first]]
