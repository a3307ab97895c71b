"""Point-cloud registration: GICP-SE(3) and Semantic-ICP as batched, Cauchy-robust GTSAM factors.

Takes arrays only (the dependency rule: no perception/ or mapping/ imports).
"""
from .config import RegistrationConfig
from .correspondences import (
    Correspondences,
    SemanticIndex,
    nearest_correspondences,
    point_covariances,
    semantic_correspondences,
    transform_points,
)
from .covariance_terms import UNCONSTRAINED_VARIANCE, covariance_from_information
from .factors import BatchedGicpFactor, cauchy_loss, cauchy_weight, gicp_terms, skew, whitening
from .gicp import Registration, register
from .metrics import PoseError, pose_error
from .result import CovarianceDiagnostic, RegistrationResult
from .semantic_icp import gicp_se3, semantic_icp
from .transform_file import read_transform, write_transform

__all__ = [
    "BatchedGicpFactor", "Correspondences", "CovarianceDiagnostic", "PoseError", "Registration",
    "RegistrationConfig", "RegistrationResult", "SemanticIndex", "UNCONSTRAINED_VARIANCE",
    "cauchy_loss", "cauchy_weight", "covariance_from_information", "gicp_se3", "gicp_terms",
    "nearest_correspondences", "point_covariances", "pose_error", "register", "semantic_icp",
    "semantic_correspondences", "skew", "transform_points", "whitening", "read_transform",
    "write_transform",
]
