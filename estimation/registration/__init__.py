"""Point-cloud registration: GICP-SE(3) and Semantic-ICP as batched, Cauchy-robust GTSAM factors.

Takes arrays only (the dependency rule: no perception/ or mapping/ imports).
"""
from .correspondences import (
    Correspondences,
    SemanticIndex,
    nearest_correspondences,
    point_covariances,
    semantic_correspondences,
    transform_points,
)
from .factors import BatchedGicpFactor, cauchy_loss, cauchy_weight, gicp_terms, skew, whitening
from .gicp import (
    UNCONSTRAINED_VARIANCE,
    Registration,
    RegistrationConfig,
    RegistrationResult,
    covariance_from_information,
    register,
)
from .metrics import PoseError, pose_error
from .semantic_icp import gicp_se3, semantic_icp
from .transform_file import read_transform, write_transform

__all__ = [
    "BatchedGicpFactor", "Correspondences", "PoseError", "Registration", "RegistrationConfig",
    "RegistrationResult", "SemanticIndex", "UNCONSTRAINED_VARIANCE", "cauchy_loss",
    "cauchy_weight", "covariance_from_information", "gicp_se3", "gicp_terms",
    "nearest_correspondences", "point_covariances", "pose_error", "register", "semantic_icp",
    "semantic_correspondences", "skew", "transform_points", "whitening", "read_transform",
    "write_transform",
]
