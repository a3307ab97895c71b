"""GICP-SE(3) and Semantic-ICP registration: an outer correspondence/EM loop around GTSAM.

Eq. (3) of Nakamura et al. (after Parkison et al., BMVC 2018):
``T* = argmin_T sum_k rho_alpha(||x_t - T x_s||^2_{C_k})`` with the Cauchy
``rho_alpha(e) = alpha^2 log(1 + e / alpha^2)`` and ``C_k = Sigma_t + R Sigma_s R^T``.
Semantic-ICP (eq. (5)-(8)) adds the EM weight omega_k (see :mod:`.correspondences`).

Each outer iteration: correspondences (and omega_k) at ``T_old``; IRLS weights of the
Cauchy kernel at ``T_old``; one batched GTSAM factor solved by GTSAM's Gauss-Newton or
Levenberg-Marquardt optimiser; stop when ``||Logmap(T_old^-1 T)||`` is below tolerance
after the correspondence distance schedule has reached ``max_correspondence_distance``.
"""
from __future__ import annotations

import copy
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor  # (here, not in the first run: 3 ms)
from dataclasses import replace

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..blas import blas_threads, find_libraries_now
from ..errors import EstimationError
from ..heap import keep_freed_memory
from .config import RegistrationConfig
from .correspondences import (
    Correspondences,
    LazyCovariances,
    NeighbourCache,
    SemanticIndex,
    VoxelGrid,
    _workers,
    grid_cells,
    grid_sample,
    kd_tree,
    lattice_pitch,
    local_means,
    looks_voxelised,
    nearest_correspondences,
    neighbourhoods,
    queries_beside,
    semantic_correspondences,
    sheets_possible,
    threads_beside,
    top_class_order,
    transform_points,
    voxel_grid,
)
from .covariance_terms import (
    BLOCK_OFFSETS,
    BLOCK_OFFSETS_CENTRE,
    MIN_CROSSING_PAIRS,
    UNCONSTRAINED_VARIANCE,
    bread_within,
    cluster_sums,
    covariance_from_information,
    crossing_bias_rms,
    grid_phase_information,
    loewner_max,
    quantisation_information,
    systematic_covariance,
)
from .factors import (
    BatchedGicpFactor,
    cauchy_loss,
    cauchy_weight,
    gauss_newton_step,
    gicp_terms,
    mahalanobis,
    normal_equations,
    pooled_covariances,
    robust_factors,
    solution_sums,
    solve_weighted,
    tangential_squares,
    whitening_rows,
    whitening_rows_into,
)
from .result import CovarianceDiagnostic, RegistrationResult, SolutionTerms
from .sampling import covariance_normals, normal_space_rows

# the BLAS libraries run() limits (numpy's and scipy's, loaded by now), found at import: the
# 6.5 ms a process's first registration would otherwise pay (estimation/blas.py)
find_libraries_now()

# Cauchy tuning constant for 95 % asymptotic efficiency at Gaussian residuals (Holland and
# Welsch 1977), in units of the residuals' standard deviation
CAUCHY_TUNING = 2.3849
# Smallest residual-based alpha: keeps the weights finite on noise-free data
MIN_ADAPTIVE_ALPHA = 1e-3

# the smallest label noise RegistrationConfig.label_noise="auto" assumes
MIN_LABEL_NOISE = 1e-3
# Semantic-ICP's last annealing stage, once converged with the paper's scores (which pull a
# wide offset in by the labels), goes on with the posterior E-step until it converges again,
# before the final stage. The paper's scores let a wrong label pull towards the nearest surface
# of its class up to the stage's d_max away; on the ICL-NUIM office's raw halves (10 % wrong
# labels) that left the annealing 0.9-1.0 mm off along the room's weakly constrained axis, and
# the final stage's cost is too flat there to bring it back: mean error along it 0.92 ->
# 0.44 mm (GICP-SE(3) 0.44), mean NEES 43.8 -> 20.0 over four starts (docs/registration_notes.md,
# "Semantic-ICP's last annealing stage settles with the posterior", twenty-third round)
SETTLE_WITH_POSTERIOR = True
# The settle stops at a Gauss-Newton step shorter than this many standard deviations of the
# estimate (the step's chi = xi^T H xi / s^2, H the weighted normal matrix of the stage's
# rows, s^2 their mean whitened squared residual per axis), after its first step (the first
# posterior E-step starts from sigma = d_max): a shorter step is within the estimate's own
# noise. On the simulated room, 90 % right labels, the settle's steps are 0.2-5 (a walk of
# changing correspondences) and it ran 7-10 iterations to the tolerance; on the office's raw
# halves its steps are 13-330 (a drift along the weak axis) until it has settled (docs/
# registration.md, "The settle stops within the estimate's noise", thirty-second round).
# None: the tolerance only
SETTLE_WITHIN_SIGMA: float | None = 1.0




