"""Shared fixtures: the read-only shared data folder and seeded generators."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shared_data_dir() -> Path:
    env = os.environ.get("OCTOFACTOR_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates += [REPO_ROOT.parent / "shared" / "data", Path("/work/shared/data")]
    for candidate in candidates:
        if (candidate / "octomap").is_dir():
            return candidate
    raise RuntimeError(
        "shared data not found: expected ../shared/data beside the repository "
        "(or set OCTOFACTOR_SHARED_DATA)")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the read-only shared data (octomap/, yud_train/)."""
    return _shared_data_dir()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
