"""mapping: an OctoMap-equivalent probabilistic octree.

Public names are imported lazily so that ``import mapping`` stays cheap (numba kernels are
compiled or loaded from cache only when a tree is first used).
"""
from __future__ import annotations

from estimation.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "mapping.octree": ("OcTree", "Leaves", "SearchResult", "RayResult", "InsertStats",
                       "OctreeError", "logodds", "probability"),
    "mapping.io": ("read_tree",),
    "mapping.fusion": ("fuse", "transform_points_octomap"),
    "mapping.semantic": ("SemanticOcTree",),
    "mapping.export": ("write_ply", "save_height_slice"),
})
