"""Convenience entry points: GICP-SE(3) and Semantic-ICP on arrays.

Semantic-ICP (Parkison et al., BMVC 2018; eq. (5)-(8) of Nakamura et al.) is the GICP-SE(3)
engine of :mod:`.gicp` with class-conditioned correspondences and EM weights omega_k:
``semantic_weight="inside"`` minimises sum rho(omega_k e_k) (eq. (7) as printed),
``"outside"`` minimises sum omega_k rho(e_k) (Parkison's implementation; the default,
because the label weight then scales a correspondence's influence without changing where the
Cauchy kernel saturates).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config import RegistrationConfig
from .gicp import Registration
from .result import RegistrationResult


def gicp_se3(source: np.ndarray, target: np.ndarray, init=None,
             config: RegistrationConfig | None = None) -> RegistrationResult:
    """Return the GICP-SE(3) estimate of T_target_source (eq. (3))."""
    return Registration(source, target, config).run(init)


def semantic_icp(source: np.ndarray, source_probs: np.ndarray, target: np.ndarray,
                 target_probs: np.ndarray, init=None,
                 config: RegistrationConfig | None = None,
                 semantic_weight: str | None = None) -> RegistrationResult:
    """Return the Semantic-ICP estimate of T_target_source (eq. (5)-(8))."""
    config = config or RegistrationConfig()
    if semantic_weight is not None:
        config = replace(config, semantic_weight=semantic_weight)
    return Registration(source, target, config, source_probs, target_probs).run(init)
