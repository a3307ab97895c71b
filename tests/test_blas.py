"""BLAS's threads while a registration runs: half the cores, the earlier limits after.

OpenBLAS's idle workers spin after a product and took the registration's second core, and
they went on spinning after it returned (estimation/blas.py). Timing is a benchmark's business
(benchmarks/registration_indoor.py); these tests check that the limit is in place, where,
and that it is undone."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from test_registration import make_pair
from threadpoolctl import threadpool_info

from estimation.blas import blas_threads, find_libraries
from estimation.registration import Registration, RegistrationConfig, gicp


def _blas_threads() -> list[int]:
    """The threads of the BLAS libraries a registration limits: those loaded when the
    registration module was imported, numpy's and scipy's among them. (OpenCV or Open3D may
    bring another OpenBLAS later, which a registration does not call.)"""
    return [lib["num_threads"] for lib in find_libraries().info() if lib["user_api"] == "blas"]


def test_the_limited_libraries_are_numpys_and_scipys():
    import scipy.linalg  # noqa: F401  (scipy's BLAS, loaded)

    theirs = {lib["filepath"] for lib in threadpool_info() if lib["user_api"] == "blas"
              and any(name in lib["filepath"] for name in ("numpy", "scipy"))}
    assert theirs <= {lib["filepath"] for lib in find_libraries().info()}


def _threads_inside_run(monkeypatch) -> tuple[list[int], list[int], list[int]]:
    """(BLAS threads before, inside _run, after) of one registration."""
    seen = []
    inner = Registration._run

    def spy(self, init):
        seen.append(_blas_threads())
        return inner(self, init)

    monkeypatch.setattr(Registration, "_run", spy)
    source, _, target, _, T_gt = make_pair(3, n=800)
    before = _blas_threads()
    result = Registration(source, target, RegistrationConfig()).run(T_gt)
    assert result.converged
    return before, seen[0], _blas_threads()


def test_a_registration_runs_with_half_the_cores_for_blas_and_restores_them(monkeypatch):
    monkeypatch.delenv("OCTOFACTOR_BLAS_THREADS", raising=False)
    before, inside, after = _threads_inside_run(monkeypatch)
    assert before, "no BLAS library found: numpy brings one"
    half = gicp.threads_beside()
    assert all(n <= half for n in inside)
    assert after == before  # the user's limits back


def test_keep_leaves_blas_alone(monkeypatch):
    monkeypatch.setenv("OCTOFACTOR_BLAS_THREADS", "keep")
    before, inside, after = _threads_inside_run(monkeypatch)
    assert inside == before == after


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: BLAS has one thread anyway")
def test_the_limit_holds_until_the_last_context_leaves_in_any_order(monkeypatch):
    monkeypatch.delenv("OCTOFACTOR_BLAS_THREADS", raising=False)
    earlier = _blas_threads()
    first, second = blas_threads(0), blas_threads(1)  # (0: at least one)
    first.__enter__()
    assert all(n == 1 for n in _blas_threads())
    a = np.ones((300, 300))
    assert float((a @ a)[0, 0]) == 300.0  # (a product still runs, on one thread)
    second.__enter__()
    # two registrations in two threads: the first to start leaves first
    first.__exit__(None, None, None)
    assert all(n == 1 for n in _blas_threads())  # the other still runs
    second.__exit__(None, None, None)
    assert _blas_threads() == earlier


def test_registrations_in_two_threads_leave_the_limits_as_they_were(monkeypatch):
    monkeypatch.delenv("OCTOFACTOR_BLAS_THREADS", raising=False)
    earlier = _blas_threads()
    pairs = [make_pair(seed, n=800) for seed in (4, 5)]
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(
            lambda p: Registration(p[0], p[2], RegistrationConfig()).run(p[4]), pairs))
    assert all(r.converged for r in results)
    assert _blas_threads() == earlier
