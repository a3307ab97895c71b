"""perception: images, depth and clouds -> lines, vanishing points, clouds, odometry.

Public names load on first use (PEP 562): OpenCV and Open3D are imported only by the
modules that need them.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "VanishingPoint": "vanishing_points", "VPResult": "vanishing_points",
    "SeedConfig": "vanishing_points", "ManhattanConfig": "vanishing_points",
    "detect_seed": "vanishing_points", "detect_manhattan": "vanishing_points",
    "manhattan_from_segments": "vanishing_points",
    "PerceptionError": "errors", "ImageError": "errors",
    "read_image": "lines",
    "CameraIntrinsics": "rgbd", "RgbdFrame": "rgbd", "TumRgbdSequence": "rgbd",
    "read_camera_file": "rgbd", "write_camera_file": "rgbd", "backproject": "rgbd",
    "voxel_filter": "rgbd",
    "rgbd_odometry": "odometry", "OdometryResult": "odometry", "OdometryConfig": "odometry",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'perception' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
