"""Estimator plug-ins: the protocols a pipeline accepts, and the registry that finds them.

Two kinds of estimator plug in:

* ``"filter"`` -- a recursive filter stepping on measurements (:class:`RecursiveFilter`);
* ``"registration"`` -- a pair registration of two point clouds (:class:`PairRegistration`).

Built-ins register themselves on first use; third-party packages add estimators through
the entry-point group ``octofactor.estimators``, whose entries name a zero-argument
factory (a class or function) returning an estimator::

    [project.entry-points."octofactor.estimators"]
    my_filter = "my_package.module:MyFilter"

Every estimator also provides ``simulate(rng)`` -- a scenario of its own with ground truth
-- so one shared contract suite (``tests/test_plugin_contract.py``) can check every
registered estimator, consistency (NEES) included.
"""
from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any, Protocol, runtime_checkable

import numpy as np

ENTRY_POINT_GROUP = "octofactor.estimators"
KINDS = ("filter", "registration")


class PluginWarning(UserWarning):
    """A plug-in could not be loaded or does not satisfy its protocol; it was skipped."""


# ---------------------------------------------------------------- scenarios
@dataclass(frozen=True)
class FilterScenario:
    """Simulated inputs and ground truth for a recursive filter.

    ``controls[k]`` (with covariance ``control_covs[k]``) drives the prediction from step
    k to k+1; ``measurements[k]`` is ``None`` when step k+1 has no measurement.
    ``truths[k]`` is the true state after step k+1.
    """

    x0: np.ndarray
    P0: np.ndarray
    controls: list[np.ndarray]
    control_covs: list[np.ndarray]
    measurements: list[np.ndarray | None]
    measurement_covs: list[np.ndarray | None]
    truths: list[np.ndarray]
    truth0: np.ndarray


@dataclass(frozen=True)
class RegistrationScenario:
    """Two clouds related by a known ``T_target_source`` and an initial guess."""

    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray
    T_init: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------- protocols
@runtime_checkable
class RecursiveFilter(Protocol):
    """A recursive estimator: ``reset``, then ``predict``/``update`` per step.

    Attributes
    ----------
    name : str
    kind : str -- ``"filter"``
    x : (n,) current state estimate
    P : (n, n) its covariance
    """

    name: str
    kind: str

    @property
    def x(self) -> np.ndarray: ...

    @property
    def P(self) -> np.ndarray: ...

    def reset(self, x0: np.ndarray, P0: np.ndarray) -> None: ...

    def predict(self, u: np.ndarray, cov_u: np.ndarray) -> None: ...

    def update(self, z: np.ndarray, R: np.ndarray) -> bool:
        """Fuse measurement ``z``; return False when it was gated out."""
        ...

    def error(self, x_true: np.ndarray) -> np.ndarray:
        """The state error ``x_true - x`` (angles wrapped) in the order of ``P``."""
        ...

    def simulate(self, rng: np.random.Generator, n_steps: int = 30) -> FilterScenario: ...


@runtime_checkable
class PairRegistration(Protocol):
    """Registration of a source cloud to a target cloud.

    ``register`` returns an object with ``T`` (4x4 ``T_target_source``), ``covariance``
    (6x6, [rotation, translation]) and ``converged``.
    """

    name: str
    kind: str

    def register(self, source: np.ndarray, target: np.ndarray, T_init: np.ndarray,
                 **options: Any) -> Any: ...

    def simulate(self, rng: np.random.Generator) -> RegistrationScenario: ...


PROTOCOLS = {"filter": RecursiveFilter, "registration": PairRegistration}
_MEMBERS = {
    "filter": ("name", "kind", "x", "P", "reset", "predict", "update", "error", "simulate"),
    "registration": ("name", "kind", "register", "simulate"),
}


# ---------------------------------------------------------------- registry
@dataclass(frozen=True)
class EstimatorInfo:
    """One registered estimator: ``factory()`` builds a fresh instance."""

    name: str
    kind: str
    factory: Callable[[], Any]
    source: str  # "builtin" or the distribution that provides the entry point


_BUILTINS = {
    # name -> "module:attribute" of a zero-argument factory (imported on first use)
    "vp_ekf": ("filter", "estimation.builtin_estimators:VPEKFEstimator"),
    "gicp": ("registration", "estimation.builtin_estimators:GICPRegistration"),
    "semantic_icp": ("registration", "estimation.builtin_estimators:SemanticICPRegistration"),
}


def _import_object(spec: str) -> Any:
    module_name, _, attribute = spec.partition(":")
    obj = importlib.import_module(module_name)
    for part in attribute.split("."):
        obj = getattr(obj, part)
    return obj


