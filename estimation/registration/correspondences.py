"""Per-point GICP covariances and nearest-neighbour correspondences (geometric and semantic).

Everything here takes arrays (``points`` (N, 3), ``probs`` (N, C)) and returns arrays or
small dataclasses; KD-trees are :class:`scipy.spatial.cKDTree`.
"""
from __future__ import annotations

import copy
import hashlib
import os
import threading
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ..aot import kernels
from ..errors import EstimationError

# compiled ahead of time by `make setup` (estimation/aot.py), numba's JIT otherwise
_kernels = kernels("estimation.registration._kernels")


_QUERY_THREADS = threading.local()


def kd_tree(points: np.ndarray) -> cKDTree:
    """The KD-tree of ``points`` that every query here uses: split at the sliding midpoint
    (``balanced_tree=False``) rather than the median. Its queries answer the same (exact
    k-NN) and were no slower; it is built in 40 % less time (measured on two cores: the scan's
    42k-point raw half 10.1 -> 6.0 ms, a TUM raw half's 358k points 101 -> 62 ms; k=20 and
    k=8 queries 0-7 % faster)."""
    return cKDTree(points, balanced_tree=False)


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # (not on every platform)
        return max(os.cpu_count() or 1, 1)


def threads_beside() -> int:
    """The threads each of a registration's two threads may use: half the cores (one on
    two; its KD-tree queries, :func:`queries_beside`, and BLAS, ``Registration.run``)."""
    return max(_cores() // 2, 1)


def _workers(n: int, k: int = 1) -> int:
    """Threads for a KD-tree query of n points, k neighbours: starting threads costs more
    than small queries gain; half the cores (one on two) inside :func:`queries_beside`."""
    if n * (1 + k // 4) < 5000:
        return 1
    return getattr(_QUERY_THREADS, "workers", -1)


@contextmanager
def queries_beside():
    """KD-tree queries on this thread use half the cores (one thread each on two cores)
    while inside: for work run beside another thread's (a registration's two threads).
    Measured on two cores (in-process A/B, bit-identical results): a query on two threads
    beside the other thread's work was slower than on one; one each took KITTI at
    0.1-0.25 m 7-8 % less time a registration and the rooms 1.5-5 %."""
    previous = getattr(_QUERY_THREADS, "workers", None)
    _QUERY_THREADS.workers = threads_beside()
    try:
        yield
    finally:
        if previous is None:
            del _QUERY_THREADS.workers
        else:
            _QUERY_THREADS.workers = previous


def point_covariances(points: np.ndarray, k: int = 20, epsilon: float = 1e-3,
                      tree: cKDTree | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """Return the (N, 3, 3) plane-regularised GICP covariance of every point (or of ``rows``).

    The covariance of the ``k`` nearest neighbours is eigen-decomposed and its eigenvalues
    replaced by ``(epsilon, 1, 1)`` (Segal et al. 2009, the C_k of eq. (3) in Nakamura et al.):
    each point is modelled as a small disc of its local surface, so the residual along the
    surface normal dominates. With fewer than 3 points the identity is returned.
    """
    return neighbourhoods(points, k, epsilon, tree, rows)[0]


def neighbourhoods(points: np.ndarray, k: int = 20, epsilon: float = 1e-3,
                   tree: cKDTree | None = None, rows: np.ndarray | None = None,
                   radius: float | None = None, min_points: int = 6,
                   k_max: int = 27, thickness: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (covariances (M, 3, 3), local means (M, 3) or None) from ONE k-NN query.

    Covariances as :func:`point_covariances`; with ``radius`` also :func:`local_means` (the
    mean of the ``k_max`` nearest points within ``radius``), which share the query. With
    ``thickness`` (M,), each neighbourhood's standard deviation along its normal is written
    into it (0 where fewer than 3 points).
    """
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    n = len(points)
    query = points if rows is None else points[rows]
    if thickness is None:
        thickness = np.empty(len(query))
    if n < 3:
        covs = np.broadcast_to(np.eye(3), (len(query), 3, 3)).copy()
        thickness[:] = 0.0
        return covs, (None if radius is None else query.copy())
    k_cov = int(min(max(k, 3), n))
    k_query = k_cov if radius is None else int(min(max(k_cov, k_max), n))
    tree = kd_tree(points) if tree is None else tree
    dist, idx = tree.query(query, k=k_query, workers=_workers(len(query), k_query))
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    covs = _kernels.neighbour_covariances(points, np.ascontiguousarray(idx[:, :k_cov]),
                                          float(epsilon), thickness)
    if radius is None:
        return covs, None
    return covs, _means_within(points, query, dist[:, :k_max], idx[:, :k_max], radius,
                               min_points)


def _means_within(points, query, dist, idx, radius, min_points) -> np.ndarray:
    inside = dist <= radius
    counts = inside.sum(axis=1)
    means = np.einsum("nk,nki->ni", inside.astype(float), points[idx]) \
        / np.maximum(counts, 1)[:, None]
    few = counts < min_points
    means[few] = query[few]
    return means


# rows a thread takes at a time while another computes rows of the same LazyCovariances
SHARED_CHUNK = 256


class LazyCovariances:
    """Per-point GICP covariances (and local means) computed on first use, row by row, cached.

    ICP only ever touches the target points near the source: in the room benchmark (10k
    source / 30k target points) 80 % of the target covariances are never needed, and their
    k-NN queries were the largest single cost of a registration. With ``radius`` the local
    means (:func:`local_means`) of the same rows come from the same query.
    """

    def __init__(self, points: np.ndarray, tree: cKDTree, k: int, epsilon: float,
                 radius: float | None = None, min_points: int = 6):
        self.points = points
        self.tree = tree
        self.k = k
        self.epsilon = epsilon
        self.radius = radius
        self.min_points = min_points
        self.values = np.empty((len(points), 3, 3))
        self.thickness_values = np.empty(len(points))
        self.mean_values = None if radius is None else np.empty((len(points), 3))
        self.done = np.zeros(len(points), bool)
        self._rank: np.ndarray | None = None
        # the rows a thread is computing now, and how many threads are (_fill)
        self._claimed = np.zeros(len(points), bool)
        self._computing = 0
        self._changed = threading.Condition()

    def _fill(self, idx: np.ndarray, wait: bool = True) -> None:
        # Two threads may fill rows at once (a symmetric registration's two directions, the
        # preparation of the next ones: Registration._prepare_forward). Each row is computed
        # once: a thread claims the rows it computes (under the lock, which is not held while
        # computing) and computes those no other thread has claimed; the rows another thread
        # is computing it waits for (``wait``: rows needed now) or leaves to it (a prefetch).
        # While another thread computes rows, it takes its own in chunks, so that the two
        # share them. A row is marked done only after its values are written. (Both threads
        # computing the rows both needed took the simulated room's first iteration 6-10 ms
        # more; a row's values do not depend on which thread computes it.)
        missing = idx[~self.done[idx]]
        if not len(missing):
            return
        rows = np.unique(missing)
        if len(rows) > 64:
            # in the KD-tree's leaf order: neighbouring queries walk the same nodes (a tenth
            # faster than the cloud's own order, e.g. a voxel filter's hash order); each
            # row's neighbours do not depend on the order
            rows = rows[np.argsort(self._leaf_rank[rows])]
        while True:
            with self._changed:
                free = rows[~(self.done[rows] | self._claimed[rows])]
                if not len(free):
                    if not wait or self.done[rows].all():
                        return
                    self._changed.wait()  # (for rows another thread is computing now)
                    continue
                if self._computing:
                    free = free[:SHARED_CHUNK]
                self._claimed[free] = True
                self._computing += 1
            try:
                self._compute(free)
            finally:
                with self._changed:
                    self._claimed[free] = False
                    self._computing -= 1
                    self._changed.notify_all()

    def _compute(self, rows: np.ndarray) -> None:
        thickness = np.empty(len(rows))
        covs, means = neighbourhoods(self.points, self.k, self.epsilon, self.tree, rows,
                                     self.radius, self.min_points, thickness=thickness)
        self.values[rows] = covs
        self.thickness_values[rows] = thickness
        if means is not None:
            self.mean_values[rows] = means
        self.done[rows] = True

    @property
    def _leaf_rank(self) -> np.ndarray:
        """Each point's position in the KD-tree's leaf order (a spatially coherent order)."""
        if self._rank is None:
            rank = np.empty(len(self.points), np.int64)
            rank[self.tree.indices] = np.arange(len(self.points))
            self._rank = rank
        return self._rank

    def prefetch(self, idx: np.ndarray, chunk: int = 512,
                 stop: threading.Event | None = None) -> None:
        """Compute the missing rows of ``idx`` in chunks of ``chunk`` (in leaf order), from a
        second thread: rows another thread computes meanwhile are left to it, and ``stop``
        (set) ends it between chunks."""
        rows = np.unique(idx[~self.done[idx]])
        rows = rows[np.argsort(self._leaf_rank[rows])]
        for start in range(0, len(rows), chunk):
            if stop is not None and stop.is_set():
                return
            self._fill(rows[start:start + chunk], wait=False)

    def fill_beside(self, idx: np.ndarray, submit) -> None:
        """Compute the missing rows of ``idx``: the second half (in leaf order) through
        ``submit(function, *args)`` (another thread's executor), the first on this thread;
        then any of them the other thread has not taken yet, and wait for the rest."""
        rows = np.unique(idx[~self.done[idx]])
        rows = rows[np.argsort(self._leaf_rank[rows])]
        half = len(rows) // 2
        submit(self.prefetch, rows[half:], SHARED_CHUNK)
        self._fill(rows[:half])
        self._fill(rows)

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        self._fill(idx)
        return self.values[idx]

    def filled(self, idx: np.ndarray) -> np.ndarray:
        """Return the whole (N, 3, 3) array with (at least) the rows ``idx`` computed."""
        self._fill(idx)
        return self.values

    def thickness(self, idx: np.ndarray) -> np.ndarray:
        """Return the neighbourhoods' thickness (m, along their normals) of rows ``idx``."""
        self._fill(idx)
        return self.thickness_values[idx]

    def means(self, idx: np.ndarray) -> np.ndarray:
        """Return the local means of rows ``idx`` (requires ``radius``)."""
        self._fill(idx)
        return self.mean_values[idx]

    def all(self) -> np.ndarray:
        """Return every covariance (computing the missing ones)."""
        return self[np.arange(len(self.points))]


def local_means(points: np.ndarray, tree: cKDTree, radius: float, min_points: int = 6,
                rows: np.ndarray | None = None, k_max: int = 27) -> np.ndarray:
    """Return each point's local surface position: the mean of its neighbours within ``radius``.

    The mean runs over the ``k_max`` nearest points within ``radius`` (the point itself
    included; 27 = a whole 3x3x3 voxel block). Where fewer than ``min_points`` lie there, the
    sample itself is returned: a mean of a few scattered samples says nothing about the
    surface. On a voxel-centre cloud (an octree map) a radius of sqrt(3) times the resolution
    averages the occupied voxels of the 3x3x3 block around each centre, which removes the
    +-half-voxel quantisation that nearest-neighbour matching otherwise turns into a pose bias
    (docs/registration_notes.md).
    """
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    query = points if rows is None else points[rows]
    k = int(min(k_max, len(points)))
    dist, idx = tree.query(query, k=k, workers=_workers(len(query), k))
    dist, idx = dist.reshape(len(query), k), idx.reshape(len(query), k)
    return _means_within(points, query, dist, idx, radius, min_points)


def lattice_pitch(points: np.ndarray, tree: cKDTree | None = None, sample: int = 1000,
                  tol: float = 1e-3, share: float = 0.9) -> float | None:
    """Return the pitch (m) of the cubic lattice the points sit on, or None if they do not.

    Voxel-centre clouds (an octree map's occupied voxels) have their coordinates on
    ``offset + k * pitch``. The candidate pitch is the median non-zero per-axis difference
    between ``sample`` points and their nearest neighbours in the whole cloud (``tree``, built
    if not given; adjacent voxels on a dense map); it is accepted when
    at least ``share`` of the sampled points lie on one lattice of that pitch to ``tol``
    pitches (float32 files included; pruned octree nodes, whose centres sit half a voxel off,
    may make up the rest). A measured cloud, a voxel filter that averages points, or a thin
    subsample whose neighbours are several voxels apart gives None.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 10:
        return None
    sel = points[:: max(1, len(points) // sample)]
    tree = kd_tree(points) if tree is None else tree
    _, j = tree.query(sel, k=2)
    diffs = np.abs(sel - points[j[:, 1]]).ravel()
    extent = float(np.ptp(sel, axis=0).max())
    diffs = diffs[diffs > 1e-9 * max(extent, 1.0)]
    if len(diffs) == 0:
        return None
    pitch = float(np.median(diffs))
    phase = sel / pitch
    best = 0.0
    for ref in phase[:8]:  # a reference point on the main lattice (not a pruned node)
        off = np.abs((phase - ref + 0.5) % 1.0 - 0.5)
        best = max(best, float(np.mean(np.all(off < tol, axis=1))))
    return pitch if best >= share else None


# Voxel-centroid maps (voxel_grid): the grid is accepted when the mean over the axes of the
# resultant length of exp(2 pi i x / pitch) reaches GRID_MIN_RESULTANT on each axis (measured:
# 0.17-0.31 at the true pitch on real rooms' 2.5-5 cm maps, ours and Open3D's
# voxel_down_sample; none of the raw or noisy clouds passed); at most GRID_MAX_SHARED of the
# points may then share a cell (a centroid within a hair of a wall of its cell)
GRID_MIN_RESULTANT = 0.15
VOXELISED_RESULTANT = 0.12  # looks_voxelised
GRID_MAX_SHARED = 0.1
GRID_SAMPLE = 600
GRID_REFINE_SAMPLE = 4000
GRID_TABLE_CELLS = 4_000_000  # a dense lookup table up to 16 MB (a 6 x 6 x 3 m room at 3 cm)
_GRID_CACHE: OrderedDict = OrderedDict()
_GRID_CACHE_SIZE = 4


def _resultants(x: np.ndarray, frequencies: np.ndarray, weights: np.ndarray | None = None
                ) -> np.ndarray:
    """Return (F, 3): per candidate frequency (1 / pitch, evenly spaced) and axis, the
    resultant length of ``exp(2 pi i f x)`` (weighted mean over the points: ``weights``
    (N, 3)). From one frequency to the next each term turns by ``exp(2 pi i df x)``: one
    complex product per point and candidate instead of a cosine and a sine."""
    w = np.full(x.shape, 1.0 / len(x)) if weights is None else weights / weights.sum(axis=0)
    terms = w * np.exp((2j * np.pi * frequencies[0]) * x)
    turn = np.exp((2j * np.pi * (frequencies[-1] - frequencies[0])
                   / max(len(frequencies) - 1, 1)) * x)
    return _kernels.resultant_lengths(np.ascontiguousarray(terms.real),
                                      np.ascontiguousarray(terms.imag),
                                      np.ascontiguousarray(turn.real),
                                      np.ascontiguousarray(turn.imag), len(frequencies))


def _in_plane(points: np.ndarray, tree: cKDTree, rows: np.ndarray,
              thickness: np.ndarray | None = None) -> np.ndarray:
    """Return (M, 3) ``1 - n_a^2`` of the local surface normals at ``rows``: how much axis a
    lies in the surface (a surface across axis a puts its centroids wherever the surface is
    along a, not at the cells' centres, so it says nothing about the grid's phase there).
    ``thickness`` (M,): the neighbourhoods' standard deviations along their normals."""
    cov, _ = neighbourhoods(points, 12, 1e-3, tree, rows, thickness=thickness)
    return np.clip(np.einsum("mii->mi", cov) - 1e-3, 0.0, 1.0) / (1.0 - 1e-3)


@dataclass(frozen=True)
class VoxelGrid:
    """The cubic grid a voxel-centroid map was made on: cell (i, j, k) spans
    ``origin + pitch * ([i, i + 1) x [j, j + 1) x [k, k + 1))`` (:func:`voxel_grid`).

    ``resultant``: the smallest axis's resultant length at the pitch; ``shared``: the share of
    the map's points that fell into an already occupied cell (the first one keeps it).
    """

    pitch: float
    origin: np.ndarray
    resultant: float
    shared: float
    lo: np.ndarray = field(repr=False)
    dims: np.ndarray = field(repr=False)
    cells: np.ndarray = field(repr=False)
    rows: np.ndarray = field(repr=False)

    table: np.ndarray | None = field(default=None, repr=False)
    # without a table: where each (i, j) column's cells begin in ``cells`` (a box whose
    # columns fit GRID_TABLE_CELLS; OctoMap's scan at 3 cm spans 17.5M cells in 140k columns:
    # same-voxel matching searches a column's few cells, 1.4 -> 0.3 ms for 13.5k pairs)
    columns: np.ndarray | None = field(default=None, repr=False)

    def lookup(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (hit (M,) bool, the map row of the cell each point lies in, -1 where the
        cell holds no map point)."""
        return self.rows_of_cells(self.cell_of(points))

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Return the (..., 3) integer cell (from the box's lowest cell) of each point."""
        return np.floor((points - self.origin) / self.pitch).astype(np.int64) - self.lo

    def rows_of_cells(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lookup` of (..., 3) integer cells (:meth:`cell_of`, cells beside them)."""
        inside = np.all((k >= 0) & (k < self.dims), axis=-1)
        k = np.where(inside[..., None], k, 0)
        key = (k[..., 0] * self.dims[1] + k[..., 1]) * self.dims[2] + k[..., 2]
        if self.table is not None:  # a dense table over the map's box (rooms)
            rows = np.where(inside, self.table[key], -1).astype(np.int64)
            return rows >= 0, rows
        pos = np.minimum(np.searchsorted(self.cells, key), len(self.cells) - 1)
        hit = inside & (self.cells[pos] == key)
        return hit, np.where(hit, self.rows[pos], -1)

    def same_cell(self, T: np.ndarray, source: np.ndarray, corr: Correspondences,
                  aligned: np.ndarray, target: np.ndarray, labels: np.ndarray | None = None
                  ) -> Correspondences:
        """Return ``corr`` with each pair flagged ``aligned`` matched to the map point of the
        cell its source point (``source`` moved by ``T``) lies in, where that cell holds one
        (and, with target ``labels``, of the pair's target's label); distances updated,
        weights kept. (One pass, as :meth:`lookup`; the rooms' 150k-point sources spent
        18 ms an iteration here in numpy.)"""
        table = _NO_CELLS if self.table is None else self.table
        columns = _NO_COLUMNS if self.columns is None else self.columns
        target_idx, distances = _kernels.same_voxel_pairs(
            np.ascontiguousarray(T, dtype=float), source, corr.source_idx, corr.target_idx,
            corr.distances, np.ascontiguousarray(aligned, dtype=bool), target, self.origin,
            float(self.pitch), self.lo, self.dims, table, columns, self.cells, self.rows,
            _NO_LABELS if labels is None else labels, labels is not None)
        return Correspondences(corr.source_idx, target_idx, corr.weights, distances,
                               corr.n_source)


_NO_CELLS = np.zeros(0, dtype=np.int32)
_NO_LABELS = np.zeros(0, dtype=np.int64)
_NO_COLUMNS = np.zeros(0, dtype=np.int64)


def voxel_grid(points: np.ndarray, tree: cKDTree | None = None,
               sample: GridSample | None = None) -> VoxelGrid | None:
    """Return the grid of a voxel-centroid map (one point per cell, the mean of the cell's
    points: Open3D's ``voxel_down_sample``, ``SemanticCloud.fuse_voxels``), or None.

    A cell's centroid lies inside its cell, and along a surface near the cell's centre, so on
    every axis the coordinates modulo the pitch gather about the centres' phase: the resultant
    length of ``exp(2 pi i x / pitch)`` is large at the true pitch and near zero at others or
    on a cloud that was not voxelised. Three steps over samples: the differences to the
    nearest neighbours (near multiples of the pitch) give a broad maximum; the coordinates
    themselves, whose maximum is about pitch / extent wide, are searched within 12 % of it,
    then within 0.15 % on a larger sample (the maximum interpolated by a parabola); the
    phase is the resultant's angle. Results are cached by content (a map is registered to
    many times). A voxel lattice (voxel centres, :func:`lattice_pitch`) passes too; callers
    check that first. ``sample``: the first two stages, if already taken (:func:`grid_sample`).
    """
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    key = (points.shape, hashlib.blake2b(points.tobytes(), digest_size=16).digest())
    if key in _GRID_CACHE:
        _GRID_CACHE.move_to_end(key)
        return _GRID_CACHE[key]
    grid = _find_grid(points, tree, sample)
    _GRID_CACHE[key] = grid
    if len(_GRID_CACHE) > _GRID_CACHE_SIZE:
        _GRID_CACHE.popitem(last=False)
    return grid


class GridSample(NamedTuple):
    """The first two stages of :func:`voxel_grid` on a sample of a cloud's points."""

    tree: cKDTree
    frequency: float  # the best candidate, 1 / pitch
    resultant: float  # its resultant length, mean over the axes
    centre: np.ndarray  # (3,) the sample's centre
    in_plane: np.ndarray  # (M, 3) the sample's 1 - n_a^2 (:func:`_in_plane`)
    thickness: np.ndarray  # (M,) its neighbourhoods' standard deviations along the normals


def looks_voxelised(points: np.ndarray, tree: cKDTree | None = None) -> bool:
    """True where ``points`` look like a voxel map (centroids or centres) of some pitch: the
    first two stages of :func:`voxel_grid` (a sample of 600 points) find a resultant of at
    least ``VOXELISED_RESULTANT`` (a raw scan's stays near the sample's noise, 0.05-0.09 on
    the real rooms and their parts; voxelised scans 0.16-0.63, docs/registration_notes.md).
    About 5 ms, whatever the cloud's size."""
    sample = grid_sample(points, tree)
    return sample is not None and sample.resultant >= VOXELISED_RESULTANT


def sheets_possible(sample: GridSample, angle: float, share: float, thickness: float) -> bool:
    """Whether a voxel-centroid map may hold surface layers its grid cut into sheets: on its
    :func:`grid_sample`, at least ``share`` of the points on surfaces within ``angle``
    degrees of an axis (a voxel map's grid is its frame's), their median thickness (12
    neighbours) at least ``thickness`` of the pitch found. A cheap necessary condition
    (Registration._partial_cells_grid) before the grid's full search."""
    aligned = sample.in_plane.min(axis=1) <= np.sin(np.deg2rad(angle)) ** 2
    return bool(aligned.mean() >= share
                and np.median(sample.thickness[aligned]) * sample.frequency >= thickness)


def grid_sample(points: np.ndarray, tree: cKDTree | None = None) -> GridSample | None:
    """The first two stages of :func:`voxel_grid` on a sample of ``points`` (uncached; pass
    it on to :func:`voxel_grid`, which then does not repeat them), or None (too few points,
    or coincident ones)."""
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 50:
        return None
    tree = kd_tree(points) if tree is None else tree
    sel_rows = np.arange(0, len(points), max(1, len(points) // GRID_SAMPLE))
    sel = points[sel_rows]
    dist, idx = tree.query(sel, k=7)
    spacing = float(np.median(dist[:, 1]))
    if not spacing > 0:
        return None
    near = dist[::2, 1:] < 3.0 * spacing
    diffs = (points[idx[::2, 1:]] - sel[::2, None, :])[near]
    # (candidates evenly spaced in frequency, 1 / pitch: see _resultants)
    coarse = np.linspace(1.0 / (3.0 * spacing), 1.0 / (0.8 * spacing), 60)
    f0 = coarse[int(np.argmax(_resultants(diffs, coarse).mean(axis=1)))]
    centre0 = sel.mean(axis=0)  # phases about the middle: half the lever arm of a pitch error
    extent = float(np.ptp(sel, axis=0).max())
    step = 0.25 / (f0 * max(extent, 1.0 / f0))  # a quarter of the sharp maximum's width
    fine = f0 * (1.0 + np.arange(-0.12, 0.12 + step, step))
    layers = np.empty(len(sel_rows))
    w_sel = _in_plane(points, tree, sel_rows, layers)
    score = _resultants(sel - centre0, fine, w_sel).mean(axis=1)
    best = int(np.argmax(score))
    return GridSample(tree, float(fine[best]), float(score[best]), centre0, w_sel, layers)


def _find_grid(points: np.ndarray, tree: cKDTree | None,
               sample: GridSample | None = None) -> VoxelGrid | None:
    sample = grid_sample(points, tree) if sample is None else sample
    if sample is None:
        return None
    tree, f1, centre0 = sample.tree, sample.frequency, sample.centre
    wide_rows = np.arange(0, len(points), max(1, len(points) // GRID_REFINE_SAMPLE))
    wide = points[wide_rows] - centre0
    w_wide = _in_plane(points, tree, wide_rows)
    steps = f1 * (1.0 + np.linspace(-0.0015, 0.0015, 21))
    score = _resultants(wide, steps, w_wide).mean(axis=1)
    j = int(np.clip(np.argmax(score), 1, len(steps) - 2))
    y0, y1, y2 = score[j - 1: j + 2]
    shift = 0.5 * (y0 - y2) / (y0 - 2.0 * y1 + y2) if y0 - 2.0 * y1 + y2 < 0 else 0.0
    pitch = 1.0 / float(steps[j] + np.clip(shift, -1.0, 1.0) * (steps[1] - steps[0]))
    resultant = _resultants(wide, np.array([1.0 / pitch]), w_wide)[0]
    if resultant.min() < GRID_MIN_RESULTANT:
        return None
    phase = (2.0 * np.pi) * wide / pitch
    centre = centre0 + np.arctan2((np.sin(phase) * w_wide).sum(axis=0),
                                  (np.cos(phase) * w_wide).sum(axis=0)) * pitch / (2.0 * np.pi)
    # (many points sharing cells: not a centroid map on this grid)
    return grid_cells(points, pitch, centre - 0.5 * pitch, float(resultant.min()),
                      GRID_MAX_SHARED)


def grid_cells(points: np.ndarray, pitch: float, origin: np.ndarray,
               resultant: float = float("nan"), max_shared: float = 1.0
               ) -> VoxelGrid | None:
    """Return the :class:`VoxelGrid` of ``points`` on the grid of ``pitch`` and ``origin``
    (the first point of a cell keeps it), or None where the grid's box needs more than 62
    bits or more than ``max_shared`` of the points fall into an already occupied cell."""
    keys = np.floor((points - origin) / pitch).astype(np.int64)
    lo = keys.min(axis=0)
    dims = keys.max(axis=0) - lo + 1
    if np.sum(np.log2(dims.astype(float))) >= 62:
        return None
    k = keys - lo
    linear = (k[:, 0] * dims[1] + k[:, 1]) * dims[2] + k[:, 2]
    order = np.argsort(linear, kind="stable")
    cells = linear[order]
    repeat = np.flatnonzero(cells[1:] == cells[:-1]) + 1
    shared = len(repeat) / len(points)
    if shared > max_shared:
        return None
    keep = np.ones(len(cells), bool)
    keep[repeat] = False
    cells, rows = cells[keep], order[keep]
    table = columns = None
    if int(np.prod(dims)) <= GRID_TABLE_CELLS:
        table = np.full(int(np.prod(dims)), -1, dtype=np.int32)
        table[cells] = rows
    elif int(dims[0] * dims[1]) <= GRID_TABLE_CELLS:
        # the sorted cells of each (i, j) column begin at columns[i dims_1 + j]
        columns = np.searchsorted(cells, np.arange(dims[0] * dims[1] + 1) * dims[2])
    return VoxelGrid(pitch, origin, resultant, shared, lo, dims, cells, rows, table, columns)


@dataclass(frozen=True)
class Correspondences:
    """Matched index pairs with their E-step weights.

    Attributes
    ----------
    source_idx, target_idx : (M,) int64 -- matched rows of the source and target arrays
    weights : (M,) float -- omega_k (1 for geometric ICP; the semantic EM weight otherwise)
    distances : (M,) float -- Euclidean distance after applying the current T
    n_source : int -- source points that were queried
    """

    source_idx: np.ndarray
    target_idx: np.ndarray
    weights: np.ndarray
    distances: np.ndarray
    n_source: int

    def __len__(self) -> int:
        return len(self.source_idx)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return ``points`` (N, 3) mapped by the 4x4 ``T``."""
    return points @ T[:3, :3].T + T[:3, 3]


def nearest_correspondences(source_in_target: np.ndarray, target_tree: cKDTree,
                            d_max: float, cache: NeighbourCache | None = None,
                            rows: np.ndarray | None = None) -> Correspondences:
    """Return nearest-neighbour pairs closer than ``d_max`` (ICP's omega_i of eq. (2)).

    With a :class:`NeighbourCache` (built for this ``d_max``) the identical pairs come from
    cached candidates, re-querying only the points that moved too far; ``rows``: the cache's
    rows of the points (all, in order: None).
    """
    n = len(source_in_target)
    if cache is not None:
        dist, idx = cache.query(source_in_target, rows)
    else:
        dist, idx = target_tree.query(source_in_target, k=1, distance_upper_bound=d_max,
                                      workers=_workers(n))
    ok = np.isfinite(dist)
    src = np.nonzero(ok)[0]
    return Correspondences(src, idx[ok].astype(np.int64), np.ones(len(src)), dist[ok], n)


class NeighbourCache:
    """Exact nearest neighbours within ``d_max`` for slowly moving points, from cached candidates.

    Each row (a source point) keeps its ``k`` nearest target points within ``2 d_max`` found
    at an anchor position (distances d_1 <= ... <= d_k; d_k := 2 d_max when fewer exist: the
    row's ``bound``, every other target point is at least that far from the anchor). After
    moving by delta, every other target point is farther than ``d_k - delta``, so the
    candidates still hold the answer while ``d_1 + delta <= d_k - delta`` (the nearest is a
    candidate) or ``d_k - delta > d_max`` (nothing else lies within d_max). Near convergence
    ICP moves the source by far less than that, so the queries (the largest per-iteration
    cost) become a candidate scan; points that fail the test are queried again.

    ``size``: the rows of the cache (the source's points), for queries of some of them
    (:meth:`query`'s ``rows``); without it the first query's points are the rows.
    """

    def __init__(self, tree: cKDTree, d_max: float, k: int = 8, size: int | None = None):
        self.tree = tree
        self.points = np.ascontiguousarray(tree.data, dtype=float)
        self.d_max = float(d_max)
        self.k = int(min(max(k, 2), tree.n))
        self.size = size
        self.anchor: np.ndarray | None = None
        self.candidates: np.ndarray | None = None
        self.reach: np.ndarray | None = None
        self.bound: np.ndarray | None = None
        if size is not None:
            self._allocate(size)

    def _allocate(self, size: int) -> None:
        """Room for ``size`` rows, those never queried with a negative reach (stale) and no
        candidates; the rows there were are kept."""
        old = 0 if self.anchor is None else len(self.anchor)
        grown = (np.zeros((size, 3)), np.full((size, self.k), len(self.points), np.int64),
                 np.full(size, -1.0), np.zeros(size))
        if old:
            for new, kept in zip(grown, (self.anchor, self.candidates, self.reach, self.bound)):
                new[:old] = kept[:size]
        self.anchor, self.candidates, self.reach, self.bound = grown
        self.size = size

    def copy(self) -> NeighbourCache:
        """A copy whose rows change apart from this cache's (the tree and points shared)."""
        twin = copy.copy(self)
        for name in ("anchor", "candidates", "reach", "bound", "classes"):
            value = getattr(self, name, None)
            if value is not None:
                setattr(twin, name, value.copy())
        return twin

    def _rows(self, points: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
        """The cache rows of ``points``, room made for them."""
        if rows is None:
            if self.anchor is None or self.size != len(points):
                self.anchor = None  # other points: the rows start again
                self._allocate(len(points))
            return np.arange(len(points))
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        if len(rows) and (self.anchor is None or rows.max() >= self.size):
            self._allocate(max(int(rows.max()) + 1, self.size or 0))
        return rows

    def _refresh(self, points: np.ndarray, rows: np.ndarray) -> None:
        """Query the tree for ``points``, the positions of the cache's ``rows``."""
        radius = 2.0 * self.d_max
        dist, idx = self.tree.query(points, k=self.k, distance_upper_bound=radius,
                                    workers=_workers(len(points), self.k))
        dk = np.minimum(dist[:, -1], radius)
        self.anchor[rows], self.candidates[rows], self.bound[rows] = points, idx, dk
        # how far a point may move before its candidates can miss the answer
        self.reach[rows] = np.maximum(dk - self.d_max, 0.5 * (dk - dist[:, 0]))

    def _scanned(self, points: np.ndarray, rows: np.ndarray | None, scan) -> tuple:
        """``scan(points, rows, which)`` (a candidate-scan kernel of those of the query's
        points, ``which`` indexing them; its third output flags the stale ones) of the cache's
        ``rows``; the stale points are queried again and scanned anew."""
        points = np.ascontiguousarray(points, dtype=float)
        rows = self._rows(points, rows)
        out = scan(points, rows, slice(None))
        stale = np.nonzero(out[2])[0]
        if len(stale):
            self._refresh(points[stale], rows[stale])
            for whole, part in zip(out, scan(points[stale], rows[stale], stale)):
                whole[stale] = part
        return out

    def query(self, points: np.ndarray, rows: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """Return (distance, index) of each point's nearest target point; inf beyond d_max.
        ``rows``: the cache's rows of the points (all, in order: None)."""
        dist, idx, _ = self._scanned(points, rows, lambda p, r, _: _kernels.cached_nearest(
            p, r, self.anchor, self.reach, self.candidates, self.points, self.d_max))
        return dist, idx

    def query_with_class(self, points: np.ndarray, rows: np.ndarray | None, labels: np.ndarray,
                         want: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`query` and :meth:`nearest_of_class` in one scan of the candidates: returns
        (distance, index, class distance, class index, unresolved)."""
        want = np.ascontiguousarray(want, dtype=np.int64)
        dist, idx, _, cdist, cidx, unresolved = self._scanned(
            points, rows, lambda p, r, which: _kernels.cached_nearest_and_class(
                p, r, self.anchor, self.bound, self.reach, self.candidates, self.points,
                labels, want[which], self.d_max))
        return dist, idx, cdist, cidx, unresolved

    def outlasts(self, points: np.ndarray, motion: float, samples: int = 500) -> bool:
        """True where the median reach of a strided sample of the rows (``points``: all of
        them, in order), queried now, exceeds ``motion`` (m): most rows' candidates would
        still hold their answer after moving that far."""
        self._rows(points, None)  # (room for all of them)
        rows = np.arange(0, len(points), max(len(points) // samples, 1))
        self.query(points[rows], rows)
        return bool(np.median(self.reach[rows]) > motion)

    def nearest_of_class(self, points: np.ndarray, rows: np.ndarray, labels: np.ndarray,
                         want: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (distance, index, unresolved) of each point's nearest target point labelled
        ``want`` (target ``labels``) within d_max, from the candidates of its row where they
        decide it (exactly; :func:`class_cached_nearest`); the others are ``unresolved``.
        For rows just queried (:meth:`query`): the class of a point's geometric neighbours
        is mostly its own, so most class queries need no tree."""
        points = np.ascontiguousarray(points, dtype=float)
        return _kernels.class_cached_nearest(
            points, np.ascontiguousarray(rows, dtype=np.int64), self.anchor, self.bound,
            self.reach, self.candidates, self.points, labels,
            np.ascontiguousarray(want, dtype=np.int64), self.d_max)


class ClassNeighbourCache(NeighbourCache):
    """:class:`NeighbourCache` for class-conditioned queries: each row searches the tree of
    its own class (``classes`` (n,); Semantic-ICP's E-step sets a row's class anew where it
    asks the row for another one, :func:`_cached_class_candidates`), all rows in one pass.

    The candidates are kept as rows of the whole target (the classes' members), so one
    candidate scan (the inherited :meth:`query`) serves every class; only rows whose
    candidates can have missed the answer go back to their class's tree. Exact, like
    :class:`NeighbourCache`: it returns the nearest target point of the row's class within
    ``d_max`` (a per-class cache each cost a call per class and iteration: 24 classes made
    the E-step 3x dearer).
    """

    def __init__(self, index: SemanticIndex, d_max: float, classes: np.ndarray | None = None,
                 k: int = 8):
        self.index = index
        self.points = index.points
        self.d_max = float(d_max)
        self.k = int(max(k, 2))
        self.anchor = None
        self.size = None
        self.classes = np.zeros(0, np.int64)
        if classes is not None:
            self.classes = np.ascontiguousarray(classes, dtype=np.int64)
            self._allocate(len(self.classes))

    def _allocate(self, size: int) -> None:
        super()._allocate(size)
        grown = np.full(size, -1, np.int64)  # (-1: no class yet)
        grown[:len(self.classes)] = self.classes[:size]
        self.classes = grown

    def _refresh(self, points: np.ndarray, rows: np.ndarray) -> None:
        index, radius = self.index, 2.0 * self.d_max
        starts, grouped = _kernels.group_rows(self.classes[rows], np.ones(len(rows), bool),
                                              index.n_classes)
        for c in np.nonzero(np.diff(starts))[0]:
            tree = index.trees.get(int(c))
            part = grouped[starts[c]:starts[c + 1]]
            sel = rows[part]
            self.anchor[sel] = points[part]
            if tree is None:  # no target point of this class: never a candidate
                self.reach[sel] = np.inf
                continue
            k = min(self.k, tree.n)
            dist, idx = tree.query(points[part], k=k, distance_upper_bound=radius,
                                   workers=_workers(len(sel), k))
            dist, idx = dist.reshape(len(sel), k), idx.reshape(len(sel), k)
            found = idx < tree.n
            self.candidates[sel, :k] = np.where(found, index.members[int(c)][
                np.where(found, idx, 0)], len(index.points))
            dk = np.minimum(dist[:, -1], radius)
            reach = np.maximum(dk - self.d_max, 0.5 * (dk - dist[:, 0]))
            if k == tree.n:  # where every point of the class is a candidate: never stale
                reach[found.all(axis=1)] = np.inf
            self.reach[sel], self.bound[sel] = reach, dk


class SemanticIndex:
    """Per-class KD-trees over the target points, for class-conditioned correspondences.

    Parameters
    ----------
    points : (N, 3) target points
    probs : (N, C) class probabilities of the target points
    """

    def __init__(self, points: np.ndarray, probs: np.ndarray):
        points = np.ascontiguousarray(points, dtype=float)  # (candidate scans read it)
        probs = np.ascontiguousarray(probs, dtype=float)  # (the E-step's kernels read it)
        if probs.ndim != 2 or len(probs) != len(points):
            raise EstimationError(
                f"target probs must be (N, C) with N={len(points)}, got {probs.shape}")
        self.points = points
        self.probs = probs
        labels = np.ascontiguousarray(probs.argmax(axis=1), dtype=np.int64)
        self.labels = labels
        self.members: dict[int, np.ndarray] = {}
        self.trees: dict[int, cKDTree] = {}
        for c in np.unique(labels):
            rows = np.nonzero(labels == c)[0]
            self.members[int(c)] = rows
            self.trees[int(c)] = kd_tree(points[rows])
        # the classes that have target points, in the trees' order (the candidates' order)
        self.classes = np.fromiter(self.trees, dtype=np.int64, count=len(self.trees))

    @property
    def n_classes(self) -> int:
        return self.probs.shape[1]


def _cached_class_candidates(source_in_target: np.ndarray, source_probs: np.ndarray,
                             index: SemanticIndex, d_max: float, order: np.ndarray,
                             min_class_prob: float, caches: dict, rows: np.ndarray | None,
                             geometric: NeighbourCache | None, first_class: tuple | None,
                             rank_target: np.ndarray, rank_dist: np.ndarray) -> None:
    """:func:`semantic_correspondences`'s class candidates (its arguments) from the class
    caches, one kernel pass per rank (:func:`_kernels.class_rank_cached`): the rows whose
    class-cache row is stale (moved beyond its reach, or queried for another class) are
    queried again (:meth:`ClassNeighbourCache._refresh`) and passed again."""
    n = len(source_in_target)
    points = np.ascontiguousarray(source_in_target, dtype=float)
    order = np.ascontiguousarray(order, dtype=np.int64)
    cache_rows = np.arange(n) if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    none_f, none_i, none_b = np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool)
    if geometric is not None:
        near = geometric.anchor, geometric.bound, geometric.reach, geometric.candidates
    else:
        near = np.zeros((0, 3)), none_f, none_f, np.zeros((0, 1), np.int64)
    everyone = np.arange(n)
    for rank in range(rank_target.shape[0]):
        cache = caches.get(rank)
        if cache is None:
            cache = caches[rank] = ClassNeighbourCache(index, d_max)
        cache._rows(points, cache_rows)  # (room for the rows)
        first = first_class if rank == 0 and first_class is not None else (none_f, none_i,
                                                                            none_b)
        # (the cache's arrays, written in place by its refreshes)
        asked = order, rank, source_probs, float(min_class_prob), *first, *near, index.points
        cached = (index.labels, cache.anchor, cache.reach, cache.candidates, cache.classes,
                  float(d_max), rank_target, rank_dist)
        stale = _kernels.class_rank_cached(points, cache_rows, everyone, *asked, *cached)
        if len(stale):
            cache.classes[cache_rows[stale]] = order[stale, rank]
            cache._refresh(points[stale], cache_rows[stale])
            _kernels.class_rank_cached(points, cache_rows, stale, *asked, *cached)


def _tree_class_candidates(source_in_target: np.ndarray, source_probs: np.ndarray,
                           index: SemanticIndex, d_max: float, order: np.ndarray,
                           min_class_prob: float, rows: np.ndarray | None,
                           geometric: NeighbourCache | None, first_class: tuple | None,
                           rank_target: np.ndarray, rank_dist: np.ndarray) -> None:
    """:func:`semantic_correspondences`'s class candidates (its arguments) without class
    caches: from the geometric cache's candidates where they decide them, from the class
    trees elsewhere."""
    n = len(source_in_target)
    for rank in range(rank_target.shape[0]):
        cls_of_point = np.ascontiguousarray(order[:, rank])
        if rank == 0:  # every point
            found, points, classes = np.arange(n), source_in_target, cls_of_point
        else:  # where the class is probable enough
            found = np.nonzero(source_probs[np.arange(n), cls_of_point] >= min_class_prob)[0]
            points, classes = source_in_target[found], cls_of_point[found]
        cache_rows = found if rows is None else rows[found]
        dist = np.full(len(found), np.inf)
        j = np.full(len(found), -1, dtype=np.int64)
        ask = np.arange(len(found))  # the points the class trees answer
        if rank == 0 and first_class is not None:
            dist, j, unresolved = first_class  # (fresh arrays: filled in below)
            ask = np.nonzero(unresolved)[0]
        elif geometric is not None and len(found):
            dist, j, unresolved = geometric.nearest_of_class(points, cache_rows, index.labels,
                                                             classes)
            ask = np.nonzero(unresolved)[0]
        if len(ask):
            starts, grouped = _kernels.group_rows(classes[ask], np.ones(len(ask), bool),
                                                  index.n_classes)
            for c, tree in index.trees.items():
                part = ask[grouped[starts[c]:starts[c + 1]]]
                if len(part) == 0:
                    continue
                d, q = tree.query(points[part], k=1,
                                  distance_upper_bound=d_max, workers=_workers(len(part)))
                ok = np.isfinite(d)
                dist[part[ok]], j[part[ok]] = d[ok], index.members[c][q[ok]]
        ok = np.isfinite(dist)
        rank_target[rank, found[ok]] = j[ok]
        rank_dist[rank, found[ok]] = dist[ok]


def top_class_order(probs: np.ndarray, top: int) -> np.ndarray:
    """Return each row's ``top`` most probable classes (n, top), best first (ties: the lower
    class): the order in which :func:`semantic_correspondences` searches the classes."""
    return _kernels.top_classes(np.ascontiguousarray(probs, dtype=float),
                                int(min(top, probs.shape[1])))


def semantic_correspondences(source_in_target: np.ndarray, source_probs: np.ndarray,
                             index: SemanticIndex, d_max: float,
                             residual_sigma: float, top_classes: int = 2,
                             min_weight: float = 1e-3,
                             min_class_prob: float = 0.1,
                             nearest: tuple[np.ndarray, np.ndarray] | None = None,
                             posterior: bool = False,
                             caches: dict | None = None,
                             label_noise: float = 0.0,
                             order: np.ndarray | None = None,
                             rows: np.ndarray | None = None,
                             geometric: NeighbourCache | None = None,
                             first_class: tuple | None = None) -> Correspondences:
    """Return class-conditioned nearest neighbours and their EM weights omega_k (eq. (5)-(8)).

    Candidates: for each source point and each of its ``top_classes`` most probable classes c,
    the nearest target point whose argmax label is c (eq. (8): the correspondence is uniform
    over the nearest neighbours within the class), scored

        omega_kc  propto  p(r_kc | i_kc; T_old) * p(c | x_s) * p(c | x_t)

    with an isotropic Gaussian residual likelihood of standard deviation ``residual_sigma``.
    With ``nearest`` = (distance, index) of every source point's geometric nearest neighbour
    among all target points (distance inf where none lies within ``d_max``), that neighbour j
    is a candidate too, scored with the label agreement summed over the classes, eq. (5)'s
    ``sum_c p(c | x_s) p(c | x_t,j)``; a class candidate that is that same point is not
    counted twice.

    ``posterior=False`` returns these scores as the weights (Parkison et al.: a point whose
    labels disagree with every candidate loses its vote). ``posterior=True`` normalises them
    over each source point's candidates: the E-step posterior of which candidate is the
    correspondence. Label noise then moves a point's vote between its candidates instead of
    removing it, so Semantic-ICP degrades towards GICP as the labels get worse.

    Candidates with omega below ``min_weight`` are dropped (after normalising); classes after
    the most probable one are only searched where their probability reaches ``min_class_prob``.

    ``label_noise`` (epsilon): the chance that a label is wrong, whatever the probabilities
    say. Every label agreement becomes ``(1 - epsilon) agreement + epsilon / C`` (C classes),
    so a point whose one-hot label is wrong still votes for its geometric nearest neighbour
    instead of putting all its posterior weight on a far candidate of its (wrong) class.

    ``order``: :func:`top_class_order` of ``source_probs``, when the caller keeps it.

    ``caches``: a dict (kept by the caller for one ``d_max`` and one source) in which a
    :class:`ClassNeighbourCache` per rank is kept, so that repeated calls while the source
    moves little return the same candidates from cached ones; ``rows``: the cache rows (the
    caller's source rows) of the points (all, in order: None). ``geometric``: the
    :class:`NeighbourCache` (same ``d_max``, same rows) that has just given ``nearest``:
    a class candidate is taken from its candidates where they decide it
    (:meth:`NeighbourCache.nearest_of_class`), from the class caches elsewhere; the same
    pairs, without most of the class trees' queries. ``first_class``: that answer for the
    most probable classes, when the caller has it (:meth:`NeighbourCache.query_with_class`,
    the same scan as ``nearest``).
    """
    n, c_src = source_probs.shape
    if c_src != index.n_classes:
        raise EstimationError(
            f"source has {c_src} classes but the target has {index.n_classes}")
    top = min(int(top_classes), c_src)
    source_probs = np.ascontiguousarray(source_probs, dtype=float)
    if order is None or order.shape != (n, top):
        order = top_class_order(source_probs, top)
    nn = np.full(n, -1, dtype=np.int64)
    nn_dist = np.zeros(n)
    if nearest is not None:
        dist, j = nearest
        near = dist <= d_max
        nn[near] = j[near]
        nn_dist[near] = dist[near]
    # each rank's class candidates, by row (-1: none within d_max, or not searched)
    rank_target = np.full((top, n), -1, dtype=np.int64)
    rank_dist = np.zeros((top, n))
    if caches is not None:
        _cached_class_candidates(source_in_target, source_probs, index, d_max, order,
                                 min_class_prob, caches, rows, geometric, first_class,
                                 rank_target, rank_dist)
    else:
        _tree_class_candidates(source_in_target, source_probs, index, d_max, order,
                               min_class_prob, rows, geometric, first_class, rank_target,
                               rank_dist)
    # the candidate list: the nearest neighbours, then each rank's classes in turn (a class
    # candidate that is the point's nearest neighbour is not counted twice); eq. (5): the
    # label agreement p(c|x_s) p(c|x_t) (with label noise) times the residual likelihood
    # under T_old
    src, tgt, dist, omega = _kernels.semantic_candidates(
        nn, nn_dist, order, rank_target, rank_dist, index.classes, source_probs,
        index.probs, float(label_noise), float(residual_sigma))
    src, tgt, omega, dist = _kernels.normalise_keep(src, tgt, omega, dist, n, bool(posterior),
                                                    float(min_weight))
    return Correspondences(src, tgt, omega, dist, n)
