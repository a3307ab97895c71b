"""Speed of mapping.OcTree against liboctomap (octomap-python), measured in the same run.

Prints medians of repeats and the ratio ours/liboctomap (throughput) for: insertion of scan.dat
(88k points, one scan) at 0.1 and 0.05 m, a synthetic corridor of 50 scans x 100k points as the
map grows, batched search, batched cast_ray, leaf traversal, memory, and .bt/.ot read/write.
Every timed row gives two ratios: by CPU time (process time, summed over threads) and by wall
time. liboctomap (the Debian / PyPI octomap-python build) is single-threaded; our insertion marks
the rays of a scan on numba's thread count (NUMBA_NUM_THREADS), everything else is one thread.

    .venv/bin/python benchmarks/octree.py [--quick] [--repeats N] [--only SECTION] [--res R]
    .venv/bin/python benchmarks/octree.py --process [--also-jit] [--repeats N] [--res R]

``--process`` times whole processes as a user runs them: ``octofactor map G.graph -r R -m 10
-o OUT.bt`` against liboctomap's ``graph2tree -i G.graph -res R -m 10 -o OUT.bt`` on the same
.graph file (the corridor's 50 scans x 100k points, and a tiny 2 x 5k-point graph for the
start-up), alternating, median wall time of the repeats; the two .bt files must be identical.
The kernels run compiled ahead of time when ``make setup`` built them (estimation/aot.py);
``--also-jit`` adds a third command, the same on numba's JIT alone (``OCTOFACTOR_JIT=1``).

The insertion rows alternate our runs with liboctomap's (so a change of machine load hits both
sides alike) and take the median of ``--repeats`` runs of each.
"""
from __future__ import annotations

import argparse
import bz2
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import octomap  # noqa: E402

from mapping import OcTree  # noqa: E402


def median_time(fn, repeats: int) -> tuple[float, float]:
    """(median CPU time, median wall time) of ``fn`` over ``repeats`` runs.

    CPU time is process time summed over all threads (far less disturbed than wall time on a
    loaded machine); wall time shows what several threads buy.
    """
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return statistics.median(cpu), statistics.median(wall)


def paired_times(fn_ours, fn_ref, repeats: int, ref_repeats: int | None = None):
    """Median (CPU, wall) times of ``fn_ours`` and ``fn_ref``, their runs alternating."""
    ref_repeats = repeats if ref_repeats is None else ref_repeats
    times = {0: ([], []), 1: ([], [])}
    for r in range(max(repeats, ref_repeats)):
        for side, fn, reps in ((0, fn_ours, repeats), (1, fn_ref, ref_repeats)):
            if r < reps:
                c0, w0 = time.process_time(), time.perf_counter()
                fn()
                times[side][0].append(time.process_time() - c0)
                times[side][1].append(time.perf_counter() - w0)
    return tuple((statistics.median(times[s][0]), statistics.median(times[s][1])) for s in (0, 1))


def row(name: str, ours: float, ref: float, unit: str, higher_is_better: bool = True) -> None:
    ratio = ours / ref if higher_is_better else ref / ours
    print(f"{name:<46} ours {ours:>12.4g} {unit:<8} liboctomap {ref:>12.4g} {unit:<8} "
          f"ratio {ratio:7.2f}x")


def trow(name: str, work_ours: float, t_ours: tuple[float, float], work_ref: float,
         t_ref: tuple[float, float], unit: str, scale: float = 1.0) -> None:
    """Throughputs ``work / CPU time / scale`` of both sides and the ratios by CPU and wall."""
    ours, ref = work_ours / t_ours[0] / scale, work_ref / t_ref[0] / scale
    wall = (work_ours / t_ours[1]) / (work_ref / t_ref[1])
    print(f"{name:<42} ours {ours:>10.4g} {unit:<7} liboctomap {ref:>10.4g} {unit:<7} "
          f"ratio CPU {ours / ref:6.2f}x  wall {wall:6.2f}x")


