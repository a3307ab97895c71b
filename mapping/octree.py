"""OcTree: an OctoMap-equivalent probabilistic occupancy octree (same maps, same files).

The tree is stored in flat numpy arrays and updated by numba kernels (``mapping._kernels``).
Every value that OctoMap computes in float32 is computed in float32 here, so log-odds, node
counts and files are bit-identical to liboctomap 1.9.7 (see docs/octree.md for the API map).
"""
from __future__ import annotations

import itertools
import math
import os
import sys
import threading
import warnings
from collections import deque
from dataclasses import dataclass

import numpy as np

from estimation.errors import OctofactorError

TREE_DEPTH = 16
#: largest leaf size (m): coordinates up to resolution * 2**15 must stay finite in float32
MAX_RESOLUTION = 1e30
KEY_OFFSET = 32768


def logodds(p: float) -> np.float32:
    """Log-odds of ``p`` as liboctomap stores it: computed in double, kept as float32."""
    return np.float32(math.log(p / (1.0 - p)))


def probability(log_odds) -> np.ndarray | float:
    """Occupancy probability ``1 - 1/(1+exp(l))`` of log-odds ``l`` (scalar or array)."""
    lo = np.asarray(log_odds, dtype=np.float64)
    out = 1.0 - 1.0 / (1.0 + np.exp(lo))
    return float(out) if out.ndim == 0 else out


class OctreeError(OctofactorError):
    """An octree operation was given input it cannot work with."""


@dataclass(frozen=True)
class Leaves:
    """All leaves (or the leaves in a box) in liboctomap's iterator order (pre-order, child 0..7).

    Attributes
    ----------
    keys : (M,3) uint16 node-centre keys at the leaf's depth (OcTreeKey of the iterator)
    depths : (M,) uint8 leaf depths (16 = finest)
    centers : (M,3) float64 metric centres (keyToCoord(key, depth))
    sizes : (M,) float64 edge lengths res * 2**(16-depth)
    log_odds : (M,) float32 stored log-odds
    """

    keys: np.ndarray
    depths: np.ndarray
    centers: np.ndarray
    sizes: np.ndarray
    log_odds: np.ndarray

    def __len__(self) -> int:
        return int(self.depths.shape[0])

    @property
    def occupied(self) -> np.ndarray:
        """(M,) bool, log-odds >= 0 (the default occupancy threshold is applied by the tree)."""
        return self.log_odds >= 0


@dataclass(frozen=True)
class SearchResult:
    """Result of :meth:`OcTree.search` for N points.

    Attributes
    ----------
    known : (N,) bool, a node exists there (False = unknown space)
    log_odds : (N,) float32, NaN where unknown
    depths : (N,) uint8, depth of the node found (a pruned leaf can be above the asked depth)
    """

    known: np.ndarray
    log_odds: np.ndarray
    depths: np.ndarray


@dataclass(frozen=True)
class RayResult:
    """Result of :meth:`OcTree.cast_ray` for N rays (liboctomap castRay semantics).

    Attributes
    ----------
    hit : (N,) bool, castRay's return value (an occupied cell was reached)
    ends : (N,3) float32, the centre of the cell where each ray stopped (NaN if not cast)
    valid : (N,) bool, False when the origin is out of the map or the direction is zero
    """

    hit: np.ndarray
    ends: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True)
class InsertStats:
    """What :meth:`OcTree.insert_point_cloud` did with a scan.

    Attributes
    ----------
    n_points : points given
    n_free, n_occupied : distinct cells updated as free / occupied
    n_nonfinite : NaN/inf points skipped
    n_out_of_bounds : endpoints outside the map (no occupied update)
    """

    n_points: int
    n_free: int
    n_occupied: int
    n_nonfinite: int
    n_out_of_bounds: int


