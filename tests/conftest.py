"""Shared fixtures: the read-only shared data folder, seeded generators and the real RGB-D
rooms against their voxel maps."""
from __future__ import annotations

import os
import subprocess
import sys
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


def pytest_sessionstart(session):
    """Compile the numba kernels ahead of time when they are missing or stale (as ``make
    setup`` does), so that the tests run the compiled kernels and not only numba's JIT
    (tests/test_aot.py checks both give the same results). OCTOFACTOR_JIT=1 skips it."""
    if hasattr(session.config, "workerinput") or os.environ.get("OCTOFACTOR_JIT", "") not in (
            "", "0"):
        return
    done = subprocess.run([sys.executable, "-m", "estimation.aot", "build", "--if-stale"],
                          cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True, env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                              [str(REPO_ROOT), os.environ.get("PYTHONPATH", "")])))
    if done.returncode:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        pytest.exit(f"compiling the numba kernels ahead of time failed: {last} (needs gcc and "
                    "the Python headers; OCTOFACTOR_JIT=1 runs the tests on numba's JIT alone)",
                    returncode=1)


@pytest.fixture(params=["compiled", "jit"])
def kernel_backend(request):
    """Run a test on the kernels compiled ahead of time, then on numba's JIT alone."""
    from estimation.aot import kernels

    ks = kernels("mapping._kernels")
    if request.param == "compiled" and ks.compiled is None:
        if os.environ.get("OCTOFACTOR_JIT", "") not in ("", "0"):
            pytest.skip("OCTOFACTOR_JIT=1: the compiled kernels are switched off")
        pytest.fail("mapping._kernels has no current compiled module "
                    "(python -m estimation.aot build)")
    ks.jit_only = request.param == "jit"
    before = ks.jit_calls
    yield request.param
    ks.jit_only = False
    # every kernel call of a "compiled" run found its signature in the compiled module
    assert ks.jit_calls == before, "a kernel call fell back to the JIT: add its signature " \
        "(OCTOFACTOR_AOT_RECORD=1, docs/octree.md, Start-up)"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the read-only shared data (octomap/, yud_train/)."""
    return _shared_data_dir()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def centroid_room():
    """Return ``get(name, step, start=0, stop=None)``: (points, labels, the 3 cm voxel-centroid
    map) of a real RGB-D room as benchmarks/registration_indoor.py fuses it (from frames
    ``start`` .. ``stop`` - 1), built once per session (each takes seconds; several test
    modules register against the same rooms)."""
    from benchmarks.registration_indoor import labelled, room_cloud, voxel_map

    rooms = {}

    def get(name: str, step: int, start: int = 0, stop: int | None = None):
        key = name, step, start, stop  # (frames start .. stop - 1; stop None: the last)
        if key not in rooms:
            points, labels = room_cloud(name, step=step, start=start, stop=stop)
            rooms[key] = (points, labels, labelled(*voxel_map(points, labels, "centroids")))
        return rooms[key]

    return get


@pytest.fixture
def strided_coarse_subset(monkeypatch):
    """The evenly strided coarse subset (``gicp.NORMAL_SPACE_SAMPLING`` False), for tests that
    use particular starts of the rooms as examples of a later stage's case (a wrong basin, a
    slow slide): the strided subset took those starts there, and half of the subset over the
    normals' directions changes which starts those are (test_registration_coarse_sampling.py;
    docs/registration_notes.md, "Normal-space sampling of the coarse subset")."""
    from estimation.registration import gicp

    monkeypatch.setattr(gicp, "NORMAL_SPACE_SAMPLING", False)
