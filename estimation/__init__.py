"""estimation: the shared PoseGraph, estimators and consistency tools.

Public names are loaded on first use (PEP 562), so ``import estimation.errors`` -- which
every CLI module does -- pulls in neither GTSAM nor SciPy.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "PoseGraph": "pose_graph", "Node": "pose_graph", "Scan": "pose_graph",
    "FactorRecord": "pose_graph", "OptimizeResult": "pose_graph", "node_key": "pose_graph",
    "OctofactorError": "errors", "FormatError": "errors", "EstimationError": "errors",
    "nees": "covariance", "nis": "covariance", "chi2_bounds": "covariance",
    "check_consistency": "covariance", "ConsistencyCheck": "covariance",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'estimation' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
