"""estimation: the shared PoseGraph, estimators and consistency tools.

Importing this package pulls in GTSAM only; registration and the VP-EKF are imported
from their modules on first use.
"""
from .covariance import ConsistencyCheck, check_consistency, chi2_bounds, nees, nis
from .errors import EstimationError, FormatError, OctofactorError
from .pose_graph import FactorRecord, Node, OptimizeResult, PoseGraph, Scan, node_key

__all__ = [
    "PoseGraph", "Node", "Scan", "FactorRecord", "OptimizeResult", "node_key",
    "OctofactorError", "FormatError", "EstimationError",
    "nees", "nis", "chi2_bounds", "check_consistency", "ConsistencyCheck",
]
