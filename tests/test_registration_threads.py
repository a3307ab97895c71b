"""Work a registration hands to its second thread: the same results as on one thread.

The re-matched bread's six poses (half of them on the second thread, with a twin of the
registration and copies of its neighbour caches) and the source's per-row covariances and
local means on a voxel lattice (computed row by row, on either thread)."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_registration import make_pair, one_hot
from test_registration_model_error import voxel_map_pair

from estimation.registration import Registration, RegistrationConfig, SemanticIndex, gicp
from estimation.registration.correspondences import (
    ClassNeighbourCache,
    LazyCovariances,
    NeighbourCache,
    local_means,
    neighbourhoods,
)


def _cache_arrays(cache):
    return [getattr(cache, name).copy() for name in ("anchor", "candidates", "reach", "bound")]


@pytest.mark.parametrize("kind", ["geometric", "class"])
def test_a_cache_copy_changes_apart_and_stays_exact(rng, kind):
    target = rng.uniform(0, 1, (3000, 3))
    points = rng.uniform(0, 1, (600, 3))
    if kind == "geometric":
        cache = NeighbourCache(cKDTree(target), 0.05, 8, 600)
    else:
        labels = rng.integers(0, 3, 3000)
        cache = ClassNeighbourCache(SemanticIndex(target, np.eye(3)[labels]), 0.05,
                                    rng.integers(0, 3, 600))
    cache.query(points)
    before = _cache_arrays(cache)
    twin = cache.copy()
    moved = points + rng.normal(0, 0.05, points.shape)  # far: most rows re-queried
    dist, idx = twin.query(moved)
    for kept, now in zip(before, _cache_arrays(cache)):
        np.testing.assert_array_equal(kept, now)  # the original's rows did not change
    assert not np.array_equal(twin.anchor, cache.anchor)
    np.testing.assert_array_equal(cache.query(moved)[1], idx)  # both exact: same answers
    assert twin.tree is cache.tree if kind == "geometric" else twin.index is cache.index


def _bread(reg, result, semantic_sigma):
    d_max = reg.config.max_correspondence_distance
    reg._sigma = semantic_sigma
    sol = reg.solution_terms(result.T, d_max)  # (its E-step sets the solution's sigma)
    sigma = reg._sigma
    bread = reg.reassociation_hessian(result.T, d_max, sol, result.covariance)
    assert reg._sigma == sigma  # the twin's E-steps did not change this registration's
    return bread


def test_the_rematched_bread_is_the_same_whichever_thread_computes_it(monkeypatch):
    """Semantic-ICP (class caches, the E-step's sigma): the bread with half its poses on the
    second thread equals, bit for bit, the bread with that thread busy (its tasks cancelled
    and done here); the twin's searches leave this registration's caches and sigma as they
    were."""
    source, labels_s, target, labels_t, _ = make_pair(15, 1500, 0.01)
    reg = Registration(source, target, RegistrationConfig(),
                       one_hot(labels_s, acc=0.9), one_hot(labels_t, acc=0.9))
    result = reg.run()
    sigma = reg._sigma
    calls = []  # (on this thread, with this registration)
    plain = gicp.Registration.correspondences

    def spied(self, *args, **kwargs):
        calls.append((threading.current_thread() is threading.main_thread(), self is reg))
        return plain(self, *args, **kwargs)

    monkeypatch.setattr(gicp.Registration, "correspondences", spied)
    # (the first call: solution_terms) some poses on the second thread, each with the twin.
    # Under load the second thread may start only after this one has taken every pose (it
    # then computes them all here, as designed; measured once in a loaded make test), so a
    # few attempts are allowed for it to take part
    for _ in range(5):
        gicp._reverse_executor().submit(lambda: None).result()  # (idle before the bread)
        calls.clear()
        beside = _bread(reg, result, sigma)
        if (False, False) in calls[1:]:
            break
    assert (False, False) in calls[1:] and set(calls) <= {(True, True), (False, False)}
    calls.clear()
    release = threading.Event()
    busy = gicp._reverse_executor().submit(release.wait, 30)
    try:
        alone = _bread(reg, result, sigma)
    finally:
        release.set()
        busy.result()
    # every pose here, with this registration: never the twin the second thread's tasks share
    assert set(calls) == {(True, True)}
    np.testing.assert_array_equal(beside, alone)


def test_source_rows_on_a_lattice_map_are_computed_as_all_at_once():
    """On a voxel lattice the source's covariances and local means are per row, on either
    thread: the rows the registration computed equal one query of all the source's points."""
    source, target, T_gt = voxel_map_pair(3)
    reg = Registration(source, target, RegistrationConfig(max_correspondence_distance=0.3))
    result = reg.run()
    assert result.converged and reg.surface_radius is not None
    cov = reg.source_cov
    assert isinstance(cov, LazyCovariances) and cov.radius == reg._means_radius
    done = np.flatnonzero(cov.done)
    assert len(done) > 0.9 * len(source)
    covs, means = neighbourhoods(source, reg.config.k_neighbours, reg.config.epsilon,
                                 cKDTree(source), radius=reg._means_radius,
                                 min_points=reg.config.surface_min_points)
    np.testing.assert_array_equal(cov.values[done], covs[done])
    np.testing.assert_array_equal(cov.mean_values[done], means[done])
    np.testing.assert_array_equal(
        cov.mean_values[done], local_means(source, cKDTree(source), reg._means_radius,
                                           reg.config.surface_min_points)[done])


def test_rows_two_threads_need_are_computed_once_and_shared(rng):
    """A prefetch on a second thread and this thread's fill of the same rows: every row is
    computed once (this thread waits for the rows the other is computing and takes its own
    in chunks meanwhile), and the values are those of one query of all of them."""
    points = rng.uniform(0, 1, (5000, 3))
    tree = cKDTree(points)
    lazy = LazyCovariances(points, tree, 20, 1e-3, radius=0.05)
    plain, computed, started = lazy._compute, [], threading.Event()

    def slow(rows):  # the second thread's chunks take long: this one shares them
        computed.append((threading.current_thread() is threading.main_thread(), rows.copy()))
        if threading.current_thread() is not threading.main_thread():
            started.set()
            threading.Event().wait(0.05)
        plain(rows)

    lazy._compute = slow
    rows = rng.permutation(5000)[:3000]
    worker = threading.Thread(target=lazy.prefetch, args=(rows, 512))
    worker.start()
    assert started.wait(10)
    covs = lazy[rows]
    worker.join()
    counts = np.bincount(np.concatenate([r for _, r in computed]), minlength=5000)
    assert counts.max() == 1 and np.all(counts[rows] == 1)
    assert {here for here, _ in computed} == {True, False}  # both threads computed rows
    ref_covs, ref_means = neighbourhoods(points, 20, 1e-3, tree, rows, radius=0.05)
    np.testing.assert_array_equal(covs, ref_covs)
    np.testing.assert_array_equal(lazy.means(rows), ref_means)
    assert lazy._computing == 0 and not lazy._claimed.any()


def test_a_source_inside_a_centroid_map_gets_the_same_result_with_its_second_thread_busy(
        rng, monkeypatch):
    """The map's model terms and half of the re-matched bread run on the second thread
    (a source inside a voxel-centroid map has no reverse direction); with that thread busy
    through the covariance, they run here, and the estimate, covariance and diagnostic are
    the same bit for bit."""
    from test_registration_voxel_matching import centroids, thick_room

    room = thick_room(rng)
    target = centroids(room, 0.03, np.array([0.004, 0.011, -0.008]))
    source = room[room[:, 0] < 2.0][::40]
    source = source + rng.normal(scale=0.005, size=source.shape)
    init = np.eye(4)
    init[:3, 3] = [0.01, -0.015, 0.008]
    where = []
    plain_terms, plain_finish = gicp.Registration._grid_terms, gicp.Registration._finish

    def grid_terms(self, sol):
        where.append(threading.current_thread() is threading.main_thread())
        return plain_terms(self, sol)

    # (with the second thread free, it begins each task handed to it: wait for that before
    # the result is asked for, else under load this thread may ask first and run the task
    # itself, as it should; seen once in a fresh clone's suite)
    plain_result = gicp._Beside.result

    def patient_result(self, *here):
        deadline = time.monotonic() + 30.0
        while not (self._future.running() or self._future.done()) \
                and time.monotonic() < deadline:
            time.sleep(1e-3)
        return plain_result(self, *here)

    monkeypatch.setattr(gicp.Registration, "_grid_terms", grid_terms)
    monkeypatch.setattr(gicp._Beside, "result", patient_result)
    free = Registration(source, target, RegistrationConfig()).run(init)
    assert where == [False] and free.diagnostic.map_error is not None
    monkeypatch.setattr(gicp._Beside, "result", plain_result)

    def busy_finish(self, *args):
        release = threading.Event()
        busy = gicp._reverse_executor().submit(release.wait, 60)
        try:
            return plain_finish(self, *args)
        finally:
            release.set()
            busy.result()

    monkeypatch.setattr(gicp.Registration, "_finish", busy_finish)
    alone = Registration(source, target, RegistrationConfig()).run(init)
    assert where == [False, True]
    np.testing.assert_array_equal(alone.T, free.T)
    np.testing.assert_array_equal(alone.covariance, free.covariance)
    for name, value in vars(free.diagnostic).items():
        np.testing.assert_array_equal(getattr(alone.diagnostic, name), value, err_msg=name)


def test_a_split_whitening_equals_the_whole(monkeypatch):
    """From SPLIT_PAIRS pairs half of an iteration's whitening runs on the second thread
    (into one array): the same numbers as one call, with that thread free or busy, and
    through the kernel compiled ahead of time where there is one."""
    from estimation import aot
    from estimation.registration.factors import whitening_rows

    source, _, target, _, T_gt = make_pair(16, 1500, 0.01)
    reg = Registration(source, target, RegistrationConfig())
    corr = reg.correspondences(T_gt, 0.3)
    R = T_gt[:3, :3]
    whole = whitening_rows(reg.target_cov.filled(corr.target_idx), corr.target_idx,
                           reg.source_cov.filled(corr.source_idx), corr.source_idx, R)
    monkeypatch.setattr(gicp, "SPLIT_PAIRS", 100)
    ks = aot.kernels("estimation.registration._kernels")
    before = ks.jit_calls
    np.testing.assert_array_equal(reg._whitening(corr, R), whole)
    if ks.compiled is not None:
        assert ks.jit_calls == before
    release = threading.Event()
    busy = gicp._reverse_executor().submit(release.wait, 30)
    try:
        np.testing.assert_array_equal(reg._whitening(corr, R), whole)
    finally:
        release.set()
        busy.result()


def submitted_to_the_second_thread(monkeypatch) -> list[str]:
    """Return the list into which every later submission to the second thread appends its
    function's name (a :class:`gicp._Beside` task: the function it runs)."""
    executor = gicp._reverse_executor()
    submitted, plain = [], executor.submit

    def submit(fn, *args, **kwargs):
        submitted.append(getattr(args[0] if fn is gicp._beside else fn, "__name__", ""))
        return plain(fn, *args, **kwargs)

    monkeypatch.setattr(executor, "submit", submit)
    return submitted


def test_the_second_thread_prefetches_before_it_searches_the_maps_grid(monkeypatch):
    """The first iteration's source rows are prefetched before the map's grid is searched
    (needed only at convergence), once per run, and never for the reverse direction."""
    source, _, target, _, T_gt = make_pair(17, 1500, 0.01)
    submitted = submitted_to_the_second_thread(monkeypatch)
    result = Registration(source, target, RegistrationConfig()).run(T_gt)
    assert result.converged
    assert submitted.count("_partial_cells_grid") == 1
    assert submitted.index("prefetch") < submitted.index("_partial_cells_grid")


def test_the_class_trees_are_built_on_the_second_thread_after_the_sources_tree(monkeypatch):
    """Semantic-ICP's class trees (SemanticIndex) are built on the second thread, after the
    source's tree, once per registration, and give the same result as built on this one."""
    source, labels_s, target, labels_t, T_gt = make_pair(4)
    probs_s, probs_t = one_hot(labels_s, acc=0.9), one_hot(labels_t, acc=0.9)
    built = []
    plain = gicp.SemanticIndex

    def spy(*args, **kwargs):
        if args[0] is target:  # (the symmetric estimate's reverse direction has its own)
            built.append(threading.current_thread() is threading.main_thread())
        return plain(*args, **kwargs)

    monkeypatch.setattr(gicp, "SemanticIndex", spy)
    submitted = submitted_to_the_second_thread(monkeypatch)
    config = RegistrationConfig(max_correspondence_distance=0.2,
                                initial_correspondence_distance=0.8, decay=0.5)
    beside = Registration(source, target, config, probs_s, probs_t).run(T_gt)
    assert beside.converged, beside.reason
    assert built == [False]  # once, not on the main thread
    assert submitted.index("spy") == submitted.index("prepare") + 1  # the source's tree first
    # built on this thread (the preparation switched off): the same bits
    monkeypatch.setattr(Registration, "_prepare_index", lambda self: None)
    here = Registration(source, target, config, probs_s, probs_t).run(T_gt)
    assert built == [False, True]
    np.testing.assert_array_equal(here.T, beside.T)
    np.testing.assert_array_equal(here.covariance, beside.covariance)


def test_a_lattice_maps_finish_measures_beside_with_the_same_result(monkeypatch):
    """On a voxel lattice (no reverse direction) the finish hands the lattice's cells and the
    off-surface share to the second thread (through _Beside); with every _Beside task done
    on the calling thread instead, the estimate, covariance and diagnostic are the same."""
    source, target, _ = voxel_map_pair(5, 3000, 30000)
    config = RegistrationConfig(max_correspondence_distance=0.1)
    handed = []
    plain = gicp._Beside.__init__

    def spied(self, fn, *args):
        handed.append(getattr(fn, "__name__", ""))
        plain(self, fn, *args)

    monkeypatch.setattr(gicp._Beside, "__init__", spied)
    reg = Registration(source, target, config)
    beside = reg.run()
    assert reg.quantisation_pitch is not None
    assert {"_lattice_grid", "coverage"} <= set(handed)

    class Here:  # (each task run at once, on the calling thread)
        def __init__(self, fn, *args):
            self.value = fn(*args)

        def result(self, *here):
            return self.value

    monkeypatch.setattr(gicp, "_Beside", Here)
    here = Registration(source, target, config).run()
    np.testing.assert_array_equal(here.T, beside.T)
    np.testing.assert_array_equal(here.covariance, beside.covariance)
    np.testing.assert_equal(here.diagnostic.off_surface, beside.diagnostic.off_surface)
    assert here.diagnostic.trusted == beside.diagnostic.trusted
