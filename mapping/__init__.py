"""mapping: an OctoMap-equivalent probabilistic octree.

Public names are imported lazily so that ``import mapping`` stays cheap (numba kernels are
compiled or loaded from cache only when a tree is first used).
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "OcTree": "mapping.octree",
    "Leaves": "mapping.octree",
    "SearchResult": "mapping.octree",
    "RayResult": "mapping.octree",
    "InsertStats": "mapping.octree",
    "OctreeError": "mapping.octree",
    "logodds": "mapping.octree",
    "probability": "mapping.octree",
    "read_tree": "mapping.io",
    "fuse": "mapping.fusion",
    "transform_points_octomap": "mapping.fusion",
    "SemanticOcTree": "mapping.semantic",
    "write_ply": "mapping.export",
    "save_height_slice": "mapping.export",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'mapping' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