def _as_points(points: np.ndarray, what: str) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise EstimationError(f"{what} must be (N, 3), got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise EstimationError(f"{what} has NaN or inf coordinates")
    return points


def _as_transform(T: np.ndarray | gtsam.Pose3 | None) -> np.ndarray:
    if T is None:
        return np.eye(4)
    if isinstance(T, gtsam.Pose3):
        return T.matrix()
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise EstimationError(f"initial T must be a finite 4x4 matrix, got shape {T.shape}")
    return gtsam.Pose3(T).matrix()  # re-orthonormalises the rotation


def _creep_ratio(step: np.ndarray, last: np.ndarray | None,
                 cosine: float | None = None) -> float | None:
    """Return rho, the Gauss-Newton ``step``'s length (tangent vector) over the ``last``
    one's, where it points the way the last one did (the cosine of their angle at least
    ``cosine``, default EXTRAPOLATE_COSINE) and is shorter: ICP creeping along a line with
    geometrically shrinking steps (the correspondences lag the pose); None otherwise (or
    without a last step)."""
    if last is None:
        return None
    norm, norm_last = np.linalg.norm(step), np.linalg.norm(last)
    if norm == 0.0 or norm_last == 0.0:
        return None
    cosine = EXTRAPOLATE_COSINE if cosine is None else cosine
    if float(step @ last) / (norm * norm_last) < cosine or norm >= norm_last:
        return None
    return float(norm / norm_last)


def step_in_sigmas(xi: np.ndarray, H: np.ndarray, w: np.ndarray, e: np.ndarray) -> float:
    """Return the length of the Gauss-Newton step ``xi`` (tangent vector) in standard
    deviations of the estimate it came from: ``sqrt(xi^T H xi / s^2)``, with ``H`` the
    pairs' weighted normal matrix ``sum w J^T J`` (whitened), and ``s^2 = sum w e / (3 sum w)``
    their mean whitened squared residual ``e`` per axis (``s^2 H^-1``: the estimate's i.i.d.
    covariance)."""
    s2 = float(np.sum(w * e)) / (3.0 * max(float(np.sum(w)), 1e-300))
    return float(np.sqrt(max(float(xi @ H @ xi), 0.0) / max(s2, 1e-300)))


def _extrapolated(T_new: np.ndarray, step: np.ndarray, rho: float | None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (the pose to go on from, the step to remember) after the Gauss-Newton step
    ``step`` (tangent vector, Logmap of T^-1 T_new) to ``T_new`` of a creep with ratio
    ``rho`` (:func:`_creep_ratio`; None: no creep).

    What remains of the creep's geometric series, rho / (1 - rho) steps (at most
    EXTRAPOLATE_MAX), is added at once, as Besl and McKay's accelerated ICP (1992); the next
    step starts afresh (it measures the jump)."""
    if rho is None:
        return T_new, step
    factor = min(rho / (1.0 - rho), EXTRAPOLATE_MAX)
    return (gtsam.Pose3(T_new) * gtsam.Pose3.Expmap(factor * step)).matrix(), None


def _trusted(result: RegistrationResult) -> bool:
    """Whether ``result`` carries a covariance flagged trusted."""
    return result.diagnostic is not None and bool(result.diagnostic.trusted)


def _rows_of(cov: np.ndarray | LazyCovariances, rows: np.ndarray) -> np.ndarray:
    """The full (N, 3, 3) covariance array with ``rows`` available (computed if lazy)."""
    return cov.filled(rows) if isinstance(cov, LazyCovariances) else cov


_REVERSE_EXECUTOR = None


def _beside(fn, *args):
    """``fn(*args)`` with this thread's KD-tree queries on half the cores (the reverse
    direction, beside the forward's iterations: KITTI at 0.15 and 0.5 m and the scan split,
    2 % less time than with two threads a query on two cores)."""
    with queries_beside():
        return fn(*args)


class _Beside:
    """``fn(*args)`` started on the second thread; :meth:`result` runs it on the calling
    thread instead where that thread has not begun it (busy: the reverse direction), so
    nothing waits behind other work. For parts of a result that do not depend on each other
    (the same values on either thread)."""

    def __init__(self, fn, *args):
        self._call = fn, args
        self._future = _reverse_executor().submit(_beside, fn, *args)

    def result(self, *here):
        """The result; ``here``: other arguments for it where it runs on this thread (e.g. not
        the twin that the second thread's tasks share: :meth:`Registration._twin`)."""
        if self._future.cancel():
            fn, args = self._call
            return fn(*(here or args))
        return self._future.result()


# a partial overlap with a voxel-centroid map is matched by cell from convergence on
# (partial_voxel_matching) where the map's grid likely cut its surface layers into sheets
# (Registration._sheets_likely): at least this share of the nearest-neighbour pairs on
# surfaces within PARTIAL_CELL_ANGLE of a grid axis, their layers at least
# PARTIAL_CELL_THICKNESS pitches thick. The cells remove that aliasing, and the estimate loses
# the midpoint of the two directions, which takes out the matching's asymmetry. Measured at
# the nearest-neighbour fixed point (docs/registration_notes.md, "Partial overlaps matched by
# cell"): the parts of ICL-NUIM's office (a CAD room in its grid's axes) share 0.54-0.71 in
# the right basins, thickness 0.15-0.22, paired error 0.35x and mean NEES 503 -> 5.8 with the
# cells; the TUM room's 0.09-0.18 (at 10 deg 0.30-0.35: with the cells there, paired error
# 1.12x); the scan splits' 0.32-0.33 but layers 0.035-0.039 pitches thin (with the cells
# there, 6 of 30 splits: error 0.15-0.86 -> 0.36-1.30 mm)
PARTIAL_CELL_SHARE = 0.3
PARTIAL_CELL_ANGLE = 5.0  # degrees
PARTIAL_CELL_THICKNESS = 0.1  # pitches
# ... and before the map's grid is searched for (on the second thread), a loose necessary
# condition on the map's own sample of 600 points (correspondences.sheets_possible): a
# third of the share, 0.7 of the thickness (12 neighbours). Measured on the maps: the
# ICL-NUIM office's parts 0.17-0.38 and 0.15-0.20 pitch, the TUM room's 0.04-0.15 and
# 0.18-0.33, the scan splits' 0.34-0.42 and 0.028-0.033: their 20 ms search is skipped
PARTIAL_MAP_SHARE = 0.1
PARTIAL_MAP_THICKNESS = 0.07  # pitches
# the final stage and the reverse direction are prepared on the second thread
# (Registration._prepare_forward, _prepare_reverse) from the first iteration of the annealing
# stages, and of the final one, whose step (||Logmap||, rad and m) is below this: the pose then
# moves by about as much again before it converges, so the neighbour caches anchored there
# stay mostly valid and the rows matched there are nearly the ones matched at the end (KITTI
# at 0.15 m, 0.5 m / 5 deg off: 6 of 11 annealing iterations to go from there; at 0.5 m
# without annealing 6 of 11 final ones)
PREPARE_STEP = 1e-2
# ... the final stage's own preparation from the first annealing step below this instead: the
# final d_max's rows barely change with the pose, and the preparation of a 10-16k point
# KITTI cloud (8-neighbour queries and covariances on one thread, 30 ms) then has the time
# it needs; 3 % less time on KITTI 0.1/0.15 m and the scan than at 1e-2 (3e-1: mixed)
PREPARE_FORWARD_STEP = 1e-1
# ... and its neighbour cache only where the candidates' median reach exceeds this many times
# the last step's median point displacement (Registration._prepare). From there the points
# moved on by 7-50 mm on KITTI (steps of 26-100 mm, reach 70-300 mm: 97-100 % of the rows
# still valid) and by 20-250 mm in the rooms (steps of 15-100 mm, reach 11-25 mm: 0-7 %
# valid, the rest queried again); the rooms' 150k-point sources took 7-14 % less time without
# that cache, KITTI 3-8 % more
PREPARED_REACH = 0.5
# the final stage's creep along a straight line is extrapolated (_extrapolated; False: not).
# Inside a room's 3 cm map the final steps shrank by only 0.75-0.8 an iteration, 10-14 of them
# from 6-12 mm off; extrapolated, 5-6 (in-process A/B, 8 starts at 150k points: time / Open3D
# 0.62 -> 0.53 for GICP-SE(3), 0.86 -> 0.66 for Semantic-ICP, median error 0.97 -> 0.87 and
# 1.02 -> 0.98 mm; at 15k points 4-10 % less time; KITTI and the scan split: the same
# estimates, time within the noise)
EXTRAPOLATE = True
EXTRAPOLATE_COSINE = 0.99  # the two steps' directions agree within 8 deg
EXTRAPOLATE_MAX = 4.0  # at most four more steps at once
# a step below ``tolerance`` ends the final stage only where the creep last measured
# (_creep_ratio) leaves less than ``tolerance`` to go: the step's length along the creep's
# direction times rho / (1 - rho); otherwise the creep is extrapolated and the stage goes on
# (False: the step alone decides). A raw half of ICL-NUIM's office crept along its weakly
# held axis with rho 0.91-0.95 and stopped 1.1 mm short of its fixed point (twenty-fourth
# round, docs/registration_notes.md, "The creep's remainder")
CONVERGE_ON_REMAINDER = True
# the creep the remainder is measured on: two steps within about 26 deg (a Semantic-ICP
# creep's direction wobbles more than EXTRAPOLATE_COSINE allows, the posterior's weights
# moving with the pose)
CREEP_COSINE = 0.9
# the iterations match through a neighbour cache once the last step (||Logmap||) is below
# this, whatever the correspondence distance: before, most points move beyond their cached
# candidates' reach, and re-querying them costs more than a plain query (k = 8 neighbours:
# about 2.4x). KITTI at 0.5 m, 2 m / 20 deg off (25 annealing iterations on all 2.7k points):
# 86 -> 82 ms a registration; 0.5 m / 5 deg off without annealing (the first two steps 0.7,
# 0.2): 50 -> 48 ms
CACHE_STEP = 1e-1
# an annealed registration whose final stage has not converged after stage_iterations with
# the residual-based kernel takes the wide one (cauchy_alpha) until it converges, then the
# narrow one again (False: not; 3 of 20 dense starts on a real office then ran out of
# iterations 2-5 cm off)
WIDE_FINAL_STAGE = True
# Semantic-ICP's second start (RegistrationConfig.semantic_rescue) runs at most this many
# final-stage iterations (None: max_iterations). It replaces the first result only where it is
# trusted, and a result that has not converged is not. On the real office's 15k-point halves
# the rescued starts converged within 15 final iterations (5 of 40 starts, small and wide
# offsets), and the second starts that ran longer all ended untrusted, 5 of them after all
# 150 (0.95-1.5 m off; docs/registration_notes.md, "The second start's final stage")
RESCUE_FINAL_ITERATIONS = 60
# a start at the final d_max (no annealing: RegistrationConfig's defaults, the CLI without
# --initial-corr) of a source with a coarse subset (coarse_points) first aligns that subset
# at the final d_max, as an annealing stage would, then every point (the same fixed point:
# the final stage converges on all points; False: every point from the first iteration,
# each of whose first steps re-queries every point). Real room halves 5 cm / 2 deg off:
# 15k points 0.39-0.51 -> 0.26-0.35 s, raw halves 4.4-6.4 -> 2.3-2.8 s; docs/registration_notes.md,
# "A coarse first stage"
COARSE_FIRST = True
# ... and that stage ends after its first step where that step is below this (rad and m): a
# start already at the fixed point needs no coarse alignment (the start-up benchmark's 10k
# pair from its truth: 6 ms instead of 17 ms more than without the stage; ending it at any
# step below this instead cost the raw half rooms 20-30 % of the stage's gain)
COARSE_FIRST_STEP = 1e-2
# the re-matched bread (Registration.reassociation_hessian) of a source with more points is
# taken over this many evenly strided rows (150k-point room scans: 0.3-0.5 -> 0.1-0.2 s;
# the point-noise covariance 0.99-1.32x the full one's)
REASSOCIATION_ROWS = 30000
# the re-matched bread's eigenvalues relative to A are limited to [REASSOCIATION_FLOOR, 1]:
# at most 100x the fixed-association variance along a direction. 0.25 (16x) held the real
# rooms' flattest directions back (ICL-NUIM, 15k-point halves: 3 of 30 starts at 0.12-0.19,
# NEES 23-33; docs/registration_notes.md, "The re-matched bread's floor"); 0.1 and 0.05 gave the
# same NEES there, and the i.i.d. scenes never reach 0.25
REASSOCIATION_FLOOR = 0.1
# the symmetric estimate's uses of the breads keep the earlier floor: the reverse direction's
# Newton step (Registration.reverse_terms) and the direction gap's covariance
# (Registration._symmetric, both directions' breads). trust_gap was measured with it; with
# the covariance's floor there too, an ICL-NUIM part 0.59 m off had a gap of 32 instead of
# 42, under the threshold (tests/test_registration_partial_cells.py)
SYMMETRIC_BREAD_FLOOR = 0.25
# Semantic-ICP's class candidates are cached from smaller steps: during the annealing the
# coarse rows still move a centimetre or more an iteration and most of them (2000-2700 of
# 3000 on the ICL office) were re-queried with eight candidates each, dearer than one plain
# query. In-process A/B against 0.1 (bit-identical): ICL office 0.95x (4 classes), 1.00x (24),
# TUM room 0.99x (small offsets) and 0.98x (wide)
CLASS_CACHE_STEP = 1e-2
# pairs from which an iteration's whitening is split between the two threads
# (Registration._whitening)
SPLIT_PAIRS = 20000
# matched source rows whose covariances are computed on the second thread when at least this
# many are missing (Registration._prefetch_source); fewer are not worth a hand-over
PREFETCH_ROWS = 256


# the annealing stages' subset of a large source (RegistrationConfig.coarse_points): half of
# it evenly strided, half spread evenly over the directions of the surface normals
# (normal-space sampling, Rusinkiewicz and Levoy 2001) from NORMAL_SPACE_POOL times as many
# evenly strided rows (False: all of it evenly strided). An evenly strided subset is mostly a
# room's dominant surfaces, along which the coarse stage can slide into another basin (ICL-NUIM
# office, 15k-point halves from 0.2 m / 8 deg: 4 of 30 starts, which Open3D GICP missed too);
# a subset spread over the normals alone lost the dominant surfaces' pull that a wide start
# needs (simulated rooms from 1 m / 40 deg: 4 of 64 more starts missed). docs/registration_notes.md,
# "Normal-space sampling"
NORMAL_SPACE_SAMPLING = True
NORMAL_SPACE_POOL = 4
def _reverse_executor():
    """The second thread: the reverse direction of symmetric registrations, what is
    prepared beside the iterations (the source's tree, the final stage's caches and
    covariances, prefetched source covariances), and parts of the covariance beside the
    others (half of the re-matched bread's poses, a centroid map's model terms: _Beside)."""
    global _REVERSE_EXECUTOR
    if _REVERSE_EXECUTOR is None:
        _REVERSE_EXECUTOR = ThreadPoolExecutor(max_workers=1,
                                               thread_name_prefix="registration-reverse")
    return _REVERSE_EXECUTOR


class Registration:
    """Register a source cloud to a target cloud (GICP-SE(3) or Semantic-ICP).

    Per-point covariances and KD-trees are computed once and cached on the instance, so
    repeated calls (other initial guesses, Monte Carlo runs) reuse them.

    Parameters
    ----------
    source, target : (N, 3) points (source frame, target frame)
    config : :class:`RegistrationConfig`
    source_probs, target_probs : (N, C) class probabilities; both given -> Semantic-ICP
    source_cov, target_cov : optional precomputed (N, 3, 3) per-point covariances
    """

    def __init__(self, source: np.ndarray, target: np.ndarray,
                 config: RegistrationConfig | None = None,
                 source_probs: np.ndarray | None = None, target_probs: np.ndarray | None = None,
                 source_cov: np.ndarray | None = None, target_cov: np.ndarray | None = None):
        self.config = config or RegistrationConfig()
        self.source = _as_points(source, "source points")
        self.target = _as_points(target, "target points")
        self.semantic = source_probs is not None and target_probs is not None
        if (source_probs is None) != (target_probs is None):
            raise EstimationError("Semantic-ICP needs class probabilities for both clouds")
        if self.semantic:
            self.source_probs = self._probs(source_probs, len(self.source), "source")
            self.target_probs = self._probs(target_probs, len(self.target), "target")
            if self.source_probs.shape[1] != self.target_probs.shape[1]:
                raise EstimationError(
                    f"source has {self.source_probs.shape[1]} classes, "
                    f"target {self.target_probs.shape[1]}")
        self._source_cov = source_cov
        self._target_cov = target_cov
        self._tree: cKDTree | None = None
        self._source_tree: cKDTree | None = None
        self._index: SemanticIndex | None = None
        self._index_ready: Future | None = None  # the index being built (_prepare_index)
        # Semantic-ICP: the source's top classes and argmax labels (made at the first E-step)
        self._source_classes: tuple[np.ndarray, np.ndarray] | None = None
        self._block: float | None = None
        self._boundary_radius: float | None = None
        self._source_block: float | None = None
        self._source_radius_value: float | None = None
        self._cache: NeighbourCache | None = None
        self._surface_radius: float | str | None = "unset"
        self._lattice_cells = None  # (the lattice's cells for sawtooth_information)
        self._pitch: float | str | None = "unset"
        self._found_pitch: float | str | None = "unset"
        self._source_pos: np.ndarray | None = None
        self._target_lazy: LazyCovariances | None = None
        self._class_cache: dict = {}
        self._class_cache_owner: NeighbourCache | None = None
        self._sigma: float | None = None  # Semantic-ICP's EM residual sigma, reset by run()
        self._settled = False  # the last annealing stage runs the posterior E-step (run())
        # Semantic-ICP's annealing stages matched geometrically (run(): semantic_rescue)
        self._geometric_annealing = False
        # same_voxel's grid, decided per run(): 0 = not yet, 1 = at convergence
        self._grid: VoxelGrid | int | None = 0
        self._nearest = None
        self._partial_grid: Future | None = None
        # the first stages of the map's grid search (grid_sample), kept by _partial_cells_grid
        # for voxel_grid where the source turns out to lie inside the map
        self._target_sample = None
        self._aligned: np.ndarray | None = None  # per target row: normal along a grid axis
        self._alpha: float = self.config.cauchy_alpha  # the kernel's alpha in use (run())
        # neighbour caches of the final d_max prepared on the second thread (run()): this
        # direction's and the reverse's; set _stop to end the preparation early
        self._forward_cache: tuple[float, Future] | None = None
        self._reverse_cache: Future | None = None
        self._stop = threading.Event()
        # the source's KD-tree, lattice pitch and median radius made on the second thread
        # (_prepare_source); whether matched source rows' covariances are prefetched there
        self._source_ready: Future | None = None
        self._source_done: Future | None = None
        self._source_pitch: float | None | str = "unset"
        self._prefetching = True

    @staticmethod
    def _probs(probs: np.ndarray, n: int, what: str) -> np.ndarray:
        probs = np.asarray(probs, dtype=float)
        if probs.ndim != 2 or len(probs) != n:
            raise EstimationError(f"{what} probs must be ({n}, C), got {probs.shape}")
        return probs

    @property
    def method(self) -> str:
        return "semantic" if self.semantic else "gicp"

    @property
    def source_cov(self) -> np.ndarray | LazyCovariances:
        """Source covariances, indexable by row arrays."""
        if self._source_cov is None:
            # per row on first use, as the target's: only the matched rows are needed (the
            # scan splits overlap by less than half: 0.084 -> 0.078 s a registration), and
            # most are computed on the second thread (_prefetch_source, _prepare_forward);
            # with the local surface positions' radius, a row's local mean comes from the
            # same neighbour query (all rows at once on this thread took the simulated
            # room's Semantic-ICP at 10k 36 ms of 157, while the second core idled)
            self._source_cov = LazyCovariances(self.source, self.source_tree,
                                               self.config.k_neighbours, self.config.epsilon,
                                               self._means_radius,
                                               self.config.surface_min_points)
        return self._source_cov

    @property
    def source_tree(self) -> cKDTree:
        """KD-tree of the source (its covariances, its lattice test, the reverse's target)."""
        if self._source_tree is None:
            if self._source_ready is not None:
                self._source_tree = self._source_ready.result()
            else:
                self._source_tree = kd_tree(self.source)
        return self._source_tree

    def _prepare_source(self) -> None:
        """Make the source's KD-tree, then its lattice pitch and median radius, on the second
        thread while the first iteration matches against the target (all three are needed
        later in it: the lattice test, the overlap test, the covariances; the same values as
        made on this thread). KITTI at 0.5 m: 3 ms of a 21 ms first iteration."""
        if self._source_tree is not None or self._source_ready is not None:
            return
        tree_ready: Future = Future()

        def prepare() -> None:
            try:
                with queries_beside():
                    tree = kd_tree(self.source)
                    tree_ready.set_result(tree)
                    if self._source_pitch == "unset":
                        self._source_pitch = lattice_pitch(self.source, tree)
                    if self._source_radius_value is None:
                        self._source_radius_value = self._median_radius(self.source, tree)
            except BaseException as error:
                if not tree_ready.done():
                    tree_ready.set_exception(error)
                raise

        self._source_ready = tree_ready
        self._source_done = _reverse_executor().submit(prepare)

    def _source_prepared(self) -> None:
        """Wait for :meth:`_prepare_source`, if started and not waited for yet."""
        done, self._source_done = self._source_done, None
        if done is not None:
            done.result()

    @property
    def target_tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = kd_tree(self.target)
        return self._tree

    @property
    def target_cov(self) -> np.ndarray | LazyCovariances:
        """Target covariances, indexable by row arrays (computed on first use per row)."""
        if self._target_cov is None:
            self._target_cov = self._target_stats
        return self._target_cov

    def _dense_share(self, points: np.ndarray, radius: float) -> float:
        """Share of (sampled) points with ``surface_min_points`` neighbours within ``radius``."""
        sample = points[:: max(1, len(points) // 500)]
        tree = self.target_tree if points is self.target else kd_tree(points)
        counts = tree.query_ball_point(sample, radius * (1 + 1e-6), return_length=True)
        return float(np.mean(counts >= self.config.surface_min_points))

    @property
    def _target_stats(self) -> LazyCovariances:
        if self._target_lazy is None:
            self._target_lazy = LazyCovariances(
                self.target, self.target_tree, self.config.k_neighbours, self.config.epsilon,
                self._means_radius, self.config.surface_min_points)
        return self._target_lazy

    @property
    def _means_radius(self) -> float | None:
        # the lattice's corner voxels lie exactly at sqrt(3) pitches: a hair more includes them
        radius = self.surface_radius
        return None if radius is None else radius * (1 + 1e-6)

    def _averaged_lattice_points(self, target_idx: np.ndarray, pitch: float):
        """Return ``neighbourhood(rows)`` for :func:`sawtooth_information`: which cells of the
        3x3x3 block around each matched lattice point ``target_idx[rows]`` hold a map point,
        those whose mean is the pair's target position (the ``local_means`` rule on a lattice:
        the block lies within sqrt(3) pitches; the point alone below ``surface_min_points``),
        as a (R, 27) mask over :data:`BLOCK_OFFSETS`; None without local surface positions."""
        if self._means_radius is None:
            return None
        cells = self._lattice_grid(pitch)
        if cells is None:
            return None

        def neighbourhood(rows: np.ndarray) -> np.ndarray:
            centre = cells.cell_of(self.target[target_idx[rows]])
            occupied = cells.rows_of_cells(centre[:, None, :] + BLOCK_OFFSETS[None, :, :])[0]
            alone = occupied.sum(axis=1) < self.config.surface_min_points
            occupied[alone] = BLOCK_OFFSETS_CENTRE
            return occupied

        return neighbourhood

    def _lattice_grid(self, pitch: float) -> VoxelGrid | None:
        """The target lattice's cells, each voxel centre in the middle of its cell (built on
        first use; None where :func:`grid_cells` finds no grid)."""
        if self._lattice_cells is None:
            self._lattice_cells = grid_cells(self.target, pitch, self.target[0] - 0.5 * pitch)
        return self._lattice_cells

    def matched_points(self, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
        """Return the (source, target) positions the residuals of ``corr`` are measured between.

        The samples themselves, or with ``surface_radius`` their local surface positions
        (source: computed once with its covariances; target: lazily, for the rows that get
        matched, from the query of their covariances).
        """
        if self.surface_radius is None:
            return self.source[corr.source_idx], self.target[corr.target_idx]
        target = self._target_stats.means(corr.target_idx)
        lazy = self._source_means
        if lazy is not None:
            return lazy.means(corr.source_idx), target
        if self._source_pos is None:  # covariances were given: the means need a query
            self._source_pos = local_means(self.source, kd_tree(self.source),
                                           self._means_radius, self.config.surface_min_points)
        return self._source_pos[corr.source_idx], target

    def _matched_arrays(self, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
        """Return whole (source, target) position arrays whose rows ``corr.source_idx`` and
        ``corr.target_idx`` are :meth:`matched_points` (for the kernels that read by row)."""
        if self.surface_radius is None:
            return self.source, self.target
        _ = self.matched_points(corr)  # fills the source means and the target's rows
        lazy = self._source_means
        return (self._source_pos if lazy is None else lazy.mean_values,
                self._target_stats.mean_values)

    @property
    def _source_means(self) -> LazyCovariances | None:
        """The source's per-row covariances where they carry its local means (not given)."""
        cov = self.source_cov
        return cov if isinstance(cov, LazyCovariances) and cov.radius is not None else None

    @property
    def surface_radius(self) -> float | None:
        """The radius of the local surface positions in use (m), or None (the samples)."""
        if self._surface_radius == "unset":
            radius = self.config.surface_radius
            if radius == "auto":
                pitch = self._lattice
                radius = None if pitch is None else float(np.sqrt(3.0) * pitch)
                if radius is not None and not (self._dense_share(self.target, radius) >= 0.1
                                               or self._dense_share(self.source, radius) >= 0.1):
                    radius = None  # thin subsamples: (nearly) every mean would fall back
            self._surface_radius = radius
        return self._surface_radius

    @property
    def semantic_index(self) -> SemanticIndex:
        if self._index is None:
            ready, self._index_ready = self._index_ready, None
            self._index = (ready.result() if ready is not None
                           else SemanticIndex(self.target, self.target_probs))
        return self._index

    def _prepare_index(self) -> None:
        """Semantic-ICP: build the target's class trees (:class:`SemanticIndex`) on the second
        thread, after the source's tree (:meth:`_prepare_source`), while this thread
        computes the coarse rows' covariances; the first E-step waits for them (the same
        trees either way; every target point has a class, its most probable one). The
        scan's 34k-point map: 6.5 ms of this thread's work per registration."""
        if self.semantic and self._index is None and self._index_ready is None:
            self._index_ready = _reverse_executor().submit(SemanticIndex, self.target,
                                                           self.target_probs)

    def _failed(self, T: np.ndarray, reason: str, start: float, iterations: int = 0,
                cost_log=()) -> RegistrationResult:
        self._stop.set()  # what was being prepared is not needed
        cov = np.eye(6) * UNCONSTRAINED_VARIANCE
        return RegistrationResult(T, cov, np.zeros((6, 6)), iterations, 0, 0.0, float("nan"),
                                  False, reason, tuple(cost_log), self.method,
                                  time.perf_counter() - start, None, self._alpha)

    def correspondences(self, T: np.ndarray, d_max: float, rows: np.ndarray | None = None,
                        step: float | None = None, cells: bool = True) -> Correspondences:
        """Return the correspondences (with omega_k) at ``T`` within ``d_max``.

        ``cells`` False: no same-voxel matching, nor its decision (a coarse first stage's,
        whose start may be too far off to decide whether the source lies inside the map).

        ``rows`` restricts the source to those points (indices stay into the full source).
        The candidates come from a :class:`NeighbourCache` (the same pairs) once ``step``,
        the last Gauss-Newton step (run()), is below CACHE_STEP, Semantic-ICP's class
        candidates once it is below CLASS_CACHE_STEP; without ``step`` both once ``d_max``
        has annealed.
        """
        if step is None:
            cached = class_cached = d_max <= self.config.max_correspondence_distance
        else:
            cached, class_cached = step < CACHE_STEP, step < CLASS_CACHE_STEP
        cache = None
        if self.config.cached_neighbours and cached:
            # annealed: the source now moves little per iteration (see NeighbourCache)
            if self._cache is None or self._cache.d_max != d_max:
                self._cache = self._prepared_cache(d_max) or NeighbourCache(
                    self.target_tree, d_max, self.config.cached_neighbours, len(self.source))
            cache = self._cache
        final = d_max <= self.config.max_correspondence_distance * (1 + 1e-9)
        semantic = self.semantic and (final or not self._geometric_annealing)
        if rows is not None:
            moved = transform_points(T, self.source[rows])
            if semantic:
                corr = self._semantic(moved, self.source_probs[rows], d_max,
                                      cache, class_cached, rows)
            else:
                corr = nearest_correspondences(moved, self.target_tree, d_max, cache, rows)
            corr = replace(corr, source_idx=rows[corr.source_idx])
        else:
            moved = transform_points(T, self.source)
            if semantic:
                corr = self._semantic(moved, self.source_probs, d_max, cache, class_cached)
            else:
                corr = nearest_correspondences(moved, self.target_tree, d_max, cache)
        self._prefetch_source(corr.source_idx)
        corr = self._gated(T, d_max, corr)
        if cells and final:
            corr = self.same_voxel(T, corr)
        return corr

    def _prefetch_source(self, rows: np.ndarray) -> None:
        """Compute the missing source covariances of the matched ``rows`` on the second
        thread while this one gates the pairs and fills the target's (whitening needs both;
        rows still missing then are computed here, as always): where many are missing, i.e.
        the first iteration and the first at the final correspondence distance. (KITTI at
        0.5 m: 5 ms of a 21 ms first iteration.)"""
        if not self._prefetching:
            return
        cov = self.source_cov
        if not isinstance(cov, LazyCovariances):
            return
        missing = rows[~cov.done[rows]]
        if len(missing) >= PREFETCH_ROWS:
            _reverse_executor().submit(cov.prefetch, missing, 256, self._stop)

    def _voxel_grid_found(self, T: np.ndarray, d_max: float | None = None) -> bool:
        """Decide same-voxel matching at ``T`` if still undecided: True (and the grid kept)
        where the source lies inside the target, the target is no lattice and its grid is
        found; False otherwise, and for good once decided.

        ``d_max`` (at convergence, run()): where the source only overlaps the map in part, the
        cells are taken too (``partial_voxel_matching``) and the nearest-neighbour fixed point
        ``T`` is kept for the consistency diagnostic (:meth:`_keep_nearest_fixed_point`)."""
        if not isinstance(self._grid, int) or self.config.voxel_matching is None:
            return False
        self._grid = None
        if self._lattice is not None:
            return False
        partial = self._partial_grid
        if source_inside_target(*self.overlap(T, self.cluster_size(T, None),
                                              OVERLAP_SAMPLES // 4)):
            if partial is not None:
                partial.result()  # (one search of the map's grid at a time; its sample)
            self._grid = voxel_grid(self.target, self.target_tree, self._target_sample)
        elif d_max is not None and partial is not None:
            grid = partial.result()
            corr = None if grid is None else self.correspondences(T, d_max)
            if corr is not None and self._sheets_likely(corr, grid.pitch):
                self._keep_nearest_fixed_point(T, d_max, corr)
                self._grid = grid
        return self._grid is not None

    def _search_partial_grid(self) -> None:
        """Start looking, on the second thread, for the map's grid (with the source's
        preparation, beside the first iterations), for same-voxel matching from convergence
        on where the source turns out not to lie inside the map (``partial_voxel_matching``):
        5-25 ms on 10k-40k points that a search at convergence would wait for. (Where the
        source does lie inside, the grid is searched for anyway: cached by content.)"""
        cfg = self.config
        if cfg.partial_voxel_matching and cfg.voxel_matching is not None \
                and self._partial_grid is None:
            self._partial_grid = _reverse_executor().submit(_beside, self._partial_cells_grid)

    def _partial_cells_grid(self) -> VoxelGrid | None:
        """The map's grid for same-voxel matching in a partial overlap, or None: also where
        the source looks like a voxel map itself (:func:`looks_voxelised`; LiDAR pipelines'
        pairs), a cell's two centroids being the means of different points there."""
        if looks_voxelised(self.source, self.source_tree) or lattice_pitch(
                self.target, self.target_tree) is not None:  # (a lattice: no cells)
            return None
        sample = self._target_sample = grid_sample(self.target, self.target_tree)
        if sample is None or not sheets_possible(sample, PARTIAL_CELL_ANGLE, PARTIAL_MAP_SHARE,
                                                 PARTIAL_MAP_THICKNESS):
            return None  # (_sheets_likely would refuse: not worth the grid's search)
        return voxel_grid(self.target, self.target_tree, sample)

    def _sheets_likely(self, corr: Correspondences, pitch: float) -> bool:
        """Whether the map's grid is likely to have cut its surface layers into sheets of
        centroids under the pairs ``corr``: at least PARTIAL_CELL_SHARE of them on surfaces
        within PARTIAL_CELL_ANGLE of a grid axis, and those surfaces' layers (median
        thickness, :meth:`map_thickness`) at least PARTIAL_CELL_THICKNESS pitches thick."""
        rows, inverse = np.unique(corr.target_idx, return_inverse=True)
        aligned = self._axis_aligned(rows, PARTIAL_CELL_ANGLE)
        if aligned[inverse].mean() < PARTIAL_CELL_SHARE:
            return False
        thickness = self.map_thickness(rows[aligned])
        return float(np.median(thickness)) >= PARTIAL_CELL_THICKNESS * pitch

    def _keep_nearest_fixed_point(self, T: np.ndarray, d_max: float,
                                  corr: Correspondences) -> None:
        """Keep the nearest-neighbour fixed point ``T`` of a partial overlap with a centroid
        map before the iterations go on with the cells (``partial_voxel_matching``): its
        solution terms, and the reverse direction from it, started on the second thread.

        The cell matching needs the source's points in the map's cells, so it has no reverse
        direction of its own: the reverse's matching (the map's centroids against the nearest
        source points) keeps the aliasing the cells remove, and the two directions' gap would
        measure the aliasing. The direction gap (``trust_gap``, the test for another basin) is
        therefore taken where both directions match by nearest neighbours, as without the
        cells; the estimate and its covariance are the cells' (:meth:`_finish`).
        """
        if not (self.config.symmetric and self.config.covariance == "sandwich"):
            return  # no reverse direction, no gap
        sol = self.solution_terms(T, d_max, corr)
        block = self.cluster_size(T, sol.corr)
        reverse = _reverse_executor().submit(_beside, self.reverse_terms, T, d_max, block,
                                             self._reverse_registration(),
                                             self._reverse_cache, self._stop)
        self._reverse_cache = None
        self._nearest = T, sol, block, reverse

    def _grid_aligned(self, rows: np.ndarray, angle: float) -> np.ndarray:
        """Return (M,) bool: the target normals at ``rows`` within ``angle`` degrees of a grid
        axis (each row worked out once per run, from its covariance)."""
        if self._aligned is None or len(self._aligned) != len(self.target):
            self._aligned = np.full(len(self.target), -1, dtype=np.int8)
        flags = self._aligned[rows]
        todo = np.unique(rows[flags < 0])
        if len(todo):
            self._aligned[todo] = self._axis_aligned(todo, angle)
            flags = self._aligned[rows]
        return flags > 0

    def _axis_aligned(self, rows: np.ndarray, angle: float) -> np.ndarray:
        """Return (M,) bool: the target normals at (unique) ``rows`` within ``angle`` degrees
        of a grid axis, from their covariances (uncached: :meth:`_grid_aligned` caches)."""
        # the plane-regularised covariance is I - (1 - eps) n n^T: n_a^2 on its diagonal
        axes = np.arange(3)
        diagonal = _rows_of(self.target_cov, rows)[rows[:, None], axes, axes]
        return diagonal.min(axis=1) <= 1.0 - (
            1.0 - self.config.epsilon) * np.cos(np.deg2rad(angle)) ** 2

    def same_voxel(self, T: np.ndarray, corr: Correspondences) -> Correspondences:
        """Return ``corr`` with the pairs on surfaces parallel to a voxel-centroid map's grid
        matched to the centroid of the source point's own cell (``voxel_matching``).

        Decided at the first call (the first iteration at the final correspondence
        distance), or, where the source did not lie inside the target there (a start without
        annealing may be further off), once more at convergence, the iterations then going on
        with the cells if it does (:meth:`_voxel_grid_found`): only where the source
        lies inside the target (:func:`source_inside_target`, the overlap at ``T`` on a
        quarter of the points), the target is no voxel lattice and its grid is found
        (:func:`.correspondences.voxel_grid`). A pair is moved when its
        nearest centroid's normal lies within ``voxel_matching`` degrees of a grid axis and
        the source point's cell holds a centroid (of the candidate's class, in Semantic-ICP);
        its weight (the boundary gate's, the E-step's) is kept.
        """
        angle = self.config.voxel_matching
        if angle is None or not len(corr):
            return corr
        if type(self._grid) is int and self._grid == 0 and not self._voxel_grid_found(T):
            self._grid = 1  # not inside (yet): convergence decides (run())
        if not isinstance(self._grid, VoxelGrid):
            return corr
        aligned = self._grid_aligned(corr.target_idx, angle)
        if not aligned.any():
            return corr
        # (a class candidate keeps its class: the cell's centroid must share it)
        return self._grid.same_cell(T, self.source, corr, aligned, self.target,
                                    self.semantic_index.labels if self.semantic else None)

    def _grid_terms(self, sol: SolutionTerms) -> tuple:
        """Return (the model terms' score covariance, crossing rms or None, map_error or None)
        of a source matched by cell in a voxel-centroid map (zeros and None where switched
        off). The two terms are independent of each other and of the point noise, so their
        score covariances add (the map term's: docs/registration_notes.md, "The map term added,
        not its maximum"; the sandwich's meat holds little of the map's error)."""
        cfg = self.config
        B, crossing, map_error = np.zeros((6, 6)), None, None
        # model error: same-voxel pairs whose source point the noise moved across a cell wall
        if cfg.crossing_bias:
            B_crossing, crossing = self.crossing_information(sol)
            B = B + B_crossing
        # model error: the map's representation of the room, coherent over whole objects
        if cfg.map_error is not None:
            B_map, map_error = self.map_error_information(sol)
            B = B + B_map
        return B, crossing, map_error

    def crossing_information(self, sol: SolutionTerms) -> tuple[np.ndarray, float | None]:
        """Return (the (6, 6) score covariance of same-voxel matching's cell crossings, the
        root-mean-square plane offset (m) used, or None where too few pairs were matched by
        cell).

        A source point that its noise moved across the wall of its cell is compared with the
        neighbouring cell's centroid. Summed over a plane, that biases the plane's residuals
        along the grid axis by an amount set by where the grid cuts the plane's surface layer
        (:func:`crossing_bias_rms`: at most about 0.1-0.15 of the noise, 0.6 mm at 5 mm),
        the same for every pair at the same position relative to the walls. Model: the
        grid's phase along each axis a is uniform; the bias of a pair is a periodic function
        of its surface's position x modulo the pitch, represented by its first harmonic with
        the model's mean square V, so the score sums gain
        ``V (Re Z_a Re Z_a^T + Im Z_a Im Z_a^T)``, ``Z_a = sum_k s_k exp(2 pi i x_k / pitch)``
        over the pairs on axis a within ``voxel_matching`` of it (s_k the score's
        sensitivity to a shift along +a; x_k the matched centroid's coordinate; a point that
        landed in an empty cell keeps its nearest centroid, as in the model). A plane
        parallel to the grid sums coherently (its whole offset moves the estimate); a plane
        tilted against it, whose pairs see every phase, averages out. The noise is the
        normal residuals' robust scale (1.4826 MAD), which also holds the layer's own
        spread, so V errs on the large side.
        """
        grid = self._grid
        same = np.flatnonzero(self._grid_aligned(sol.corr.target_idx,
                                                 self.config.voxel_matching))
        if len(same) < MIN_CROSSING_PAIRS:
            return np.zeros((6, 6)), None
        normals = sol.normals[same]
        axis = np.argmax(np.abs(normals), axis=1)
        sign = np.where(normals[np.arange(len(same)), axis] < 0.0, -1.0, 1.0)
        r = sol.normal_residuals[same] * sign
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        rms = crossing_bias_rms(sigma, grid.pitch)
        phase = np.exp(2j * np.pi * (sol.tgt[same, axis] - grid.origin[axis]) / grid.pitch)
        terms = sol.sensitivity[same] * (sign * phase)[:, None]
        B = np.zeros((6, 6))
        for a in range(3):
            Z = terms[axis == a].sum(axis=0)
            B += np.outer(Z.real, Z.real) + np.outer(Z.imag, Z.imag)
        return rms ** 2 * B, rms

    def map_error_information(self, sol: SolutionTerms) -> tuple[np.ndarray, float]:
        """Return (the (6, 6) score covariance of the map's representation error, the
        blocks' offset standard deviation (m) used).

        A voxel-centroid map represents each surface by the mean of the points in each
        cell: it rounds edges and corners, thins small objects and cuts surface layers
        where the grid happens to lie, the same way over a whole object. Model: the map's
        surfaces within each cube of edge ``map_error_block`` are displaced together by a
        random offset u_b, independent between cubes, with covariance s^2 I, s =
        ``map_error`` times the grid's pitch. A shift u of a pair's target point changes its
        score by G_k u, G_k = w_k J_k^T U_k^T (:meth:`SolutionTerms.shift_sensitivity`), so
        the score sums gain ``s^2 sum_b G_b G_b^T``, G_b the sum of G_k over the pairs whose
        target point is in cube b. ``A^-1 B_map A^-1`` is added to the point-noise sandwich
        and the other model terms: the sandwich's meat holds the map's error only at its own
        blocks' scale, which is little of it. With ``map_phase_error``, the part set by the
        grid's phase, coherent over the whole map, is added with the same weights
        (:func:`grid_phase_information`). The estimate does not change.
        """
        cfg = self.config
        grid = self._grid
        s = cfg.map_error * grid.pitch
        # each pair's offset scales with its map surface's local thickness
        weight = self.map_thickness(sol.corr.target_idx) / (MAP_ERROR_THICKNESS * grid.pitch)
        G = sol.shift_sensitivity(weight)
        blocks = cluster_sums(sol.tgt, G.reshape(-1, 18), cfg.map_error_block).reshape(-1, 6, 3)
        B = s ** 2 * np.einsum("bik,bjk->ij", blocks, blocks)
        if cfg.map_phase_error:
            B = B + (cfg.map_phase_error * grid.pitch) ** 2 * grid_phase_information(
                G, sol.tgt, grid.origin, grid.pitch)
        return B, s

    def map_thickness(self, target_idx: np.ndarray) -> np.ndarray:
        """Return the local thickness (m) of the target's surface at each ``target_idx``: the
        standard deviation along the normal of its ``k_neighbours`` nearest target points,
        from the query of its covariance (given covariances: a query of its own)."""
        if isinstance(self.target_cov, LazyCovariances):
            return self.target_cov.thickness(target_idx)
        rows, inverse = np.unique(target_idx, return_inverse=True)
        thickness = np.empty(len(rows))
        neighbourhoods(self.target, self.config.k_neighbours, self.config.epsilon,
                       self.target_tree, rows, thickness=thickness)
        return thickness[inverse.reshape(-1)]

    def _whitening(self, corr: Correspondences, R: np.ndarray) -> np.ndarray:
        """Return the (M, 3, 3) whitening of ``corr`` at rotation ``R`` (:func:`whitening`),
        read from the covariance arrays by row (no gathered copies)."""
        cov_t = _rows_of(self.target_cov, corr.target_idx)
        cov_s, rows = _rows_of(self.source_cov, corr.source_idx), corr.source_idx
        if self.config.pooled_source_covariance and isinstance(self._grid, VoxelGrid):
            # a centroid is the plain mean of its cell's points: the source points matched
            # to it share one covariance (the mean of theirs), so that their whitened
            # residuals sum to the whitened offset of their own mean from it (below). Its
            # pairs then share both covariances: one whitening per centroid serves them all
            # (the same numbers; the scan's 15k-point halves match 1.9 points a centroid,
            # 1.5 -> 1.1 ms a call)
            cov_s, group = pooled_covariances(cov_s, rows, corr.target_idx, len(self.target))
            centroid = np.empty(len(cov_s), np.int64)
            centroid[group] = corr.target_idx
            return self._whitening_rows(cov_t, centroid, cov_s, np.arange(len(cov_s)),
                                        R)[group]
        return self._whitening_rows(cov_t, corr.target_idx, cov_s, rows, R)

    @staticmethod
    def _whitening_rows(cov_t: np.ndarray, target_rows: np.ndarray, cov_s: np.ndarray,
                        source_rows: np.ndarray, R: np.ndarray) -> np.ndarray:
        """:func:`whitening_rows`, half of many rows on the second thread."""
        if len(target_rows) < SPLIT_PAIRS:
            return whitening_rows(cov_t, target_rows, cov_s, source_rows, R)
        # many pairs: half of them on the second thread (the same rows either way)
        out, h = np.zeros((len(target_rows), 3, 3)), len(target_rows) // 2
        rest = _Beside(whitening_rows_into, out[h:], cov_t, target_rows[h:], cov_s,
                       source_rows[h:], R)
        whitening_rows_into(out[:h], cov_t, target_rows[:h], cov_s, source_rows[:h], R)
        rest.result()
        return out

    def _gated(self, T: np.ndarray, d_max: float, corr: Correspondences) -> Correspondences:
        """Return ``corr`` with the pairs beyond the target's surface down-weighted or dropped
        (``boundary_gate``).

        Only at the final correspondence distance (while it anneals, far pairs are what pulls
        a coarse alignment in) and off a voxel lattice (there a room view lies inside its map,
        and the quantisation term models the matching: the gate made a coarse view's run
        oscillate until max_iterations). The target covariance is ``I - (1 - eps) n n^T``,
        so the residual's squared component along the target normal is
        ``r^T (I - C) r / (1 - eps)`` and the rest lies in the tangent plane.
        """
        gate = self.config.boundary_gate
        if (gate is None or not len(corr) or self._lattice is not None
                or d_max > self.config.max_correspondence_distance * (1 + 1e-9)):
            return corr
        src, tgt = self._matched_arrays(corr)
        tangential = tangential_squares(T, src, corr.source_idx, tgt, corr.target_idx,
                                        _rows_of(self.target_cov, corr.target_idx),
                                        self.config.epsilon)
        # exp(-(t / tau)^4 / 2): 0.61 at tau, 0.08 at 1.5 tau; smooth, so the pair set does
        # not flicker at a hard threshold (3 cm noise: 3/30 runs never converged with a hard
        # gate at 0.4, 0/30 with this one). On a random sampling a pair over the surface keeps
        # 0.78 of its weight on average (its nearest neighbour is not always close); a sharper
        # gate (power 8, tau 0.45) kept more but converged less often on the real room's
        # parts (4/10 against 6/10) and was less accurate there (3.4 against 2.9 mm)
        factor = np.exp(-0.5 * (tangential / (gate * self.boundary_radius) ** 2) ** 2)
        keep = factor > 1e-6
        return Correspondences(corr.source_idx[keep], corr.target_idx[keep],
                               corr.weights[keep] * factor[keep], corr.distances[keep],
                               corr.n_source)

    @property
    def boundary_radius(self) -> float:
        """Median distance (m) from a target point to its k-th nearest neighbour (a sample
        of 500): the scale of ``boundary_gate`` and, times ``cluster_factor``, the
        sandwich's block edge (:meth:`cluster_size`)."""
        if self._boundary_radius is None:
            self._boundary_radius = self._median_radius(self.target, self.target_tree)
        return self._boundary_radius

    def _class_caches(self, cache: NeighbourCache | None) -> dict | None:
        """Per-class candidate caches, alive as long as the geometric ``cache`` (same d_max)."""
        if cache is None:
            return None
        if self._class_cache_owner is not cache:
            self._class_cache_owner, self._class_cache = cache, {}
        return self._class_cache

    def _semantic(self, moved: np.ndarray, probs: np.ndarray, d_max: float,
                  cache: NeighbourCache | None, class_cached: bool,
                  rows: np.ndarray | None = None) -> Correspondences:
        """Return Semantic-ICP's candidates and E-step weights (and update the EM sigma) of
        the source ``rows`` (all: None), ``moved`` and ``probs`` theirs; the class candidates
        from caches where ``class_cached``."""
        cfg = self.config
        if self._source_classes is None:  # (the source's labels do not change)
            self._source_classes = (top_class_order(self.source_probs, cfg.top_classes),
                                    self.source_probs.argmax(axis=1))
        order, labels = self._source_classes
        if rows is not None:
            order, labels = order[rows], labels[rows]
        # the posterior E-step is for the final d_max (and the last annealing stage once it
        # has converged: SETTLE_WITH_POSTERIOR); while d_max is still annealing the paper's
        # scores let the labels pull the alignment in (wide offsets: 100 % vs 99 %)
        posterior = (cfg.semantic_estep == "posterior"
                     and (self._settled
                          or d_max <= cfg.max_correspondence_distance * (1 + 1e-9)))
        sigma = d_max if self._sigma is None or not posterior else min(self._sigma, d_max)
        nearest, label_noise, first_class = None, 0.0, None
        if posterior and cache is not None and class_cached:
            # the nearest neighbours and the most probable class's from one candidate scan
            dist, j, *first_class = cache.query_with_class(
                moved, rows, self.semantic_index.labels, np.ascontiguousarray(order[:, 0]))
            nearest = dist, j
        elif posterior:
            nearest = cache.query(moved, rows) if cache is not None else self.target_tree.query(
                moved, k=1, distance_upper_bound=d_max, workers=_workers(len(moved)))
        if posterior:
            if cfg.label_noise == "auto":
                label_noise = self._label_noise(labels, nearest, d_max)
            else:
                label_noise = float(cfg.label_noise)
        corr = semantic_correspondences(
            moved, probs, self.semantic_index, d_max, residual_sigma=max(sigma, 1e-6),
            top_classes=cfg.top_classes, nearest=nearest, posterior=posterior,
            caches=self._class_caches(cache) if class_cached else None,
            label_noise=label_noise, order=order, rows=rows,
            geometric=cache if nearest is not None else None, first_class=first_class)
        if posterior and len(corr):
            # M-step of the isotropic residual variance: sigma^2 = sum w d^2 / (3 sum w)
            w = corr.weights
            self._sigma = float(max(np.sqrt(np.sum(w * corr.distances ** 2) / (3 * np.sum(w))),
                                    1e-4))
        return corr

    def _label_noise(self, labels: np.ndarray, nearest: tuple[np.ndarray, np.ndarray],
                     d_max: float) -> float:
        """The share of source points whose ``labels`` (argmax) differ from their geometric
        nearest neighbour's, among those with one within ``d_max``: the E-step's label noise
        (``RegistrationConfig.label_noise="auto"``), clipped to [MIN_LABEL_NOISE, 0.5]."""
        dist, j = nearest
        ok = dist <= d_max
        if not ok.any():
            return 0.5
        differ = np.mean(labels[ok] != self.semantic_index.labels[j[ok]])
        return float(np.clip(differ, MIN_LABEL_NOISE, 0.5))

    @property
    def adaptive_scale(self) -> bool:
        """True when alpha follows the residuals (``cauchy_scale="auto"``, no lattice)."""
        return self.config.cauchy_scale == "auto" and self._lattice is None

    def _update_alpha(self, e: np.ndarray, wide: bool = False) -> None:
        """Set the Cauchy alpha from the whitened residuals ``e`` (squared norms) if adaptive;
        ``cauchy_alpha`` where ``wide`` (while annealing, and in a final stage that has not
        converged after ``stage_iterations``, until it converges: the wide kernel finds the
        basin. Dense sources against a room's map with the residual-based alpha from the
        first stage slid into another basin or ran out of iterations in 3 of 12 starts that
        Open3D found at 150k points, and with it throughout the final stage in 3 of 20 at
        60k)."""
        if wide:
            self._alpha = self.config.cauchy_alpha
        elif self.adaptive_scale and len(e):
            sigma = 1.4826 * float(np.median(np.sqrt(e)))
            self._alpha = max(CAUCHY_TUNING * sigma, MIN_ADAPTIVE_ALPHA)

    def _weights(self, e: np.ndarray, omega: np.ndarray) -> np.ndarray:
        alpha = self._alpha
        if self.semantic and self.config.semantic_weight == "inside":
            # d/dxi rho(omega e) = omega rho'(omega e) de/dxi  (eq. (7))
            return omega * cauchy_weight(omega * e, alpha)
        return omega * cauchy_weight(e, alpha)

    def _curvature(self, e: np.ndarray, omega: np.ndarray) -> np.ndarray:
        """Coefficient c_k of g_k g_k^T (g_k = J_k^T r_k) in the exact robust Hessian.

        The IRLS matrix sum w_k J^T J drops the rho'' term; for the Cauchy kernel rho'' < 0, so
        dropping it overstates the information exactly when residuals are large (high noise).
        """
        alpha = self._alpha
        if self.semantic and self.config.semantic_weight == "inside":
            return -2.0 * omega ** 2 * cauchy_weight(omega * e, alpha) ** 2 / alpha ** 2
        return -2.0 * omega * cauchy_weight(e, alpha) ** 2 / alpha ** 2

    def _cost(self, e: np.ndarray, omega: np.ndarray) -> float:
        alpha = self._alpha
        if self.semantic and self.config.semantic_weight == "inside":
            return float(np.sum(cauchy_loss(omega * e, alpha)))
        return float(np.sum(omega * cauchy_loss(e, alpha)))

    def run(self, init: np.ndarray | gtsam.Pose3 | None = None) -> RegistrationResult:
        """Return the registration result starting from ``init`` (T_target_source).

        Semantic-ICP whose annealed result is not trusted starts once more with its
        annealing stages matched geometrically (``RegistrationConfig.semantic_rescue``).

        The first call in a process raises glibc's malloc thresholds
        (:func:`estimation.heap.keep_freed_memory`; ``OCTOFACTOR_KEEP_HEAP=0``: not), so that
        the iterations' large arrays reuse memory instead of being faulted in again.

        While it runs, BLAS uses half the cores (one on two; :func:`estimation.blas.blas_threads`,
        ``OCTOFACTOR_BLAS_THREADS=keep``: not): OpenBLAS's idle workers spin and took the
        second thread's core."""
        keep_freed_memory()
        # the second thread works beside this one throughout (preparations, the reverse):
        # this thread's queries leave it its core (:func:`.correspondences.queries_beside`),
        # and so do BLAS's workers
        with queries_beside(), blas_threads(threads_beside()):
            result = self._run(init)
            cfg = self.config
            if (not self.semantic or not cfg.semantic_rescue or _trusted(result)
                    or (cfg.initial_correspondence_distance or 0.0)
                    <= cfg.max_correspondence_distance):
                return result
            # an untrusted Semantic-ICP run that annealed: again, the annealing geometric
            self._geometric_annealing = True
            try:
                second = self._run(init)
            finally:
                self._geometric_annealing = False
        if not _trusted(second):
            return replace(result, time_s=result.time_s + second.time_s)
        return replace(second, iterations=result.iterations + second.iterations,
                       time_s=result.time_s + second.time_s, rescued=True)

    def _run(self, init: np.ndarray | gtsam.Pose3 | None) -> RegistrationResult:
        cfg = self.config
        start = time.perf_counter()
        T = _as_transform(init)
        self._sigma = None
        self._settled = False
        # (the posterior settles the last annealing stage: Semantic-ICP's posterior E-step,
        # stages run to convergence)
        settles = (SETTLE_WITH_POSTERIOR and self.semantic and not self._geometric_annealing
                   and cfg.anneal == "convergence"
                   and cfg.semantic_estep == "posterior")
        self._grid = 0
        self._alpha = cfg.cauchy_alpha
        self._forward_cache = self._reverse_cache = None
        self._nearest = None  # a partial overlap's nearest-neighbour fixed point (_finish)
        self._partial_grid = None  # its map's grid, searched on the second thread
        self._stop = threading.Event()
        if len(self.source) < cfg.min_inliers or len(self.target) < cfg.min_inliers:
            return self._failed(T, f"too few points: source {len(self.source)}, target "
                                   f"{len(self.target)} (need {cfg.min_inliers})", start)
        self._prepare_source()
        self._prepare_index()
        key = gtsam.symbol("t", 0)
        d_final = cfg.max_correspondence_distance
        d = max(cfg.initial_correspondence_distance or d_final, d_final)
        cost_log: list[float] = []
        converged = False
        reason = "max iterations"
        iterations = 0
        T_prev = None
        stage_iterations = 0
        coarse = self._coarse_rows()
        # every annealing stage is capped by stage_iterations and the final one by
        # max_iterations; the hard cap also bounds a schedule that never reaches d_final
        annealing_budget = 0
        if d > d_final * (1 + 1e-9) and cfg.decay < 1.0:
            stages = int(np.ceil(np.log(d_final / d) / np.log(cfg.decay))) + 1  # +1: rounding
            annealing_budget = stages * (cfg.stage_iterations if cfg.anneal == "convergence"
                                         else 1)
        final_iterations = 0
        max_final = cfg.max_iterations  # (a second start's: RESCUE_FINAL_ITERATIONS)
        if self._geometric_annealing and RESCUE_FINAL_ITERATIONS is not None:
            max_final = min(max_final, RESCUE_FINAL_ITERATIONS)
        # an annealed registration whose final stage (residual-based kernel) has not converged
        # after stage_iterations is crawling: the wide kernel (cauchy_alpha) until it
        # converges, then the narrow one again
        rescue = annealing_budget > 0 and self.adaptive_scale and WIDE_FINAL_STAGE
        # a source with a coarse subset started at the final d_max: a coarse stage there
        coarse_first = annealing_budget == 0 and coarse is not None and COARSE_FIRST
        if coarse_first:
            annealing_budget = cfg.stage_iterations
        wide = False
        # the final stage's (_prepare_forward) and the reverse's (_prepare_reverse) preparation
        # started
        prepared_forward = prepared_reverse = False
        step = np.inf  # the last Gauss-Newton step
        last_step = None  # the final stage's last step (tangent vector), for _extrapolated
        creep = None  # the creep of the final stage's last two steps: (rho, the later step)
        for iterations in range(1, cfg.max_iterations + annealing_budget + 1):
            annealing = coarse_first or d > d_final * (1 + 1e-9)
            if not annealing:
                if final_iterations >= max_final:
                    iterations -= 1
                    break
                final_iterations += 1
                if rescue and final_iterations > cfg.stage_iterations:
                    rescue, wide, T_prev = False, True, None
            # (the coarse first stage queries the tree: the final stage's neighbour cache, at
            # the same d_max, is being prepared for every point on the second thread; and it
            # leaves the same-voxel decision to the first iteration on every point, as
            # annealing does: from the start, often not yet inside the map, it would wait
            # for convergence and two or three more iterations)
            corr = self.correspondences(T, d, coarse if annealing else None,
                                        np.inf if coarse_first else step,
                                        cells=not coarse_first)
            if iterations == 1:
                # after the first prefetch: the second thread computes the source rows the
                # first whitening needs before it searches the map's grid (needed at
                # convergence; KITTI at 0.5 m: this thread computed them meanwhile, 5.6 ms)
                self._search_partial_grid()
            if len(corr) < cfg.min_inliers:
                return self._failed(T, f"only {len(corr)} correspondences within "
                                       f"d_max={d:g} m (need {cfg.min_inliers})",
                                    start, iterations, cost_log)
            # (every point array with the rows of corr available: no gathered copies)
            src_all, tgt_all = self._matched_arrays(corr)
            Ut = self._whitening(corr, T[:3, :3])
            e = mahalanobis(T, src_all, corr.source_idx, tgt_all, corr.target_idx, Ut)
            self._update_alpha(e, annealing or wide)
            cost_log.append(self._cost(e, corr.weights))
            if cfg.factors == "batched" and cfg.optimizer == "gn" and cfg.inner_iterations == 1:
                # one Gauss-Newton step of the batched factor, from its normal equations
                # (GaussNewtonOptimizer would evaluate the factor three times)
                w = self._weights(e, corr.weights)
                H, g = normal_equations(T, src_all, corr.source_idx, tgt_all, corr.target_idx,
                                        Ut, w)
                T_new = gauss_newton_step(T, H, g, key)
            else:
                H = None  # (GTSAM's optimiser forms the normal equations)
                src, tgt = self.matched_points(corr)
                if cfg.factors == "batched":
                    factor = BatchedGicpFactor(key, src, tgt, Ut, self._weights(e, corr.weights))
                else:  # GTSAM applies the Cauchy kernel itself, one factor per correspondence
                    factor = robust_factors(key, src, tgt, Ut, corr.weights, self._alpha,
                                            cfg.semantic_weight if self.semantic else "outside")
                T_new = solve_weighted(T, factor, cfg.optimizer, cfg.inner_iterations, key)
            xi = gtsam.Pose3.Logmap(gtsam.Pose3(T).between(gtsam.Pose3(T_new)))
            step = np.linalg.norm(xi)
            # nearest-neighbour sets can alternate forever between two poses
            two_cycle = T_prev is not None and np.linalg.norm(gtsam.Pose3.Logmap(
                gtsam.Pose3(T_prev).between(gtsam.Pose3(T_new)))) < cfg.tolerance
            stage_iterations += 1
            if annealing:
                # the settle's step within the estimate's noise (after its first step)
                within = (SETTLE_WITHIN_SIGMA is not None and self._settled
                          and stage_iterations >= 2 and H is not None
                          and step_in_sigmas(xi, H, w, e) < SETTLE_WITHIN_SIGMA)
                if (settles and not self._settled and (step < cfg.tolerance or two_cycle)
                        and not coarse_first and d * cfg.decay <= d_final * (1 + 1e-9)):
                    # Semantic-ICP's last annealing stage has converged with the paper's
                    # scores: it goes on with the posterior E-step before the final stage
                    self._settled = True
                    stage_iterations, T_prev, T = 0, None, T_new
                    continue
                if not prepared_forward and step < PREPARE_FORWARD_STEP:
                    prepared_forward = True
                    # (after a coarse first stage's short steps the cache would outlast
                    # them, and this thread would wait for the other to query it whole)
                    self._prepare_forward(T_new, d_final,
                                          np.inf if coarse_first else self._motion(T, T_new))
                if (cfg.anneal == "iteration" or step < cfg.tolerance or two_cycle
                        or stage_iterations >= cfg.stage_iterations or within
                        or (coarse_first and stage_iterations == 1
                            and step < COARSE_FIRST_STEP)):
                    d = max(d * cfg.decay, d_final)
                    coarse_first = False
                    stage_iterations, T_prev, T = 0, None, T_new
                else:
                    T_prev, T = T, T_new
                continue
            if not prepared_reverse and step < PREPARE_STEP:
                prepared_reverse = True
                self._prepare_reverse(T_new, d)
            if (step < cfg.tolerance and CONVERGE_ON_REMAINDER and creep is not None
                    and float(xi @ creep[1]) / np.linalg.norm(creep[1]) * creep[0]
                    / (1.0 - creep[0]) >= cfg.tolerance):
                # a short step of a creep that has further to go: not converged
                # (creep is measured where the creep is extrapolated: EXTRAPOLATE)
                T_prev, (T, last_step) = T, _extrapolated(T_new, xi, creep[0])
                continue
            if step < cfg.tolerance or two_cycle:
                # converged; a two-cycle of correspondence sets stops in its middle
                T = T_new if step < cfg.tolerance else (
                    gtsam.Pose3(T) * gtsam.Pose3.Expmap(0.5 * xi)).matrix()
                if wide:  # converged with the wide kernel: now the narrow one
                    wide, T_prev, creep = False, None, None
                    continue
                if self._voxel_grid_found(T, d):  # in a centroid map: on, matched by cell
                    T_prev, creep = None, None
                    continue
                converged, reason = True, ("converged" if step < cfg.tolerance else
                                           "converged (two-cycle of correspondence sets)")
                break
            if EXTRAPOLATE:
                if last_step is not None:  # (after a jump, the creep measured before it)
                    held = _creep_ratio(xi, last_step, CREEP_COSINE)
                    creep = None if held is None else (held, xi)
                T_new, last_step = _extrapolated(T_new, xi, _creep_ratio(xi, last_step))
            T_prev, T = T, T_new
        return self._finish(T, d_final, converged, reason, iterations, cost_log, start)

    def _coarse_rows(self) -> np.ndarray | None:
        """The source rows the annealing stages match (None: every row)."""
        cfg = self.config
        n_src = len(self.source)
        if not cfg.coarse_points or n_src <= 2 * cfg.coarse_points:
            return None

        def strided(count: int) -> np.ndarray:  # about count evenly strided rows
            return np.arange(0, n_src, max(n_src // count, 1))

        if not NORMAL_SPACE_SAMPLING:
            return strided(cfg.coarse_points)
        pool = strided(NORMAL_SPACE_POOL * cfg.coarse_points)
        cov = self.source_cov
        if isinstance(cov, LazyCovariances) and self._prefetching:
            # (half of them on the second thread; the final stage matches every row too)
            cov.fill_beside(pool, _reverse_executor().submit)
        half = cfg.coarse_points // 2
        return np.union1d(strided(half),
                          pool[normal_space_rows(covariance_normals(cov[pool]), half)])

    def solution_terms(self, T: np.ndarray, d_max: float,
                       corr: Correspondences | None = None) -> SolutionTerms | None:
        """Return the correspondences, scores and Hessians at ``T`` (None if too few);
        ``corr``: the correspondences at ``T``, if already found."""
        corr = self.correspondences(T, d_max) if corr is None else corr
        if len(corr) < self.config.min_inliers:
            return None
        src, tgt = self.matched_points(corr)
        Ut = self._whitening(corr, T[:3, :3])
        terms = gicp_terms(T, src, tgt, Ut)
        w = self._weights(terms.mahalanobis, corr.weights)
        # the exact Hessian of the robust cost (with the rho'' term, which IRLS drops)
        c = self._curvature(terms.mahalanobis, corr.weights)
        # (one pass over the pairs: the numpy products' (M, 3, 6) temporaries took 0.4 s of a
        # raw half-room's 3.4 s; the target covariance I - (1 - epsilon) n n^T gives the normal)
        H, curvature, scores, normals, rn, sens = solution_sums(
            T, src, tgt, Ut, terms, w, c, _rows_of(self.target_cov, corr.target_idx),
            corr.target_idx)
        A = H + curvature
        if np.linalg.eigvalsh(A).min() <= 1e-9 * np.abs(np.linalg.eigvalsh(H)).max():
            A = H  # too many residuals beyond the kernel's inflection: fall back to IRLS
        return SolutionTerms(corr, src, tgt, w, H, A, scores, normals, rn, sens,
                             terms.jacobians, Ut)

    def _finish(self, T, d_max, converged, reason, iterations, cost_log, start):
        cfg = self.config
        if isinstance(self._grid, int):  # still undecided: the matching stays as it ran
            self._grid = None
        pitch = self.quantisation_pitch
        sandwich = cfg.covariance == "sandwich"
        # on a lattice there is no reverse direction and the second thread is free: it builds
        # the lattice's cells (the quantisation term's neighbourhoods) and, below, measures
        # the off-surface share while this one computes the solution's terms (the simulated
        # room at 10k points: 7 of the 23-29 ms here; in-process A/B, bit-identical: 2-5 %
        # less time a Semantic-ICP registration)
        cells = (_Beside(self._lattice_grid, pitch) if sandwich and pitch is not None
                 and self._means_radius is not None and self._lattice_cells is None else None)
        # (Semantic-ICP: the E-step at the solution sets the sigma the reverse direction takes)
        corr = self.correspondences(T, d_max)
        if len(corr) < cfg.min_inliers:
            return self._failed(T, "too few correspondences at the solution",
                                start, iterations, cost_log)
        block = self.cluster_size(T, corr)
        # the reverse direction of the symmetric estimate depends only on T: it runs on a
        # second thread while this direction's covariance is computed (its KD-tree queries
        # and kernels release the GIL; the result is the same on one thread). It starts before
        # the overlap test that may rule it out (a source inside its target), which then
        # stops it: started after this direction's solution terms and overlap, it was the
        # longer of the two threads (KITTI at 0.15 m: 10 ms later). Not where the source was
        # found inside a voxel-centroid map (same_voxel): the test would most likely stop it
        symmetric = cfg.symmetric and sandwich and pitch is None and converged
        reverse = None
        # a partial overlap matched by cell: the forward estimate, the gap of the nearest-
        # neighbour fixed point's two directions (_keep_nearest_fixed_point)
        nearest, self._nearest = self._nearest, None
        if nearest is not None and not symmetric:
            nearest = None
            self._stop.set()  # its reverse direction is not needed

        def start_reverse():
            # (the reverse registration takes its state, e.g. Semantic-ICP's sigma, now, on
            # this thread: the re-matched bread below changes it while it runs)
            return _reverse_executor().submit(_beside, self.reverse_terms, T, d_max,
                                              block, self._reverse_registration(),
                                              self._reverse_cache, self._stop)

        if symmetric and not isinstance(self._grid, VoxelGrid):
            reverse = start_reverse()
        overlap, off_surface = (float("nan"), float("nan")), float("nan")
        lattice_coverage = None  # (on a lattice: measured beside, collected for the diagnostic)
        if sandwich and pitch is None and converged:
            covered, target_covered, off_surface = self.coverage(T, block)
            overlap = (covered, target_covered)
        elif sandwich and converged:  # on a lattice: no overlap rule, but the share
            lattice_coverage = _Beside(self.coverage, T, block)
        # a part of a map registered to that map (no lattice term): trusted only with the
        # map's representation error in the covariance (map_error) and every point on the
        # map's surfaces (INSIDE_TRUSTED_COVERAGE; docs/registration_notes.md, "Real rooms")
        inside = source_inside_target(*overlap)
        if inside:
            reverse = None  # the forward estimate is kept (a reverse started ends early)
        elif symmetric and reverse is None and nearest is None:
            reverse = start_reverse()
        if reverse is None and nearest is None:
            self._stop.set()  # the reverse direction's preparation is not needed
        self._reverse_cache = None
        sol = self.solution_terms(T, d_max, corr)
        src, tgt, w = sol.src, sol.tgt, sol.w
        diagnostic = None
        # the voxel-centroid map's model terms depend only on the solution's terms: on the
        # second thread (free here: a source inside the map has no reverse direction) while
        # this one computes the sandwich and the re-matched bread (the scan's raw half:
        # 21 ms of its 105 ms)
        grid_terms = None
        if sandwich and isinstance(self._grid, VoxelGrid) and (
                cfg.crossing_bias or cfg.map_error is not None):
            grid_terms = _Beside(self._grid_terms, sol)
        # M-estimator sandwich A^-1 B A^-1: A the exact Hessian of the robust cost, B the
        # outer product of the scores summed per spatial block (cluster-robust: neighbouring
        # residuals share target points and the neighbourhoods their covariances came from)
        clustered = cluster_sums(tgt, sol.scores, block)
        B = clustered.T @ clustered
        # model error: a voxel lattice's quantisation offsets, common to whole planes
        B_model = np.zeros((6, 6))
        if cells is not None:
            cells.result()
        if pitch is not None:
            B_model = quantisation_information(
                sol.normals, tgt, sol.sensitivity, pitch,
                self.target[corr.target_idx] if cfg.tilted_planes else None, cfg.plane_tilt,
                cfg.lattice_noise, self._averaged_lattice_points(corr.target_idx, pitch),
                (sol.jacobians, sol.whitening, w) if cfg.inplane_quantisation else None)
        scale = self._scale(src)
        H_normal = self._normal_information(T, src, sol.normals, w)

        def information_to_covariance(bread, meat):
            return covariance_from_information(bread, meat, scale, H_normal,
                                               cfg.degeneracy_ratio)

        crossing = map_error = None
        modelled = pitch is not None
        if not sandwich:
            cov, unconstrained = information_to_covariance(sol.H, None)
        else:
            cov_noise, unconstrained = information_to_covariance(sol.A, B)
            A_noise, gain = sol.A, 1.0
            if cfg.reassociation_step is not None and not unconstrained and pitch is None:
                # the point noise moves which neighbours are matched. (On a voxel lattice the
                # matches jump between lattice sites: that is the quantisation, which its own
                # term covers, through the fixed-association bread: a plane's common offset
                # moves the plane as a whole and keeps its matches.)
                A_noise = self.reassociation_hessian(T, d_max, sol, cov_noise)
                fixed = cov_noise
                # the bread's differences are noisy and may turn the ellipsoid a little:
                # re-matching never makes a direction more certain, so keep the larger
                cov_noise = loewner_max(fixed, information_to_covariance(A_noise, B)[0])
                gain = float(np.trace(np.linalg.solve(fixed, cov_noise)) / 6.0)
            if grid_terms is not None:
                B_grid, crossing, map_error = grid_terms.result()
                B_model = B_model + B_grid
                modelled = modelled or crossing is not None or map_error is not None
            cov_model = np.zeros((6, 6))
            if modelled:
                cov_model, _ = information_to_covariance(sol.A, B_model)
            # (unconstrained directions: one UNCONSTRAINED_VARIANCE, not one per part)
            cov = cov_noise + cov_model if not unconstrained else \
                information_to_covariance(sol.A, B + B_model)[0]
            wide = cluster_sums(tgt, sol.scores, 4.0 * block)
            cov_wide = information_to_covariance(A_noise, wide.T @ wide)[0] + cov_model
            S2 = np.array([scale ** 2] * 3 + [1.0] * 3)
            share = float(np.trace(cov_model * S2[:, None]) / np.trace(cov * S2[:, None])) \
                if modelled and not unconstrained else 0.0
            ratio = float(np.trace(np.linalg.solve(cov, cov_wide)) / 6.0)
            if lattice_coverage is not None:
                off_surface = lattice_coverage.result()[2]
            diagnostic = CovarianceDiagnostic(
                pitch, share, ratio, ratio <= cfg.trust_ratio and (not inside or (
                    map_error is not None and overlap[0] >= INSIDE_TRUSTED_COVERAGE)),
                cov_model, gain,
                overlap=overlap, off_surface=off_surface,
                voxel_pitch=self._grid.pitch if isinstance(self._grid, VoxelGrid) else None,
                crossing_bias=crossing, map_error=map_error,
                plane_tilt=cfg.plane_tilt if pitch is not None and cfg.plane_tilt else None,
                lattice_noise=(cfg.lattice_noise if pitch is not None and cfg.tilted_planes
                               else None),
                inplane_quantisation=pitch is not None and cfg.inplane_quantisation)
            if reverse is not None:
                reverse_terms = reverse.result()  # (waited for when unused, too)
                if not unconstrained:
                    T, cov, diagnostic = self._symmetric(T, cov, diagnostic, sol, A_noise,
                                                         block, reverse_terms, sol.A)
            elif nearest is not None:
                T_near, sol_near, block_near, reverse_near = nearest
                reverse_terms = reverse_near.result()
                if not unconstrained and reverse_terms is not None:
                    # (the re-matched bread of the cells' solution: the same basin, mm away)
                    gap = self._symmetric(T_near, cov, diagnostic, sol_near, A_noise,
                                          block_near, reverse_terms, sol.A)[2].direction_gap
                    diagnostic = replace(diagnostic, direction_gap=gap)
        inliers = len(corr)
        if unconstrained:
            converged = False
            reason = f"degenerate geometry: {unconstrained} unconstrained direction(s)"
        if diagnostic is not None and diagnostic.trusted and (
                not converged or diagnostic.direction_gap > cfg.trust_gap
                or diagnostic.off_surface > cfg.trust_off_surface):
            # an estimate that did not converge, whose two directions found different
            # solutions (another basin, or a bias the midpoint does not cover), or with part
            # of the source beside the target's surfaces (another basin), has no
            # covariance to trust (NaN gap: one direction; NaN share: not measured)
            diagnostic = replace(diagnostic, trusted=False)
        # an offset common to the whole source that the data cannot show (an input)
        cov = cov + systematic_covariance(cfg.systematic_sigma, T[:3, :3],
                                          cfg.systematic_rotation_sigma)
        dist = np.linalg.norm(tgt - transform_points(T, src), axis=1)
        return RegistrationResult(
            T, cov, sol.H, iterations, inliers, inliers / len(self.source),
            float(np.sqrt(np.mean(dist ** 2))), converged, reason, tuple(cost_log),
            self.method, time.perf_counter() - start, diagnostic, self._alpha)

    def _motion(self, T: np.ndarray, T_new: np.ndarray) -> float:
        """The median distance (m) the source's points moved from ``T`` to ``T_new`` (a
        strided sample of about 1000)."""
        sample = self.source[::max(len(self.source) // 1000, 1)]
        return float(np.median(np.linalg.norm(
            transform_points(T_new, sample) - transform_points(T, sample), axis=1)))

    def _prepare_forward(self, T: np.ndarray, d_max: float, motion: float | None = None
                         ) -> None:
        """Start preparing the iterations at the final ``d_max`` from ``T`` (an annealing
        stage's pose once its steps have become small, ``PREPARE_FORWARD_STEP``) on the
        second thread, beside this stage's remaining iterations, which leave that core idle:
        the neighbour cache of the final ``d_max`` and the covariances of the rows matched
        within it at ``T`` (missing ones are computed when needed, as always).

        The cache gives the exact nearest neighbours from any anchor (:class:`NeighbourCache`),
        and each row's covariance does not depend on when it is computed, so no result
        changes. (KITTI at 0.15 m: the cache and these covariances took 30-35 ms at the start
        of the final stage, on both cores.)

        ``motion``: the last step's median point displacement (m). The pose moves on after
        ``T``, and a cache whose candidates' reach is shorter than that would be queried again
        almost whole (:meth:`_prepare`).
        """
        k = self.config.cached_neighbours
        if not k or (self._cache is not None and self._cache.d_max == d_max):
            return
        self._forward_cache = d_max, self._prepare(NeighbourCache(self.target_tree, d_max, k,
                                                                  len(self.source)),
                                                   transform_points(T, self.source),
                                                   self.source_cov, self.target_cov,
                                                   None if motion is None
                                                   else PREPARED_REACH * motion)

    def _prepared_cache(self, d_max: float) -> NeighbourCache | None:
        """The neighbour cache :meth:`_prepare_forward` made for ``d_max`` (waited for), if any."""
        if self._forward_cache is None or self._forward_cache[0] != d_max:
            return None
        prepared, self._forward_cache = self._forward_cache[1], None
        return prepared.result()

    def _prepare_reverse(self, T: np.ndarray, d_max: float) -> None:
        """Start the symmetric estimate's reverse direction's preparation at ``T`` on the second
        thread, beside this direction's remaining iterations at the final ``d_max`` (they
        leave that core idle): its neighbour cache and the covariances of the rows it will
        match (those within ``d_max`` at ``T``; missing ones are computed when needed, as
        always). Started once the steps have become small (``PREPARE_STEP``); exact for the
        same reasons as :meth:`_prepare_forward`. (KITTI at 0.15 m: the cache and the
        covariances took 12 and 10 ms of the reverse, which the forward waited for.)
        """
        cfg = self.config
        k = min(cfg.cached_neighbours, 4)  # as _reverse_registration's
        if not (cfg.symmetric and cfg.covariance == "sandwich" and k
                and self.quantisation_pitch is None and not isinstance(self._grid, VoxelGrid)):
            return  # no reverse direction will run (a voxel-centroid map: source inside)
        self._reverse_cache = self._prepare(NeighbourCache(self.source_tree, d_max, k,
                                                           len(self.target)),
                                            transform_points(np.linalg.inv(T), self.target),
                                            self.target_cov, self.source_cov)

    def _prepare(self, cache: NeighbourCache, moved: np.ndarray,
                 moved_cov: np.ndarray | LazyCovariances,
                 fixed_cov: np.ndarray | LazyCovariances, motion: float | None = None
                 ) -> Future:
        """Query ``cache`` with the ``moved`` points on the second thread, then compute the
        covariances of the pairs found (``moved_cov`` of the points, ``fixed_cov`` of their
        neighbours). Return a future of the cache, set as soon as it is queried.

        With ``motion`` (m, how far the points are expected to move before the cache is
        used): where a sample of the cache's rows says that most of its candidates would be
        stale by then (:meth:`NeighbourCache.outlasts`), no cache is made (the future's
        result is None: its user queries its own) and the covariances' rows come from plain
        nearest neighbours. (A room's 3 cm map: the candidates' reach was 11 mm, and 0-7 %
        of the rows were still valid when the final stage began, 20-250 mm further on;
        KITTI's 70-300 mm reach kept 97-100 %.)"""
        ready: Future = Future()
        stop = self._stop

        def prepare() -> None:
            try:
                with queries_beside():  # this thread's queries beside the other's
                    if motion is None or cache.outlasts(moved, motion):
                        dist, nearest = cache.query(moved)
                        ready.set_result(cache)
                    else:
                        ready.set_result(None)
                        dist, nearest = cache.tree.query(moved, k=1,
                                                         distance_upper_bound=cache.d_max,
                                                         workers=_workers(len(moved)))
                    ok = np.isfinite(dist)
                    for cov, rows in ((moved_cov, np.flatnonzero(ok)), (fixed_cov, nearest[ok])):
                        if isinstance(cov, LazyCovariances):
                            cov.prefetch(rows, stop=stop)
            except BaseException as error:
                if not ready.done():
                    ready.set_exception(error)
                raise

        _reverse_executor().submit(prepare)
        return ready

    def _twin(self) -> Registration:
        """A copy of this registration whose correspondences at other poses may run on another
        thread beside this one's: what both read is shared (trees, covariances, which both
        fill row by row, the grid), what the searches change is the twin's own (copies of
        the neighbour caches, the E-step's sigma); no prefetching from it."""
        twin = copy.copy(self)
        twin._prefetching = False
        # (what this registration prepared on the second thread stays its own)
        twin._forward_cache = twin._reverse_cache = twin._nearest = None
        if self._cache is not None:
            twin._cache = self._cache.copy()
        if self._class_cache_owner is self._cache and self._cache is not None:
            twin._class_cache_owner = twin._cache
            twin._class_cache = {rank: cache.copy() for rank, cache in self._class_cache.items()}
        return twin

    def _reverse_registration(self) -> Registration:
        """Return the registration of the target to the source, sharing what is shared.

        The per-point covariances (the reverse's source is this target, its target this
        source), the lattice decision, the kernel's alpha and Semantic-ICP's residual sigma.
        """
        # (every pose the reverse visits is within a few standard deviations of the first:
        # four cached candidates keep its neighbour search exact at a cheaper query than
        # eight; with two, KITTI's six re-matched poses re-queried 1.2k-3.9k of 10.6k rows each)
        cfg = replace(self.config, initial_correspondence_distance=None, symmetric=False,
                      cauchy_scale="fixed", cauchy_alpha=self._alpha,
                      cached_neighbours=min(self.config.cached_neighbours, 4))
        # (the target's covariances stay lazy: the reverse matches mostly the same rows)
        rev = Registration(self.target, self.source, cfg,
                           self.target_probs if self.semantic else None,
                           self.source_probs if self.semantic else None,
                           source_cov=self.target_cov, target_cov=self.source_cov)
        rev._found_pitch, rev._pitch = self._found_pitch, self._pitch
        rev._surface_radius = self._surface_radius
        if self._surface_radius is not None:  # the local means come with the covariances
            rev._source_pos = self._target_stats.means(np.arange(len(self.target)))
            if isinstance(self._source_cov, LazyCovariances):
                rev._target_lazy = self._source_cov  # (its rows' means, those computed kept)
        rev._sigma, rev._alpha, rev._block = self._sigma, self._alpha, self._block
        # (the reverse's boundary_radius is this source's; overlap() has computed it already)
        rev._boundary_radius = self._source_radius
        rev._tree = self.source_tree
        rev._grid = None  # the reverse's target is the source: no map grid
        rev._prefetching = False  # (it runs on the thread that would prefetch)
        return rev

    def overlap(self, T: np.ndarray, block: float, samples: int = 0) -> tuple[float, float]:
        """Return (share of the source covered by the target, share of the target covered by
        the source) at ``T``: the share of (up to ``samples``, default ``OVERLAP_SAMPLES``,
        evenly strided) points
        with a point of the other cloud within the larger of the two clouds' block edges
        (``block``, the target's; the source's alike), i.e. on a surface the other cloud
        has sampled too.
        """
        return self.coverage(T, block, samples, off_surface=False)[:2]

    def coverage(self, T: np.ndarray, block: float, samples: int = 0,
                 off_surface: bool = True) -> tuple[float, float, float]:
        """Return :meth:`overlap` and the source's off-surface share at ``T`` (NaN unless
        ``off_surface``), from the same queries.

        Off-surface share: of the sampled source points within two of the overlap's radii of
        a target point, the share not within one. In the right basin a source point lies on a
        surface the target sampled too or beyond what the target covers; in another basin
        part of it lies beside the target's surfaces (docs/registration_notes.md, "Off the
        surfaces"). NaN where no source point is that near.
        """
        if self._source_block is None:
            self._source_block = self.config.cluster_factor * self._source_radius
        radius = max(block, self._source_block)
        samples = samples or OVERLAP_SAMPLES
        src = self.source[:: max(1, len(self.source) // samples)]
        tgt = self.target[:: max(1, len(self.target) // samples)]
        d_f, _ = self.target_tree.query(
            transform_points(T, src), distance_upper_bound=(2.0 if off_surface else 1.0) * radius)
        d_r, _ = self.source_tree.query(transform_points(np.linalg.inv(T), tgt),
                                        distance_upper_bound=radius)
        on, near = int(np.sum(d_f < radius)), int(np.sum(d_f < 2.0 * radius))
        share = (near - on) / near if off_surface and near else float("nan")
        return on / len(src), float(np.mean(d_r < radius)), float(share)

    def reverse_terms(self, T: np.ndarray, d_max: float, block: float,
                      rev: Registration | None = None, cache: Future | None = None,
                      stop: threading.Event | None = None
                      ) -> tuple[np.ndarray, SolutionTerms, np.ndarray] | None:
        """Return (T_rev, its solution terms, its re-matched bread) of the reverse direction.

        The target registered to the source, started at ``T^-1``: ``T_rev = T^-1 Exp(eta)``
        with the Newton step ``eta = -A_r^-1 F_r`` of the reverse's score sum ``F_r`` at
        ``T^-1``, ``A_r`` its re-matched bread (:meth:`reassociation_hessian`): the bread is
        the derivative of the score sum with the correspondences re-matched, so this is the
        reverse's own fixed point to first order (the forward solution is within about one
        standard deviation of it). None when the reverse has too few correspondences or
        leaves a direction unconstrained (the forward estimate is then kept). ``rev``: the
        reverse registration, if already made (:meth:`_reverse_registration`); ``cache``: its
        neighbour cache, if prepared (:meth:`_prepare_reverse`); ``stop`` (set): None, early
        (the forward estimate is kept).
        """
        rev = self._reverse_registration() if rev is None else rev
        if cache is not None:
            rev._cache = cache.result()
        T_inv = np.linalg.inv(T)
        sol = None if stop is not None and stop.is_set() else rev.solution_terms(T_inv, d_max)
        if sol is None or (stop is not None and stop.is_set()):
            return None
        H_normal = self._normal_information(T_inv, sol.src, sol.normals, sol.w)
        summed = cluster_sums(sol.src, sol.scores, block)
        fixed, unconstrained = covariance_from_information(
            sol.A, summed.T @ summed, self._scale(sol.src), H_normal, self.config.degeneracy_ratio)
        if unconstrained:
            return None  # the reverse leaves a direction unconstrained: no Newton step
        A_noise = sol.A if self.config.reassociation_step is None else \
            rev.reassociation_hessian(T_inv, d_max, sol, fixed)
        # (the step with the bread at the earlier floor: see SYMMETRIC_BREAD_FLOOR)
        eta = -np.linalg.solve(bread_within(sol.A, A_noise, SYMMETRIC_BREAD_FLOOR),
                               sol.scores.sum(axis=0))
        return T_inv @ gtsam.Pose3.Expmap(eta).matrix(), sol, A_noise

    def _symmetric(self, T: np.ndarray, cov: np.ndarray, diagnostic: CovarianceDiagnostic,
                   sol_f: SolutionTerms, A_nf: np.ndarray, block: float,
                   reverse: tuple[np.ndarray, SolutionTerms, np.ndarray] | None,
                   A_f: np.ndarray) -> tuple[np.ndarray, np.ndarray, CovarianceDiagnostic]:
        """Return (T, covariance, diagnostic) of the midpoint of both registration directions.

        Nearest-neighbour matching is not symmetric: on real scans the estimate moves when
        source and target swap roles, by an error every split of a scan repeats (a bias of
        the matching, docs/registration_notes.md). The target is registered to the source from
        the forward solution (:meth:`reverse_terms`), and the reported pose is the midpoint
        of the two estimates, ``T Exp(delta / 2)`` with ``delta = Logmap(T^-1 T_rev^-1)``.
        Its covariance is the sandwich of the two stacked estimating equations: both
        directions' scores summed in the same spatial blocks (they re-use the same points,
        so the two estimates are correlated), each direction's own bread, the midpoint's
        linear map ``[I/2, -Ad(T_rev)/2]``; with the fixed-association and the re-matched
        breads, the Loewner maximum of the two, as for one direction. ``sol_f``, ``A_nf`` and
        ``block`` are the forward direction's solution terms, re-matched bread and block edge;
        ``reverse`` is what :meth:`reverse_terms` returned for ``T``; ``A_f`` the Hessian the
        forward bread was taken against (the direction gap's breads are limited relative to
        it, and the reverse's to its own, at ``SYMMETRIC_BREAD_FLOOR``).
        """
        if reverse is None:
            return T, cov, diagnostic
        T_rev, sol_r, A_nr = reverse
        T_rev_inv = np.linalg.inv(T_rev)
        delta = gtsam.Pose3.Logmap(gtsam.Pose3(T).between(gtsam.Pose3(T_rev_inv)))
        T_mid = T @ gtsam.Pose3.Expmap(0.5 * delta).matrix()
        # the reverse's right perturbation eta of T_rev maps to xi = -Ad(T_rev) eta
        M = -gtsam.Pose3(T_rev).AdjointMap()
        m_f, m_r = len(sol_f.scores), len(sol_r.scores)
        values = np.zeros((m_f + m_r, 12))
        values[:m_f, :6] = sol_f.scores
        values[m_f:, 6:] = sol_r.scores
        # the reverse's source points are this target's, in the target frame
        summed = cluster_sums(np.vstack([sol_f.tgt, sol_r.src]), values, block)
        B12 = summed.T @ summed

        def stacked(A_f, A_r, L):
            G = np.hstack([np.linalg.solve(A_f, L[:, :6].T).T,
                           np.linalg.solve(A_r, L[:, 6:].T).T])
            return G @ B12 @ G.T

        I6 = np.eye(6)
        mid = np.hstack([0.5 * I6, 0.5 * M])
        gap = np.hstack([I6, -M])
        cov_mid = loewner_max(stacked(sol_f.A, sol_r.A, mid), stacked(A_nf, A_nr, mid))
        # (the gap's test keeps the re-matched breads at SYMMETRIC_BREAD_FLOOR, the floor its
        # threshold trust_gap was measured with)
        cov_gap = loewner_max(stacked(sol_f.A, sol_r.A, gap),
                              stacked(bread_within(A_f, A_nf, SYMMETRIC_BREAD_FLOOR),
                                      bread_within(sol_r.A, A_nr, SYMMETRIC_BREAD_FLOOR), gap))
        cov_mid = 0.5 * (cov_mid + cov_mid.T) + np.eye(6) * 1e-12
        asym = float(delta @ np.linalg.solve(cov_gap + np.eye(6) * 1e-12, delta))
        return T_mid, cov_mid, replace(diagnostic, symmetric=True, direction_gap=asym)

    def reassociation_hessian(self, T: np.ndarray, d_max: float, sol: SolutionTerms,
                              cov: np.ndarray) -> np.ndarray:
        """Return the bread of the point-noise sandwich: the score sum's derivative with the
        correspondences re-matched.

        The Hessian ``A`` holds the correspondences fixed. The estimate is the root of the
        score sum ``F(T) = sum_k w_k J_k^T r_k`` with the correspondences (nearest neighbours,
        Semantic-ICP's E-step) chosen at ``T`` itself, and where the point noise is of the
        order of the point spacing the neighbours follow the noise: a pose change moves the
        scores less than ``A`` says, so the estimate responds more to the noise. ``F`` is
        piecewise smooth in ``T``, so its derivative is taken by forward differences over
        ``reassociation_step`` standard deviations of the fixed-association covariance
        ``cov`` per axis (the scale at which the estimate actually varies). The result is
        symmetrised, and its eigenvalues relative to ``A`` are limited to
        [REASSOCIATION_FLOOR, 1]: re-matching to nearer neighbours lowers the cost (the
        matched cost is the lower envelope of the fixed-association costs), so it cannot add
        curvature, and the lower limit bounds the inflation (100x in variance) where the
        differences are noisy.
        """
        A = sol.A
        steps = self.config.reassociation_step * np.sqrt(np.maximum(np.diag(cov), 1e-24))
        # a dense source: the differences over evenly strided rows, scaled to all of them
        n_src = len(self.source)
        rows, scale = None, 1.0
        if n_src > REASSOCIATION_ROWS:
            stride = -(-n_src // REASSOCIATION_ROWS)
            rows = np.arange(0, n_src, stride)
            scale = n_src / len(rows)
            steps = steps * np.sqrt(scale)  # the scale at which the rows' estimate varies
            F0 = sol.scores[sol.corr.source_idx % stride == 0].sum(axis=0)
        else:
            F0 = sol.scores.sum(axis=0)
        sigma = self._sigma  # Semantic-ICP's E-step re-estimates it; keep the solution's

        def score_sum(reg: Registration, i: int) -> np.ndarray | None:
            xi = np.zeros(6)
            xi[i] = steps[i]
            T_i = T @ gtsam.Pose3.Expmap(xi).matrix()
            reg._sigma = sigma
            corr = reg.correspondences(T_i, d_max, rows)
            if len(corr) < self.config.min_inliers:
                return None
            src, tgt = reg.matched_points(corr)
            Ut = reg._whitening(corr, T_i[:3, :3])
            terms = gicp_terms(T_i, src, tgt, Ut)
            w = reg._weights(terms.mahalanobis, corr.weights)
            # sum_k w_k J_k^T r_k as one matrix-vector product
            return terms.jacobians.reshape(-1, 6).T @ (w[:, None] * terms.residuals).reshape(-1)

        # the six poses are independent: half of them on the second thread, with a twin of
        # this registration (its own neighbour caches, which only that thread uses), where
        # that thread is free; one that has not started when this thread is done with its
        # half is done here, with this registration (the same sums either way: the caches'
        # answers are exact)
        twin = self._twin()
        beside = {i: _Beside(score_sum, twin, i) for i in (3, 4, 5)}
        sums = {i: score_sum(self, i) for i in (0, 1, 2)}
        sums.update({i: done.result(self, i) for i, done in beside.items()})
        self._sigma = sigma
        D = np.empty((6, 6))
        for i in range(6):
            if sums[i] is None:
                return A
            D[:, i] = scale * (sums[i] - F0) / steps[i]
        return bread_within(A, D, REASSOCIATION_FLOOR)

    @property
    def quantisation_pitch(self) -> float | None:
        """Pitch (m) of the voxel lattice whose quantisation enters the covariance, or None."""
        if self._pitch == "unset":
            q = self.config.quantisation
            self._pitch = self._lattice if q == "auto" else q
        return self._pitch

    @property
    def _lattice(self) -> float | None:
        """The voxel lattice pitch found in the target (else the source), or None (cached)."""
        if self._found_pitch == "unset":
            self._found_pitch = lattice_pitch(self.target, self.target_tree)
            if self._found_pitch is None:
                self._source_prepared()
                if self._source_pitch == "unset":
                    self._source_pitch = lattice_pitch(self.source, self.source_tree)
                self._found_pitch = self._source_pitch
        return self._found_pitch

    def cluster_size(self, T, corr) -> float:
        """Edge (m) of the blocks of the cluster-robust sandwich."""
        if self.config.cluster_size is not None:
            return self.config.cluster_size
        if self._block is None:
            self._block = self.config.cluster_factor * self.boundary_radius
        return self._block

    @property
    def _source_radius(self) -> float:
        """:meth:`_median_radius` of the source (the reverse direction's ``boundary_radius``)."""
        self._source_prepared()
        if self._source_radius_value is None:
            self._source_radius_value = self._median_radius(self.source, self.source_tree)
        return self._source_radius_value

    def _median_radius(self, points: np.ndarray, tree: cKDTree) -> float:
        """Median distance to the k-th nearest neighbour over a sample of 500 ``points``."""
        sample = points[:: max(1, len(points) // 500)]
        dist, _ = tree.query(sample, k=min(self.config.k_neighbours, len(points)))
        return float(np.median(dist[:, -1]))

    @staticmethod
    def _scale(points: np.ndarray) -> float:
        return float(max(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))), 1e-3))

    @staticmethod
    def _normal_information(T, src, normals, w) -> np.ndarray:
        """Point-to-plane information: what the surfaces constrain (for degeneracy only).

        With the (epsilon, 1, 1) covariances even in-plane residuals carry weight 1/epsilon
        smaller, so the GICP Hessian of a single plane is merely ill-conditioned; projected on
        the target normals it is singular, which is the test we want.
        """
        R = T[:3, :3]
        J = np.empty((len(src), 6))
        # n^T [R [x_s]_x, -R] = [((R^T n) x x_s)^T, -(R^T n)^T]; the sign does not matter here
        Rn = normals @ R
        J[:, :3] = np.cross(src, Rn)
        J[:, 3:] = -Rn
        return (J * w[:, None]).T @ J


# Overlap (Registration.overlap) is estimated on this many points of each cloud; the source
# lies inside the target (a map) when it is covered to at least INSIDE_COVERAGE and the target
# is covered by at least INSIDE_MARGIN less (source_inside_target)
OVERLAP_SAMPLES = 4000
INSIDE_COVERAGE = 0.95
INSIDE_MARGIN = 0.1
# ... and its covariance (with the map-representation term) is trusted where at least this
# share is covered: in the right basin every point lies on the map's surfaces (measured 1.000
# on both rooms, 15k and 150k points), in another basin 1-2 % do not (0.983 and 0.989 in the
# two ICL-NUIM starts that converged 13-17 cm off inside the map)
INSIDE_TRUSTED_COVERAGE = 0.995

# The map term's offsets are map_error pitches where the map's surface is MAP_ERROR_THICKNESS
# pitches thick (its local layer's standard deviation; the RGB-D rooms' 3 cm centroid maps:
# median 0.42-0.56), proportionally less or more elsewhere (docs/registration_notes.md, "A single
# laser scan's map")
MAP_ERROR_THICKNESS = 0.5


def source_inside_target(source_covered: float, target_covered: float) -> bool:
    """True when the source lies inside the target: (almost) every source point is on a
    surface the target has, while the target extends beyond the source (a map, a part of it
    registered to it).

    The symmetric midpoint (``RegistrationConfig.symmetric``) cancels the matching bias of
    clouds that each have parts the other lacks (the points near the other's boundary are
    matched to its edge, in both directions). When the source lies inside the target, the
    forward matching has no such boundary, but the reverse has (the target's points just
    beyond the source's edge): the midpoint would add that bias (real RGB-D rooms against
    their 3 cm voxel map: mean NEES 33 against 6.3, 2.2 mm against 0.8 mm error;
    docs/registration_notes.md), so the forward estimate is kept.
    """
    return (source_covered >= INSIDE_COVERAGE
            and target_covered <= source_covered - INSIDE_MARGIN)



def register(source: np.ndarray, target: np.ndarray, init=None,
             config: RegistrationConfig | None = None, source_probs=None,
             target_probs=None) -> RegistrationResult:
    """Return the GICP-SE(3) (or, with both probability arrays, Semantic-ICP) result."""
    return Registration(source, target, config, source_probs, target_probs).run(init)
