"""Plug-ins: discovery through entry points, validation, and one contract for every estimator.

The example package in tests/plugins/ is pip-installed into a temporary folder (the venv is
left untouched) and found through its ``octofactor.estimators`` entry point.
"""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from estimation.covariance import check_consistency
from estimation.plugins import (
    PluginWarning,
    available_estimators,
    create_estimator,
    filter_nees,
    validate,
)

EXAMPLE = Path(__file__).parent / "plugins" / "octofactor_example_filter"


@pytest.fixture(scope="session")
def example_plugin_path(tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("plugin_site")
    result = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
         str(EXAMPLE)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    sys.path.insert(0, str(target))
    importlib.invalidate_caches()
    yield target
    sys.path.remove(str(target))
    importlib.invalidate_caches()


def _discover() -> tuple[dict, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PluginWarning)
        found = available_estimators()
    return found, [str(w.message) for w in caught if issubclass(w.category, PluginWarning)]


def test_entry_point_plugin_is_discovered_and_broken_one_skipped(example_plugin_path):
    found, messages = _discover()
    assert "example_cv_filter" in found
    assert found["example_cv_filter"].source == "octofactor-example-filter"
    assert "example_broken" not in found
    broken = [m for m in messages if "example_broken" in m]
    assert broken and "missing" in broken[0] and "predict" in broken[0]


def test_plugins_command_lists_the_plugin(example_plugin_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(example_plugin_path),
                                                       os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run([sys.executable, "-m", "pipelines", "plugins"], capture_output=True,
                            text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "example_cv_filter" in result.stdout
    assert "example_broken" in result.stderr and "skipped" in result.stderr


def test_validate_rejects_wrong_kinds():
    class NoKind:
        name = "x"

    with pytest.raises(TypeError, match="kind"):
        validate(NoKind())


def test_unknown_estimator_is_a_clear_error():
    from estimation.errors import OctofactorError

    with pytest.raises(OctofactorError, match="unknown filter estimator 'nope'"):
        create_estimator("nope", kind="filter")


def _filter_names() -> list[str]:
    names = ["example_cv_filter"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        names += [n for n, i in available_estimators("filter").items() if n not in names]
    return names


def _registration_names() -> list[str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sorted(available_estimators("registration"))


def _filter_nees(name: str, process_scale: float) -> tuple[np.ndarray, int]:
    simulator = create_estimator(name, kind="filter")
    runs = np.array([filter_nees(create_estimator(name, kind="filter"),
                                 simulator.simulate(np.random.default_rng(seed), 30),
                                 process_scale)
                     for seed in range(100)])
    return runs, len(simulator.simulate(np.random.default_rng(0), 2).x0)


@pytest.mark.parametrize("name", _filter_names())
def test_filter_contract_and_consistency(example_plugin_path, name):
    """NEES over 100 seeded runs of the estimator's own scenario, per step, inside the 95 %
    chi-square band on >= 80 % of the steps (steps of one run are correlated)."""
    runs, dim = _filter_nees(name, 1.0)
    check = check_consistency(runs, dof=dim, min_fraction=0.8)
    assert check.passed, check


@pytest.mark.parametrize("name", _filter_names())
def test_filter_contract_negative_control_fails(example_plugin_path, name):
    """The same check with the process noise given to the filter scaled by 0.05 must fail."""
    runs, dim = _filter_nees(name, 0.05)
    check = check_consistency(runs, dof=dim, min_fraction=0.8)
    assert not check.passed, check


@pytest.mark.parametrize("name", _registration_names())
def test_registration_contract(name):
    estimator = create_estimator(name, kind="registration")
    scenario = estimator.simulate(np.random.default_rng(0))
    result = estimator.register(scenario.source, scenario.target, scenario.T_init,
                                **scenario.extra)
    assert result.converged
    T = np.asarray(result.T)
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    cov = np.asarray(result.covariance)
    assert cov.shape == (6, 6)
    np.linalg.cholesky(0.5 * (cov + cov.T))
    import gtsam

    error = gtsam.Pose3(T).localCoordinates(gtsam.Pose3(scenario.T_target_source))
    assert np.linalg.norm(error) < 0.05


def test_plugin_warnings_are_one_clean_line_in_every_command(example_plugin_path, tmp_path):
    """Outside `octofactor plugins` too (here: register --estimator), a skipped plug-in is one
    line 'octofactor: warning: ...', not a raw Python warning with file and source line."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(example_plugin_path),
                                                       os.environ.get("PYTHONPATH", "")]))
    cloud = "".join(f"{x} {y} {z}\n" for x in range(3) for y in range(3) for z in range(2))
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 18\nproperty float "
                                    "x\nproperty float y\nproperty float z\nend_header\n" + cloud)
    result = subprocess.run([sys.executable, "-m", "pipelines", "register", "a.ply", "a.ply",
                             "--method", "gicp", "--estimator", "no_such_estimator",
                             "-o", str(tmp_path / "r.json")], cwd=tmp_path,
                            capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    warning = [line for line in lines if "example_broken" in line]
    assert len(warning) == 1 and warning[0].startswith("octofactor: warning: "), lines
    assert "PluginWarning" not in result.stderr and "warnings.warn" not in result.stderr


def test_a_plugin_result_without_iterations_prints_no_none():
    from pipelines.register_cmd import _summary

    out = {"method": "my_icp", "converged": True, "reason": "", "iterations": None,
           "inliers": None, "time_s": 0.5}
    assert _summary(out) == "my_icp: converged=True, 0.500 s"
    out.update(iterations=7, inliers=100, reason="converged")
    assert _summary(out) == "my_icp: converged=True (converged), 7 iterations, 100 inliers, 0.500 s"