def validate(estimator: Any, expected_kind: str | None = None) -> None:
    """Raise ``TypeError`` unless ``estimator`` satisfies the protocol of its kind."""
    kind = getattr(estimator, "kind", None)
    if kind not in PROTOCOLS:
        raise TypeError(f"kind must be one of {KINDS}, got {kind!r}")
    if expected_kind is not None and kind != expected_kind:
        raise TypeError(f"registered as {expected_kind!r} but its kind is {kind!r}")
    if not isinstance(getattr(estimator, "name", None), str):
        raise TypeError("has no string attribute 'name'")
    protocol = PROTOCOLS[kind]
    missing = [name for name in _MEMBERS[kind] if not hasattr(estimator, name)]
    if missing or not isinstance(estimator, protocol):
        raise TypeError(f"does not implement {protocol.__name__}: missing {missing}")


def _load(name: str, kind: str, factory: Callable[[], Any], source: str) -> EstimatorInfo | None:
    try:
        validate(factory(), kind)
    except Exception as exc:  # a broken plug-in must not break octofactor
        warnings.warn(f"octofactor estimator {name!r} from {source} skipped: {exc}",
                      PluginWarning, stacklevel=3)
        return None
    return EstimatorInfo(name, kind, factory, source)


def available_estimators(kind: str | None = None) -> dict[str, EstimatorInfo]:
    """Every usable estimator (built-ins, then entry points), validated, by name.

    A plug-in that fails to import, to build or to satisfy its protocol is skipped with a
    :class:`PluginWarning` naming it and the reason.
    """
    found: dict[str, EstimatorInfo] = {}
    for name, (builtin_kind, spec) in _BUILTINS.items():
        try:
            factory = _import_object(spec)
        except (ImportError, AttributeError) as exc:
            warnings.warn(f"built-in estimator {name!r} unavailable: {exc}", PluginWarning,
                          stacklevel=2)
            continue
        info = _load(name, builtin_kind, factory, "builtin")
        if info is not None:
            found[name] = info
    for entry in entry_points(group=ENTRY_POINT_GROUP):
        source = entry.dist.name if entry.dist is not None else entry.value
        if entry.name in found:
            warnings.warn(f"octofactor estimator {entry.name!r} from {source} skipped: "
                          "the name is taken", PluginWarning, stacklevel=2)
            continue
        try:
            factory = entry.load()
        except Exception as exc:
            warnings.warn(f"octofactor estimator {entry.name!r} from {source} skipped: "
                          f"cannot import {entry.value}: {exc}", PluginWarning, stacklevel=2)
            continue
        declared_kind = getattr(factory, "kind", None)
        info = _load(entry.name, declared_kind if declared_kind in KINDS else "filter", factory,
                     source)
        if info is not None:
            found[entry.name] = info
    if kind is not None:
        found = {name: info for name, info in found.items() if info.kind == kind}
    return found


def create_estimator(name: str, kind: str | None = None) -> Any:
    """A fresh instance of the estimator called ``name`` (optionally checking its kind)."""
    from .errors import OctofactorError

    estimators = available_estimators(kind)
    if name not in estimators:
        known = ", ".join(sorted(estimators)) or "none"
        what = f"{kind} estimator" if kind else "estimator"
        raise OctofactorError(f"unknown {what} {name!r}; installed: {known}")
    return estimators[name].factory()


def filter_nees(estimator: RecursiveFilter, scenario: FilterScenario,
                process_scale: float = 1.0) -> np.ndarray:
    """Run ``estimator`` over ``scenario``; return the NEES after each step.

    ``process_scale`` multiplies the control covariance given to the filter (0.05 makes
    the negative control of the contract suite). Raises ``AssertionError`` when the
    contract breaks: a non-finite state, or P not symmetric positive definite.
    """
    estimator.reset(scenario.x0, scenario.P0)
    values = []
    for u, cov_u, z, R, truth in zip(scenario.controls, scenario.control_covs,
                                     scenario.measurements, scenario.measurement_covs,
                                     scenario.truths):
        estimator.predict(u, np.asarray(cov_u) * process_scale)
        if z is not None:
            estimator.update(z, R)
        P = estimator.P
        if not np.all(np.isfinite(estimator.x)):
            raise AssertionError(f"{estimator.name}: non-finite state")
        if not np.allclose(P, P.T, atol=1e-9):
            raise AssertionError(f"{estimator.name}: P is not symmetric")
        np.linalg.cholesky(P)  # raises LinAlgError when P is not positive definite
        error = estimator.error(truth)
        values.append(float(error @ np.linalg.solve(P, error)))
    return np.array(values)