def corridor_scans(n_scans: int, n_points: int, seed: int = 0):
    """Scans of a 2 m x 2.5 m corridor along x, sensor moving 0.2 m per scan (points in world)."""
    rng = np.random.default_rng(seed)
    half_w, height = 1.0, 2.5
    scans = []
    for s in range(n_scans):
        origin = np.array([0.2 * s, 0.1 * np.sin(s), 1.2])
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t = np.full(n_points, np.inf)
        for axis, lo, hi in ((1, -half_w, half_w), (2, 0.0, height)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t_lo = (lo - origin[axis]) / d[:, axis]
                t_hi = (hi - origin[axis]) / d[:, axis]
            for tt in (t_lo, t_hi):
                t = np.where((tt > 0) & (tt < t), tt, t)
        t = np.minimum(t, 25.0)  # open corridor ends: a far wall at 25 m
        pts = origin + d * t[:, None] + rng.normal(scale=0.01, size=(n_points, 3))
        scans.append((pts.astype(np.float32), origin))
    return scans


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller corridor, fewer repeats")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--only", choices=("insert", "queries", "memory", "files"), default=None,
                    help="run one section only")
    ap.add_argument("--res", type=float, default=None,
                    help="insertion rows at this resolution only (0.1 or 0.05)")
    ap.add_argument("--process", action="store_true",
                    help="time whole `octofactor map` processes against graph2tree on the "
                    "same .graph file")
    ap.add_argument("--also-jit", action="store_true",
                    help="with --process: also time `octofactor map` on numba's JIT alone "
                    "(OCTOFACTOR_JIT=1), as it runs without the compiled kernels")
    args = ap.parse_args()
    repeats = args.repeats or (3 if args.quick else 5)
    if args.process:
        return process_rows(args, repeats)
    data = REPO.parent / "shared" / "data" / "octomap"
    if not data.is_dir():
        data = Path("/work/shared/data/octomap")
    text = bz2.decompress((data / "scan.dat.bz2").read_bytes()).decode()
    scan = np.loadtxt(text.splitlines(), dtype=np.float64).astype(np.float32)
    scan64 = scan.astype(np.float64)
    zero = np.zeros(3)

    # warm up the numba kernels (compiled once, cached on disk)
    w = OcTree(0.5)
    w.insert_point_cloud(scan[:100], zero)
    w.search(scan[:10])
    w.cast_ray(zero[None], np.ones((1, 3)))
    w.leaves()
    w.to_bytes_bt()

    from numba import threading_layer

    from mapping.octree import _num_threads as get_num_threads

    print(f"# mapping.OcTree vs liboctomap (octomap-python), medians of {repeats} repeats "
          "(liboctomap: 1 run for the per-call queries)")
    print("# throughputs by CPU time (summed over threads); ratios by CPU time and by wall time")
    print(f"# liboctomap (Debian/PyPI build) is single-threaded; our insertion marks rays on "
          f"{get_num_threads()} thread(s) (numba's default, NUMBA_NUM_THREADS; threading layer "
          f"{threading_layer()}), all else 1 thread")
    print(f"# load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    n_scans, n_pts = (10, 20_000) if args.quick else (50, 100_000)
    scans = corridor_scans(n_scans, n_pts)
    resolutions = (0.1, 0.05) if args.res is None else (args.res,)
    if args.only in (None, "insert"):
        insertion_rows(scan, scan64, zero, scans, resolutions, repeats)
    if args.only in (None, "queries", "memory", "files"):
        other_rows(args, data, scan, zero, scans, repeats)
    print(f"# load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


def _write_graph(path: Path, scans) -> int:
    """The scans as an OctoMap .graph (sensor-frame float32 points, pose = the origin)."""
    import gtsam

    from estimation import PoseGraph, Scan
    from estimation.io import write_scan_graph

    pg = PoseGraph()
    for i, (pts, origin) in enumerate(scans):
        pg.add_node(i, gtsam.Pose3(gtsam.Rot3(), origin),
                    scan=Scan((pts - origin.astype(np.float32)).astype(np.float32)))
    write_scan_graph(path, pg)
    return sum(len(p) for p, _ in scans)


def process_rows(args, repeats: int) -> int:
    """Whole-process `octofactor map` vs `graph2tree` on the same .graph (median wall times)."""
    import shutil
    import subprocess

    graph2tree = shutil.which("graph2tree")
    if graph2tree is None:
        print("graph2tree not found (Debian package octomap-tools)", file=sys.stderr)
        return 2
    octofactor = [sys.executable, "-m", "pipelines"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO),
                                                       os.environ.get("PYTHONPATH", "")]))
    jit_env = dict(env, OCTOFACTOR_JIT="1")
    from estimation.aot import kernels

    compiled = kernels("mapping._kernels").compiled
    how = (f"compiled ahead of time ({compiled.__name__})" if compiled else
           "JIT only (no current compiled module: python -m estimation.aot build)")
    if args.also_jit:
        how += "; JIT only = the same with OCTOFACTOR_JIT=1 (numba cache warm)"
    print(f"# whole processes, median wall time of {repeats} alternating runs; "
          f"octofactor = {' '.join(octofactor)} map, graph2tree = {graph2tree}")
    print(f"# kernels: {how}")
    print(f"# load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        n_scans, n_pts = (10, 20_000) if args.quick else (50, 100_000)
        cases = [("tiny 2 x 5k points", _write_graph(tmp / "tiny.graph", corridor_scans(2, 5000)),
                  tmp / "tiny.graph"),
                 (f"corridor {n_scans} x {n_pts // 1000}k points",
                  _write_graph(tmp / "corridor.graph", corridor_scans(n_scans, n_pts)),
                  tmp / "corridor.graph")]
        resolutions = (0.1, 0.05) if args.res is None else (args.res,)
        for label, n_points, graph in cases:
            for res in resolutions:
                ours_out, ref_out = tmp / "ours.bt", tmp / "ref.bt"
                ours_cmd = octofactor + ["map", str(graph), "-r", str(res), "--max-range", "10",
                                         "-q", "-o", str(ours_out)]
                ref_cmd = [graph2tree, "-i", str(graph), "-res", str(res), "-m", "10",
                           "-o", str(ref_out)]
                jit_out = tmp / "jit.bt"
                jit_cmd = ours_cmd[:-1] + [str(jit_out)]
                sides = [(ours_cmd, env), (ref_cmd, env)]
                if args.also_jit:
                    sides.append((jit_cmd, jit_env))
                subprocess.run(ours_cmd, check=True, env=env)  # warm the numba cache
                subprocess.run(jit_cmd, check=True, env=jit_env)
                times = {side: [] for side in range(len(sides))}
                for _ in range(repeats):
                    for side, (cmd, cmd_env) in enumerate(sides):
                        start = time.perf_counter()
                        subprocess.run(cmd, check=True, env=cmd_env, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL)
                        times[side].append(time.perf_counter() - start)
                same = ours_out.read_bytes() == ref_out.read_bytes()
                ours, ref = statistics.median(times[0]), statistics.median(times[1])
                line = (f"{label:<28} res {res:<5g} octofactor map {ours:8.3f} s  graph2tree "
                        f"{ref:8.3f} s  ratio {ref / ours:6.2f}x  ({n_points / ours / 1e6:.2f} "
                        f"Mpts/s; .bt identical: {same})")
                if args.also_jit:
                    jit = statistics.median(times[2])
                    line += (f"  | JIT only {jit:8.3f} s, ratio {ref / jit:6.2f}x, .bt "
                             f"identical: {jit_out.read_bytes() == ref_out.read_bytes()}")
                print(line)
    print(f"# load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


def insertion_rows(scan, scan64, zero, scans, resolutions, repeats) -> None:
    """Insertion throughput of scan.dat and of the growing corridor map, both sides alternating."""
    print("## insertion, scan.dat (88,206 points, one scan from the origin)")
    for res, max_range in ((0.1, -1.0), (0.1, 10.0), (0.05, 10.0), (0.05, -1.0)):
        if res not in resolutions:
            continue
        t_ours, t_ref = paired_times(
            lambda res=res, mr=max_range: OcTree(res).insert_point_cloud(scan, zero, mr),
            lambda res=res, mr=max_range: octomap.OcTree(res).insertPointCloud(
                scan64, zero, maxrange=mr), repeats)
        trow(f"insert scan.dat res {res} max_range {max_range:g}", len(scan), t_ours,
             len(scan), t_ref, "Mpts/s", 1e6)

    n_scans, n_pts = len(scans), scans[0][0].shape[0]
    print(f"## insertion, synthetic corridor {n_scans} scans x {n_pts} points (map grows)")
    for res in resolutions:
        def ours(res=res):
            t = OcTree(res)
            for p, o in scans:
                t.insert_point_cloud(p, o, max_range=10.0)
            return t

        def ref(res=res):
            t = octomap.OcTree(res)
            for p, o in scans:
                t.insertPointCloud(p.astype(np.float64), o, maxrange=10.0)
            return t

        t_ours, t_ref = paired_times(ours, ref, repeats)
        total = n_scans * n_pts
        trow(f"insert corridor res {res} max_range 10", total, t_ours, total, t_ref, "Mpts/s",
             1e6)


def other_rows(args, data, scan, zero, scans, repeats) -> None:
    """Queries, memory and files on maps built from scan.dat, the corridor and geb079.bt."""
    tree = OcTree(0.05)
    tree.insert_point_cloud(scan, zero, 10.0)
    ref_tree = octomap.OcTree.read(tree.to_bytes_ot())
    rng = np.random.default_rng(0)
    if args.only in (None, "queries"):
        query_rows(tree, ref_tree, rng, zero, repeats)
    if args.only in (None, "memory"):
        memory_rows(tree, ref_tree, scans)
    if args.only in (None, "files"):
        file_rows(data, repeats)


def query_rows(tree, ref_tree, rng, zero, repeats) -> None:
    print(f"## queries on scan.dat at 0.05 m, max range 10 ({tree.size()} nodes)")
    q = rng.uniform(-10, 10, size=(1_000_000, 3)).astype(np.float32)
    t_ours = median_time(lambda: tree.search(q), repeats)
    q_small = q[:20_000].astype(np.float64)

    def ref_search():
        for p in q_small:
            try:
                ref_tree.search(p)
            except octomap.NullPointerException:
                pass

    t_ref = median_time(ref_search, 1)
    trow("search (batched, ours) vs per call", len(q), t_ours, len(q_small), t_ref, "Mq/s", 1e6)

    n_rays = 100_000
    dirs = rng.normal(size=(n_rays, 3))
    t_ours = median_time(lambda: tree.cast_ray(zero[None], dirs, ignore_unknown=True,
                                               max_range=15.0), repeats)
    end = np.zeros(3)

    def ref_rays():
        for d in dirs[:5000]:
            ref_tree.castRay(zero, d, end, True, 15.0)

    t_ref = median_time(ref_rays, 1)
    trow("cast_ray (batched) vs per call", n_rays, t_ours, 5000, t_ref, "krays/s", 1e3)

    def ours_leaves():
        tree._cache = None
        lv = tree.leaves()
        return lv.centers.sum()

    def ref_leaves():
        s = 0.0
        for n in ref_tree.begin_leafs():
            s += n.getValue()
        return s

    t_ours = median_time(ours_leaves, repeats)
    t_ref = median_time(ref_leaves, 1)
    n_leaves = tree.num_leaf_nodes()
    trow("leaf traversal (arrays vs iterator)", n_leaves, t_ours, n_leaves, t_ref, "Mleaf/s",
         1e6)



def memory_rows(tree, ref_tree, scans) -> None:
    print("## memory (ratio = liboctomap memoryUsage / ours allocated)")
    grown = OcTree(0.05)
    for p, o in scans:
        grown.insert_point_cloud(p, o, max_range=10.0)
    ref_grown = octomap.OcTree.read(grown.to_bytes_ot())
    row("scan.dat 0.05 m (one insert)", tree.memory_bytes(), ref_tree.memoryUsage(), "B",
        higher_is_better=False)
    row("corridor 0.05 m (grown map)", grown.memory_bytes(), ref_grown.memoryUsage(), "B",
        higher_is_better=False)
    grown.compact()
    row("corridor 0.05 m after compact()", grown.memory_bytes(), ref_grown.memoryUsage(), "B",
        higher_is_better=False)



def file_rows(data, repeats) -> None:
    print("## files (geb079.bt, 532,566 nodes)")
    geb = data / "geb079.bt"
    with tempfile.TemporaryDirectory() as tmp:
        g = OcTree.read(geb)
        rg = octomap.OcTree(0.1)
        rg.readBinary(str(geb).encode())
        t_ours = median_time(lambda: OcTree.read(geb), repeats)
        t_ref = median_time(lambda: octomap.OcTree(0.1).readBinary(str(geb).encode()), repeats)
        trow(".bt read", 1, t_ours, 1, t_ref, "files/s")
        out = Path(tmp) / "g.bt"
        t_ours = median_time(lambda: g.write_bt(out), repeats)
        t_ref = median_time(lambda: rg.writeBinary(str(out).encode()), repeats)
        trow(".bt write", 1, t_ours, 1, t_ref, "files/s")
        out = Path(tmp) / "g.ot"
        t_ours = median_time(lambda: g.write_ot(out), repeats)
        t_ref = median_time(lambda: rg.write(str(out).encode()), repeats)
        trow(".ot write", 1, t_ours, 1, t_ref, "files/s")
        t_ours = median_time(lambda: OcTree.read(out), repeats)
        t_ref = median_time(lambda: octomap.OcTree.read(str(out).encode()), repeats)
        trow(".ot read", 1, t_ours, 1, t_ref, "files/s")


if __name__ == "__main__":
    sys.exit(main())