def as_points3(points, what: str = "points", dtype=np.float32) -> np.ndarray:
    """``points`` as a C-contiguous (N, 3) array; one point (3,) becomes (1, 3). Anything
    else (an (N, 2) cloud, a flat list of 3N numbers) is an :class:`OctreeError` naming the
    argument, instead of numpy's reshape error or a silently reinterpreted array."""
    try:
        arr = np.asarray(points, dtype=dtype)
    except (TypeError, ValueError):
        raise OctreeError(f"{what} must be an (N, 3) array of numbers") from None
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise OctreeError(f"{what} must be an (N, 3) array, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def as_point3(point, what: str = "origin", dtype=np.float32) -> np.ndarray:
    """``point`` as a (3,) array (also from (1, 3) or (3, 1)); anything else is an
    :class:`OctreeError` naming the argument."""
    try:
        arr = np.asarray(point, dtype=dtype)
    except (TypeError, ValueError):
        raise OctreeError(f"{what} must be 3 numbers (x, y, z)") from None
    if arr.size != 3 or arr.ndim > 2:
        raise OctreeError(f"{what} must be 3 numbers (x, y, z), got shape {arr.shape}")
    return arr.reshape(3)


def _k():
    """The numba kernels (mapping/_kernels.py): compiled ahead of time when the project was
    set up, numba's JIT otherwise (estimation/aot.py)."""
    from estimation.aot import kernels

    return kernels("mapping._kernels")


# Rays of one scan are marked on several threads (numba's thread count, NUMBA_NUM_THREADS):
# the scan is sorted by ray direction once (kernels.sort_rays: alike rays in a row mark
# faster; a share sorted on its own groups fewer alike rays and marked 5-10% slower, more than
# the sort the threads would share), then each thread takes every n-th block of
# _PARALLEL_BLOCK sorted rays (directions differ in ray length, so contiguous halves would be
# unbalanced) and marks it into its own bricks, which are then OR-ed brick by brick. Key sets
# are a union over the rays, so neither the order nor the split changes them: the maps stay
# bit-identical. Below _PARALLEL_MIN_CHUNK points per thread the threads cost more than they
# save.
_PARALLEL_MIN_CHUNK = 16384
_PARALLEL_BLOCK = 4096
_EXECUTOR = None
# dense marking grids (kernels.scan_marks), kept zeroed between scans so that a scan does not
# pay for fresh pages: a pool of buffers, one per concurrent share
_GRID_POOL: list = []
_GRID_LOCK = threading.Lock()
# marking path: 0 = automatic (dense grid, brick grid or hashed bricks by the scan's extent);
# tests set 1 (brick grid) or 2 (hashed bricks only) to check every path against liboctomap
_MARK_PATH = 0


def _num_threads() -> int:
    """numba's thread count (NUMBA_NUM_THREADS), with a threading layer that loads quietly.

    The rays are marked on our own threads (``_executor``), not by numba ``parallel=True``
    kernels, so numba's threading layer only answers this count. Left to itself numba tries TBB
    first and warns on every run when the system's TBB is too old (Debian's 2021.5); "omp" (the
    GNU OpenMP runtime Open3D loads anyway), then numba's built-in "workqueue", load without a
    warning, and the layer does not change the insertion speed (benchmarks/octree.py,
    docs/octree.md). NUMBA_THREADING_LAYER(_PRIORITY) in the environment still wins.

    A process whose kernels were all compiled ahead of time (estimation/aot.py) has not
    imported numba: it reads the count as numba does (NUMBA_NUM_THREADS, else the processors
    this process may run on) instead of importing numba for it (0.15-0.2 s).
    """
    if "numba" not in sys.modules:
        try:
            count = int(os.environ.get("NUMBA_NUM_THREADS", ""))
        except ValueError:
            count = 0
        if count < 1:
            count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
                os.cpu_count() or 1)
        return max(1, count)
    import numba

    if not any(k in os.environ for k in ("NUMBA_THREADING_LAYER",
                                         "NUMBA_THREADING_LAYER_PRIORITY")):
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
    return numba.get_num_threads()


def _executor(n_workers: int):
    global _EXECUTOR
    if _EXECUTOR is None or _EXECUTOR._max_workers < n_workers:
        from concurrent.futures import ThreadPoolExecutor

        _EXECUTOR = ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="octree")
    return _EXECUTOR


def _scan_updates(pts: np.ndarray, origin: np.ndarray, res: float, max_range: float,
                  discretize: bool, hit_log: np.float32, miss_log: np.float32,
                  max_shares: int | None = None):
    """A scan's sorted codes, their log-odds updates, the number of hit cells and the counters
    (non-finite, out of bounds, failed): the rays marked in shares on numba's threads
    (with ``discretize``, one ray per endpoint voxel centre). ``max_shares=1`` marks on the
    calling thread alone (a scan of ``OcTree.insert_point_clouds``, already on a worker)."""
    k = _k()
    get_num_threads = _num_threads

    skipped = (0, 0)
    if discretize:
        pts, *skipped = k.discretize_points(pts, res)
    n = pts.shape[0]
    n_chunks = max(1, min(get_num_threads(), n // _PARALLEL_MIN_CHUNK,
                          max_shares or get_num_threads()))
    block = _PARALLEL_BLOCK if n_chunks > 1 else max(n, 1)
    empty = np.zeros(0, np.uint8)
    with _GRID_LOCK:
        grids = [_GRID_POOL.pop() if _GRID_POOL else empty for _ in range(n_chunks)]
    parts = []
    presorted = n_chunks > 1
    if presorted:
        pts = k.sort_rays(pts, origin)
        ex = _executor(n_chunks - 1)
        futures = [ex.submit(k.sorted_scan_marks, pts, origin, res, max_range, c, n_chunks,
                             block, grids[c], _MARK_PATH, True) for c in range(n_chunks - 1)]
    # the calling thread marks the last share (the kernels release the GIL)
    last = k.sorted_scan_marks(pts, origin, res, max_range, n_chunks - 1, n_chunks, block,
                               grids[-1], _MARK_PATH, presorted)
    if n_chunks > 1:
        parts = [f.result() for f in futures]
    parts.append(last)
    with _GRID_LOCK:
        # the kernels leave the grids zeroed; keep at most one per thread
        _GRID_POOL.extend(p[6] for p in parts if p[6].shape[0])
        del _GRID_POOL[get_num_threads():]
    tab_keys, tab_vals, pool, bcodes, nb = parts[0][:5]
    for p in parts[1:]:
        tab_keys, tab_vals, pool, bcodes, nb = k.unite_marks(tab_keys, tab_vals, pool, bcodes,
                                                             nb, p[2], p[3], p[4])
    codes, upd, n_hit = k.emit_updates(pool, bcodes, nb, hit_log, miss_log)
    counts = [sum(int(p[5][j]) for p in parts) for j in (1, 2, 3)]
    return (codes, upd, int(n_hit), counts[0] + int(skipped[0]), counts[1] + int(skipped[1]),
            counts[2])


