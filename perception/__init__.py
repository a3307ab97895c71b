"""perception: images, depth and clouds -> lines, vanishing points, clouds, odometry.

Public names load on first use (PEP 562): OpenCV and Open3D are imported only by the
modules that need them.
"""
from __future__ import annotations

from estimation.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "perception.vanishing_points": ("VanishingPoint", "VPResult", "SeedConfig",
                                    "ManhattanConfig", "detect_seed", "detect_manhattan",
                                    "manhattan_from_segments"),
    "perception.errors": ("PerceptionError", "ImageError"),
    "perception.lines": ("read_image",),
    "perception.rgbd": ("CameraIntrinsics", "RgbdFrame", "TumRgbdSequence", "read_camera_file",
                        "write_camera_file", "backproject", "voxel_filter"),
    "perception.odometry": ("rgbd_odometry", "OdometryResult", "OdometryConfig"),
})
