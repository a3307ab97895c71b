"""estimation: the shared PoseGraph, estimators and consistency tools.

Public names are loaded on first use (PEP 562), so ``import estimation.errors`` -- which
every CLI module does -- pulls in neither GTSAM nor SciPy.
"""
from __future__ import annotations

from .lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "estimation.pose_graph": ("PoseGraph", "Node", "Scan", "FactorRecord", "OptimizeResult",
                              "node_key"),
    "estimation.errors": ("OctofactorError", "FormatError", "EstimationError"),
    "estimation.covariance": ("nees", "nis", "chi2_bounds", "check_consistency",
                              "ConsistencyCheck"),
})