def _in_order(fn, items, threads: int):
    """``fn(item)`` for each of ``items``, yielded in order, computed on ``threads`` threads
    (at most 2 threads + 1 in flight; the rest are not started once the consumer stops)."""
    if threads < 2:
        yield from map(fn, items)
        return
    executor = _executor(threads)
    items = iter(items)
    pending = deque(executor.submit(fn, item) for item in itertools.islice(items, 2 * threads + 1))
    try:
        while pending:
            result = pending.popleft().result()
            pending.extend(executor.submit(fn, item) for item in itertools.islice(items, 1))
            yield result
    finally:
        for future in pending:
            future.cancel()


def _checked_scan(points, origin) -> tuple[np.ndarray, np.ndarray]:
    pts = as_points3(points, "points")
    o = as_point3(origin, "origin")
    if not np.isfinite(o).all():
        raise OctreeError(f"sensor origin must be finite, got {o.tolist()}")
    return pts, o


class OcTree:
    """Probabilistic occupancy octree with liboctomap's semantics, defaults and file formats.

    Parameters
    ----------
    resolution : leaf edge length in metres
    prob_hit, prob_miss : sensor model (probabilities), stored as float32 log-odds
    clamping_thres_min, clamping_thres_max : clamping (probabilities)
    occupancy_thres : occupancy threshold (probability); log-odds >= threshold is occupied

    Attributes
    ----------
    resolution : float
    prob_hit_log, prob_miss_log, clamp_min_log, clamp_max_log, occupancy_thres_log : np.float32
    tree_type : "OcTree" (or "ColorOcTree" for a tree read from such a file)
    """

    tree_type = "OcTree"

    def __init__(self, resolution: float, prob_hit: float = 0.7, prob_miss: float = 0.4,
                 clamping_thres_min: float = 0.1192, clamping_thres_max: float = 0.971,
                 occupancy_thres: float = 0.5):
        resolution = float(resolution)
        if not resolution > 0 or not math.isfinite(resolution):
            raise OctreeError(f"resolution must be positive, got {resolution}")
        if resolution > MAX_RESOLUTION:
            raise OctreeError(f"resolution must be <= {MAX_RESOLUTION:g} m (float32 voxel "
                              f"coordinates), got {resolution}")
        for name, p in (("prob_hit", prob_hit), ("prob_miss", prob_miss),
                        ("clamping_thres_min", clamping_thres_min),
                        ("clamping_thres_max", clamping_thres_max),
                        ("occupancy_thres", occupancy_thres)):
            if not isinstance(p, (int, float, np.floating, np.integer)) or not 0 < p < 1:
                raise OctreeError(f"{name} must be a probability strictly between 0 and 1, "
                                  f"got {p!r}")
        if not clamping_thres_min <= clamping_thres_max:
            raise OctreeError(f"clamping_thres_min ({clamping_thres_min}) must not exceed "
                              f"clamping_thres_max ({clamping_thres_max})")
        self.resolution = resolution
        self.prob_hit_log = logodds(prob_hit)
        self.prob_miss_log = logodds(prob_miss)
        self.clamp_min_log = logodds(clamping_thres_min)
        self.clamp_max_log = logodds(clamping_thres_max)
        self.occupancy_thres_log = logodds(occupancy_thres)
        self.color = None  # (slots, 3) uint8 for ColorOcTree
        self.clear()

    # ------------------------------------------------------------------ storage
    def clear(self) -> None:
        """Delete every node (an empty tree has no root)."""
        self._alloc(16)
        self._has_root = False
        self._cache = None

    def _alloc(self, n_blocks: int) -> None:
        n = n_blocks * 8
        self._val = np.zeros(n, np.float32)
        self._first = np.full(n, -1, np.int32)
        self._cmask = np.zeros(n, np.uint8)
        self._free = np.zeros(n_blocks, np.int64)
        self._state = np.array([0, 1], np.int64)  # free-stack size, next unused block

    def _ensure_blocks(self, extra: int) -> None:
        cap = self._free.shape[0]
        need = int(self._state[1]) + int(extra)
        if need <= cap:
            return
        new_cap = max(need, int(cap * 1.25) + 16)
        n_old = cap * 8
        # slots beyond the used blocks are written before they are read: no initialisation
        val = np.empty(new_cap * 8, np.float32)
        first = np.empty(new_cap * 8, np.int32)
        cmask = np.empty(new_cap * 8, np.uint8)
        val[:n_old] = self._val
        first[:n_old] = self._first
        cmask[:n_old] = self._cmask
        free = np.zeros(new_cap, np.int64)
        free[:cap] = self._free
        self._val, self._first, self._cmask, self._free = val, first, cmask, free
        if self.color is not None:
            color = np.full((new_cap * 8, 3), 255, np.uint8)
            color[:n_old] = self.color
            self.color = color

    def _changed(self) -> None:
        self._cache = None

    def _structure(self):
        """Cached pre-order listing (nodes, depths, keys) of the current tree."""
        if self._cache is None:
            nodes, depths, keys = _k().preorder(self._first, self._cmask, self._has_root)
            self._cache = (nodes, depths, keys)
        return self._cache

    # ------------------------------------------------------------------ parameters
    @property
    def root_log_odds(self) -> float | None:
        return float(self._val[0]) if self._has_root else None

    def _check_updatable(self) -> None:
        if self.color is not None:
            raise OctreeError("ColorOcTree maps read from files are read-only here "
                              "(colour fusion is not implemented)")

    # ------------------------------------------------------------------ keys
    def coord_to_key(self, points) -> np.ndarray:
        """Keys (N,3) uint16 of points, ``floor(c/res) + 32768`` (coordToKey, no bounds check)."""
        pts = as_points3(points, dtype=np.float64)
        k = np.floor((1.0 / self.resolution) * pts.astype(np.float32).astype(np.float64))
        return (k.astype(np.int64) + KEY_OFFSET).astype(np.uint16)

    def coord_to_key_checked(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(keys (N,3) uint16, valid (N,) bool) like coordToKeyChecked (float32 coordinates)."""
        pts = as_points3(points)
        k = _k().coords_to_keys(pts, 1.0 / self.resolution)
        valid = (k >= 0).all(axis=1)
        return np.where(k >= 0, k, 0).astype(np.uint16), valid

    def key_to_coord(self, keys, depth: int = 16) -> np.ndarray:
        """Centres (N,3) float64 of the nodes with these keys at ``depth`` (keyToCoord)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        return _key_to_coord(k, depth, self.resolution)

    def adjust_key_at_depth(self, keys, depth: int) -> np.ndarray:
        """Key of the node centre at ``depth`` containing each key (adjustKeyAtDepth)."""
        k = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        if depth >= 16:
            return k.astype(np.uint16)
        diff = 16 - depth
        return ((((k - KEY_OFFSET) >> diff) << diff) + (1 << (diff - 1)) + KEY_OFFSET).astype(
            np.uint16)

    def node_size(self, depth: int) -> float:
        """Edge length of a node at ``depth`` (0 = root)."""
        return self.resolution * float(1 << (16 - depth))

    def compute_ray_keys(self, origin, end) -> np.ndarray:
        """Keys (M,3) uint16 a ray passes through, origin cell first, end cell excluded.

        Exact computeRayKeys (float32 direction and length). Raises OctreeError when either
        point is outside the map (liboctomap returns false).
        """
        o = as_point3(origin, "origin")
        e = as_point3(end, "end")
        out = np.empty((4096, 3), np.int64)
        k = _k()
        n = k.ray_keys(o[0], o[1], o[2], e[0], e[1], e[2], self.resolution, out)
        if n < 0:
            raise OctreeError(f"ray {o.tolist()} -> {e.tolist()} leaves the map")
        if n > out.shape[0]:
            out = np.empty((n, 3), np.int64)
            k.ray_keys(o[0], o[1], o[2], e[0], e[1], e[2], self.resolution, out)
        return out[:n].astype(np.uint16)

    # ------------------------------------------------------------------ updates
    def _apply(self, codes: np.ndarray, upd: np.ndarray, lazy: bool = False) -> int:
        k = _k()
        if codes.shape[0] == 0:
            return 0
        # reserve what the batch can need at most, but not more than half the tree again:
        # apply_updates stops cleanly when it runs out and the rest is applied after growing
        used = int(self._state[1])
        most = max(used // 2, 1 << 16)
        if used + most + 17 > self._free.shape[0]:  # else the bound cannot make it grow
            self._ensure_blocks(min(k.new_block_bound(codes), most) + 17)
        root_new = not self._has_root
        if root_new:
            self._val[0] = 0.0
            self._first[0] = -1
            self._cmask[0] = 0
            self._has_root = True
        total = 0
        start = 0
        while True:
            n, stopped = k.apply_updates(
                self._val, self._first, self._cmask, self._free, self._state, codes[start:],
                upd[start:], self.clamp_min_log, self.clamp_max_log, root_new, bool(lazy))
            total += n
            if stopped < 0:
                break
            if n:
                root_new = False
            start += stopped
            self._ensure_blocks(max(int(self._state[1]) // 2, 4096))
        if root_new and total == 0 and self._first[0] < 0:
            self._has_root = False  # nothing was inserted
        self._changed()
        return total

    def insert_point_cloud(self, points, origin, max_range: float = -1.0,
                           discretize: bool = False, lazy_eval: bool = False) -> InsertStats:
        """Integrate one scan (points in the map frame, float32) seen from ``origin``.

        liboctomap insertPointCloud: every cell on a ray is updated at most once as free and
        every endpoint cell at most once as occupied; occupied wins over free; rays longer than
        ``max_range`` (if >= 0) are cut there and give no occupied endpoint. NaN/inf points are
        skipped and counted (one warning), as are endpoints outside the map. Large scans are
        marked on numba's thread count (``NUMBA_NUM_THREADS``); the result does not depend on it.
        """
        self._check_updatable()
        pts, o = _checked_scan(points, origin)
        updates = _scan_updates(pts, o, self.resolution, float(max_range), bool(discretize),
                                np.float32(self.prob_hit_log), np.float32(self.prob_miss_log))
        return self._apply_scan(pts.shape[0], updates, lazy_eval)

    def insert_point_clouds(self, scans, max_range: float = -1.0, discretize: bool = False,
                            lazy_eval: bool = False, prepare=None) -> list[InsertStats]:
        """:meth:`insert_point_cloud` for each ``(points, origin)`` of ``scans``, in order.

        The tree is the same as from inserting the scans one by one, bit for bit: a scan's
        updates depend only on its own rays, so the scans are marked on numba's thread count
        (``NUMBA_NUM_THREADS``) at the same time, a whole scan per thread, and applied to the
        tree in order on the calling thread while the next ones are marked. ``prepare``
        (optional) turns an item of ``scans`` into its ``(points, origin)`` on those threads,
        so reading or transforming a scan overlaps the work on the others (``octofactor map``
        narrows and transforms each .graph node there). At most 2 threads + 1 scans are in
        flight. Fewer scans than threads are inserted one after the other, each scan's rays
        shared among the threads as in :meth:`insert_point_cloud`. An error of a scan is
        raised when its turn comes: the scans before it are in the tree, the others are
        dropped.
        """
        self._check_updatable()
        res, hit, miss = self.resolution, np.float32(self.prob_hit_log), np.float32(
            self.prob_miss_log)

        threads = _num_threads()
        items = iter(scans)
        first = list(itertools.islice(items, threads))
        # fewer scans than threads (a single scan, say): each scan's rays in shares on all
        # threads instead, the scans one after the other
        by_scan = len(first) == threads

        def mark(item):
            points, origin = prepare(item) if prepare else item
            pts, o = _checked_scan(points, origin)
            return pts.shape[0], _scan_updates(pts, o, res, float(max_range), bool(discretize),
                                               hit, miss, max_shares=1 if by_scan else None)

        results = (_in_order(mark, itertools.chain(first, items), threads) if by_scan
                   else map(mark, first))
        stats = []
        for n_points, updates in results:
            stats.append(self._apply_scan(n_points, updates, lazy_eval))
        return stats

    def _apply_scan(self, n_points: int, updates: tuple, lazy_eval: bool) -> InsertStats:
        """Apply a scan's :func:`_scan_updates` (warning once for skipped points)."""
        codes, upd, n_occ, n_nonfinite, n_oob, _n_failed = updates
        if n_nonfinite or n_oob:
            # stacklevel 3: the caller of insert_point_cloud(s)
            warnings.warn(f"insert_point_cloud: skipped {n_nonfinite} non-finite points and "
                          f"{n_oob} endpoints outside the map", RuntimeWarning, stacklevel=3)
        self._apply(codes, upd, lazy_eval)
        return InsertStats(int(n_points), int(codes.shape[0]) - n_occ, n_occ, int(n_nonfinite),
                           int(n_oob))

    def insert_ray(self, origin, end, max_range: float = -1.0, lazy_eval: bool = False) -> None:
        """insertRay: free cells along the ray (cut at ``max_range``), the end cell occupied.

        Each ray key gets a miss, the end key a hit (no deduplication against other rays).
        """
        self._check_updatable()
        o = as_point3(origin, "origin")
        e = as_point3(end, "end")
        d = (e - o).astype(np.float32)
        length = math.sqrt(float(np.float32(np.float32(d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])))
        hit = True
        if max_range > 0 and length > max_range:
            fl = np.float32(length)
            e = (o + (d / fl).astype(np.float32) * np.float32(max_range)).astype(np.float32)
            hit = False
        keys = self.compute_ray_keys(o, e)
        # the keys of one ray are distinct, so one sorted batch equals per-key updateNode calls
        codes = np.sort(_k().keys_to_codes(np.ascontiguousarray(keys)))
        self._apply(codes, np.full(codes.shape[0], self.prob_miss_log, np.float32), lazy_eval)
        if hit:
            self.update_node(e[None, :], True, lazy_eval=lazy_eval)

    def update_node(self, points, update, lazy_eval: bool = False, keys: bool = False) -> None:
        """updateNode for N points (or keys): ``update`` is True (hit), False (miss) or log-odds.

        Applied in order; a key given twice is updated twice (like calling updateNode twice).
        """
        self._check_updatable()
        if keys:
            kk = as_points3(points, "keys", dtype=np.int64)
            valid = ((kk >= 0) & (kk < 65536)).all(axis=1)
        else:
            kk, valid = self.coord_to_key_checked(points)
        if not valid.all():
            warnings.warn(f"update_node: {int((~valid).sum())} points outside the map skipped",
                          RuntimeWarning, stacklevel=2)
        kk = np.ascontiguousarray(np.asarray(kk, dtype=np.int64)[valid])
        n = kk.shape[0]
        if isinstance(update, (bool, np.bool_)):
            upd = np.full(n, self.prob_hit_log if update else self.prob_miss_log, np.float32)
        else:
            u = np.asarray(update)
            if u.dtype == np.bool_:
                upd = np.where(u.reshape(-1)[valid] if u.ndim else u, self.prob_hit_log,
                               self.prob_miss_log).astype(np.float32)
                upd = np.broadcast_to(upd, (n,)).copy()
            else:
                upd = np.broadcast_to(np.asarray(u, np.float32).reshape(-1)[valid]
                                      if u.ndim else np.float32(u), (n,)).astype(np.float32)
        codes = _k().keys_to_codes(kk.astype(np.uint16))
        # duplicates: apply in rounds so that every occurrence counts, in order
        order = np.argsort(codes, kind="stable")
        sc = codes[order]
        rank = np.zeros(n, np.int64)
        if n:
            same = np.concatenate([[False], sc[1:] == sc[:-1]])
            grp_start = np.maximum.accumulate(np.where(~same, np.arange(n), 0))
            rank = np.arange(n) - grp_start
        for r in range(int(rank.max()) + 1 if n else 0):
            sel = order[rank == r] if r else order[rank == 0]
            self._apply(codes[sel], upd[sel], lazy_eval)

    def update_inner_occupancy(self) -> None:
        """updateInnerOccupancy: every inner node = max of its children (after lazy updates)."""
        _k().update_inner(self._val, self._first, self._cmask, self._has_root)
        self._changed()

    def prune(self) -> int:
        """prune(): collapse 8 equal leaf children, sweeping depth 15 -> 1 (liboctomap's early
        stop included). Returns the number of collapsed nodes."""
        if not self._has_root:
            return 0
        n = _k().prune_sweeps(self._val, self._first, self._cmask, self._free, self._state)
        self._changed()
        return int(n)

    def expand(self) -> None:
        """expand(): every pruned leaf is split down to depth 16 (children copy the value)."""
        self._check_updatable()
        if not self._has_root:
            return
        k = _k()
        need = k.expand_block_need(self._first, self._cmask, self._has_root)
        if need > 200_000_000:
            raise OctreeError(f"expand() would create {need * 8} nodes")
        self._ensure_blocks(need)
        k.expand_all(self._val, self._first, self._cmask, self._free, self._state,
                     self._free.shape[0])
        self._changed()

    def to_max_likelihood(self) -> None:
        """toMaxLikelihood: every node (leaves and inner) becomes clamp_max if occupied, else
        clamp_min (judged on its own stored value)."""
        if not self._has_root:
            return
        # every node converts on its own value, so one pass over all used slots is the same
        # as liboctomap's depth sweeps (unused slots are re-initialised before any use)
        used = int(self._state[1]) * 8
        v = self._val[:used]
        with np.errstate(invalid="ignore"):
            self._val[:used] = np.where(v >= self.occupancy_thres_log, self.clamp_max_log,
                                        self.clamp_min_log)
        self._changed()

    # ------------------------------------------------------------------ counts
    def size(self) -> int:
        """Number of nodes (inner + leaves, root included)."""
        return int(self._structure()[0].shape[0])

    def __len__(self) -> int:
        return self.size()

    def num_leaf_nodes(self) -> int:
        nodes = self._structure()[0]
        return int((self._first[nodes] < 0).sum())

    def num_inner_nodes(self) -> int:
        return self.size() - self.num_leaf_nodes()

    def memory_usage(self) -> int:
        """liboctomap's memoryUsage() for this tree: 320 + 16 * nodes + 64 * inner nodes."""
        n = self.size()
        return 320 + 16 * n + 64 * self.num_inner_nodes()

    def memory_bytes(self) -> int:
        """Bytes this implementation allocates for the tree (all array capacity)."""
        arrays = [self._val, self._first, self._cmask, self._free]
        if self.color is not None:
            arrays.append(self.color)
        return int(sum(a.nbytes for a in arrays))

    def compact(self) -> None:
        """Release array capacity beyond the used blocks (freed blocks inside stay reusable)."""
        used = max(int(self._state[1]), 1)
        n = used * 8
        self._val = self._val[:n].copy()
        self._first = self._first[:n].copy()
        self._cmask = self._cmask[:n].copy()
        self._free = self._free[:used].copy()
        if self.color is not None:
            self.color = self.color[:n].copy()

    # ------------------------------------------------------------------ queries
    def is_occupied(self, log_odds) -> np.ndarray:
        """log-odds >= occupancy threshold (isNodeOccupied)."""
        return np.asarray(log_odds, np.float32) >= self.occupancy_thres_log

    def is_at_threshold(self, log_odds) -> np.ndarray:
        """log-odds at or beyond a clamping bound (isNodeAtThreshold)."""
        lo = np.asarray(log_odds, np.float32)
        return (lo >= self.clamp_max_log) | (lo <= self.clamp_min_log)

    def search(self, points, depth: int = 0, keys: bool = False) -> SearchResult:
        """search(point, depth) for N points at once (depth 0 = full depth 16).

        Points outside the map are reported unknown.
        """
        if keys:
            kk = as_points3(points, "keys", dtype=np.int64)
            valid = ((kk >= 0) & (kk < 65536)).all(axis=1)
            kk = np.where(valid[:, None], kk, 0).astype(np.uint16)
        else:
            kk, valid = self.coord_to_key_checked(points)
        max_depth = 16 if depth == 0 else int(depth)
        if not 0 <= max_depth <= 16:
            raise OctreeError(f"depth must be in 0..16, got {depth}")
        k = _k()
        codes = k.keys_to_codes(np.ascontiguousarray(kk))
        idx, dep = k.search_codes(self._val, self._first, self._cmask, self._has_root, codes,
                                  max_depth)
        idx = np.where(valid, idx, -1)
        known = idx >= 0
        lo = np.where(known, self._val[np.maximum(idx, 0)], np.float32(np.nan)).astype(np.float32)
        return SearchResult(known, lo, np.where(known, dep, 0).astype(np.uint8))

    def cast_ray(self, origins, directions, ignore_unknown: bool = False,
                 max_range: float = -1.0) -> RayResult:
        """castRay for one or N rays: first occupied cell along each ray (exact semantics)."""
        o = as_points3(origins, "origins")
        d = as_points3(directions, "directions")
        if d.shape[0] == 1 and o.shape[0] > 1:
            d = np.ascontiguousarray(np.broadcast_to(d, o.shape))
        if o.shape[0] == 1 and d.shape[0] > 1:
            o = np.ascontiguousarray(np.broadcast_to(o, d.shape))
        hit, status, end = _k().cast_rays(self._val, self._first, self._cmask, self._has_root,
                                          o, d, self.resolution, self.occupancy_thres_log,
                                          bool(ignore_unknown), float(max_range))
        return RayResult(hit, end, status == 0)

    def leaves(self, bbox_min=None, bbox_max=None, max_depth: int = 0) -> Leaves:
        """All leaves as arrays, in liboctomap's leaf-iterator order.

        ``bbox_min``/``bbox_max`` keep the leaves whose node intersects the key box of the two
        corners (leaf_bbx_iterator). ``max_depth`` > 0 treats nodes at that depth as leaves.
        """
        nodes, depths, keys = self._structure()
        md = int(max_depth) if max_depth and max_depth < 16 else 16
        sel, centers, sizes, vals = _k().leaf_arrays(self._first, self._val, nodes, depths, keys,
                                                     self.resolution, md)
        keys_l = keys[sel]
        depths_l = depths[sel]
        if bbox_min is not None or bbox_max is not None:
            lo_k, ok1 = self.coord_to_key_checked(
                bbox_min if bbox_min is not None else [-1e300] * 3)
            hi_k, ok2 = self.coord_to_key_checked(
                bbox_max if bbox_max is not None else [1e300] * 3)
            lo_k = lo_k[0].astype(np.int64) if ok1[0] else np.zeros(3, np.int64)
            hi_k = hi_k[0].astype(np.int64) if ok2[0] else np.full(3, 65535, np.int64)
            half = (1 << (16 - depths_l.astype(np.int64))) >> 1
            kmin = keys_l.astype(np.int64) - half[:, None]
            kmax = kmin + np.maximum(2 * half, 1)[:, None] - 1
            kmin = np.where(depths_l[:, None] == 16, keys_l.astype(np.int64), kmin)
            kmax = np.where(depths_l[:, None] == 16, keys_l.astype(np.int64), kmax)
            inside = ((kmax >= lo_k) & (kmin <= hi_k)).all(axis=1)
            keys_l, depths_l = keys_l[inside], depths_l[inside]
            centers, sizes, vals = centers[inside], sizes[inside], vals[inside]
        return Leaves(keys_l, depths_l, centers, sizes, vals)

    def iter_leaves(self, bbox_min=None, bbox_max=None):
        """Iterate (centre (3,), size, log_odds, depth) over leaves (see :meth:`leaves`)."""
        lv = self.leaves(bbox_min, bbox_max)
        for i in range(len(lv)):
            yield lv.centers[i], float(lv.sizes[i]), float(lv.log_odds[i]), int(lv.depths[i])

    def nodes(self) -> Leaves:
        """Every node (inner and leaves) as arrays in pre-order (tree iterator)."""
        nodes, depths, keys = self._structure()
        return Leaves(keys, depths, _key_to_coord(keys.astype(np.int64), depths, self.resolution),
                      self.resolution * (2.0 ** (16 - depths.astype(np.float64))),
                      self._val[nodes].copy())

    def metric_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) corners of the leaves' bounding box (getMetricMin/Max)."""
        if not self._has_root:
            return np.zeros(3), np.zeros(3)
        lv = self.leaves()
        half = lv.sizes / 2.0
        return ((lv.centers - half[:, None]).min(axis=0),
                (lv.centers - half[:, None] + lv.sizes[:, None]).max(axis=0))

    def metric_size(self) -> np.ndarray:
        lo, hi = self.metric_bounds()
        return hi - lo

    def volume(self) -> float:
        """Volume of the metric bounding box (liboctomap volume())."""
        s = self.metric_size()
        return float(s[0] * s[1] * s[2])

    def occupied_voxels(self) -> Leaves:
        """Occupied leaves (log-odds >= occupancy threshold) as arrays."""
        lv = self.leaves()
        m = lv.log_odds >= self.occupancy_thres_log
        return Leaves(lv.keys[m], lv.depths[m], lv.centers[m], lv.sizes[m], lv.log_odds[m])

    # ------------------------------------------------------------------ files
    def write_bt(self, path, const: bool = False) -> None:
        """writeBinary: converts to max-likelihood and prunes first (like liboctomap), unless
        ``const`` (writeBinaryConst)."""
        from . import io

        if not const:
            self.to_max_likelihood()
            self.prune()
        io.write_bt(self, path)

    def write_ot(self, path) -> None:
        """write(): the full tree with every stored log-odds (.ot, lossless)."""
        from . import io

        io.write_ot(self, path)

    def write(self, path) -> None:
        """Write .bt or .ot by the file extension."""
        if str(path).lower().endswith(".bt"):
            self.write_bt(path)
        else:
            self.write_ot(path)

    @classmethod
    def read(cls, path) -> OcTree:
        """Read a .bt or .ot file (the magic line decides); FormatError on bad input."""
        from . import io

        return io.read_tree(path)

    def to_bytes_bt(self) -> bytes:
        from . import io

        return io.bt_bytes(self)

    def to_bytes_ot(self) -> bytes:
        from . import io

        return io.ot_bytes(self)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(resolution={self.resolution}, nodes={self.size()}, "
                f"leaves={self.num_leaf_nodes()})")


def _key_to_coord(keys: np.ndarray, depth, res: float) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.int64)
    if depth.ndim == 0:
        depth = np.full(keys.shape[0], int(depth), np.int64)
    diff = (16 - depth).astype(np.float64)[:, None]
    scale = 2.0 ** diff
    c = (np.floor((keys.astype(np.float64) - 32768.0) / scale) + 0.5) * (res * scale)
    return np.where(depth[:, None] == 0, 0.0, c)
