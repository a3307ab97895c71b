"""Benchmark on real indoor rooms: a 3 cm voxel map against a raw part of the room.

Issue 14's held-out check registers real indoor scans with semantic labels: a 3 cm voxel map
of a room against a raw half-room cloud with 5 mm noise and 10 % wrong labels. This script
builds the same kind of case from the real RGB-D sequences in ``shared/data/rgbd``:

room
    The depth frames of a sequence (every ``--step``-th, every second pixel, depth <= 4 m)
    back-projected and placed with the sequence's ground-truth poses, thinned to one measured
    point per 5 mm voxel (``perception.rgbd.voxel_filter``). The room is only a point set:
    errors of the ground-truth poses make its surfaces thicker, they do not enter the
    registration's ground truth.
    ``scan`` is another kind of room: one real 3-D laser scan of a building's corridor
    (OctoMap's ``scan.dat.bz2`` in ``shared/data/octomap``, read as float32 as OctoMap
    does), its points within ``SCAN_RANGE`` (8 m) of the sensor: 68k points, one scan, no
    fusion, 2 points per 3 cm voxel on average (the RGB-D rooms: about 10).
labels
    The shared data have no semantic labels, so each room point gets a geometric class as a
    stand-in: the axis its surface normal (Open3D, 5 cm radius; 15 cm for the sparser
    laser scan) is nearest to (three classes)
    or "other" where no axis is within about 32 deg. Spatially coherent like real classes;
    they are not object classes. ``--classes N`` (more than 4) stands in for object labels,
    which come in dozens: each geometric class within each 0.6 m block is a segment, and
    the segments are spread over N classes by a hash of their block (a class recurs in
    several places, as chairs do); Semantic-ICP then searches N class trees.
map (target)
    The room as a 3 cm voxel map: ``centroids`` (the mean point of each voxel, as Open3D's
    ``voxel_down_sample`` and ``SemanticCloud.fuse_voxels``) or ``centres`` (the voxel
    centres, as an octree map), each with its voxel's majority label.
source (per trial, seeded)
    The room's points on one side of a random vertical plane through its centroid, 15000 of
    them drawn at random (``--source-points``; 0: all of them, a raw half-room cloud), 5 mm
    Gaussian noise added (``--noise``; 0: the map's points as they are), 10 % of the labels
    changed to another class at random (each point on its own; ``--wrong-blocks M``: whole
    M-metre blocks of the half, 10 % of them, each to one other class, as a segmentation
    network errs on whole objects and regions), moved into their own frame by a random rigid
    transform (5-30 deg, about 1.7 m): the exact ground truth ``T_target_source``.
setting
    ``half`` (default, the held-out check's case): that half against the map of the whole
    room, so the source lies inside the map. ``part``: two overlapping parts, as two scans
    of a room: the source from the points more than ``PART_OVERLAP / 2`` (0.5 m) behind the
    plane's far side, the map (per trial) of the points up to 0.5 m beyond it; the overlap
    is a 1 m slab and each cloud has much the other lacks.

Protocol as benchmarks/registration.py: the same clouds, initial guess (small: 0.2 m / 8 deg,
wide: 1.0 m / 40 deg about the source centroid) and two-stage schedule (d0 0.5 / 1.0 m, then
0.2 m) for every method. Methods: "gicp-se3" and "semantic-icp" (ours, default
RegistrationConfig but for the schedule), "semantic-icp-once" (ours with
``semantic_rescue=False``: no second start with geometric annealing after an untrusted
result, as before the thirty-first round), "gicp-se3-nogate" (ours with ``boundary_gate=None``,
the estimator before the boundary gate), "gicp-se3-nearest" (ours with ``voxel_matching=None``:
the nearest centroid throughout, the estimator before same-voxel matching),
"gicp-se3-midpoint" (ours with ``partial_voxel_matching=False``: a partial overlap matched by
nearest centroids, the midpoint of both directions, as before the fifteenth round),
"gicp-se3-own" (ours with ``pooled_source_covariance=False``: each source point whitened with
its own covariance inside a centroid map, as before the nineteenth round), "open3d-gicp"
(CauchyLoss(1.0), the reference of the ratios). Semantic-ICP uses one-hot labels (the wrong
ones too). NEES = e^T P^-1 e of the final error against the reported covariance; every trial is
an independent source (another half, subsample, noise, labels, ground truth), the map is the
same: the mean NEES is compared with the chi-square bounds of a mean of N (6 dof). Those bounds
are for N independent errors, and the map's own representation error is common to every
trial of a cell (one draw for all): the report also splits the mean NEES into the trials'
common error, in the map's frame, and their variation about it
(``estimation.covariance.nees_about_common``). ``--map-phase random`` voxelises each trial's
map with its own random grid phase: an independent draw of the grid's part of the map's error
per trial (the trials' sources are the same as with one fixed map). ``--map-phases M``
registers every trial against M maps of the room instead of one: the default grid and M - 1
random grid phases (:func:`map_shift`). It prints each map's mean NEES over its trials (what
a test on one map sees: one draw of that map's error for all of them), how many of the maps'
means lie inside the band of a mean of N, and the mean over every map and trial (the
calibration over the grid's phase, the draw the covariance's model terms describe), with that
mean's crossed-bootstrap 95 % interval (maps and trials resampled,
``estimation.covariance.crossed_bootstrap_interval``): its runs share their map's and their
trial's draws, so the chi-square band of as many independent runs is too narrow for it.
``--first-trial K`` draws the trials from seeds K, K + 1, ... (the map term's sizes were chosen
on seeds 0-5 of the raw halves: seeds from 6 on are halves not tuned on). Times per
registration include the per-point covariances of every method; "paired" = median of the per-
trial ratios to Open3D, also printed over the trials where both found the right basin (failed
runs stop at different iteration caps: Open3D 30 a stage, ours 150).

Diagnosis of the covariance gap (``--phase-covariance K``, GICP-SE(3) on centroid maps, half
setting): the map's representation error is where the voxel grid cuts the room's surfaces.
The room's own points are voxelised again at K random grid phases (the same pitch), the
source is registered to each of those maps from the estimate (one direction, final d_max),
and the covariance of those estimates about their mean, the spread the grid's phase alone
causes, is added to the reported covariance: the printed mean NEES with it says how much
of the gap that term would close. It needs the points the map was made from, which a
registration of a given map does not have: a measurement, not an estimator
(docs/registration_notes.md, "Where the room gap comes from"). The K maps push the room map's grid
out of ``voxel_grid``'s cache, so times in such a run include finding it again.

Usage::

    python benchmarks/registration_indoor.py                         # tum and icl, 30 trials
    python benchmarks/registration_indoor.py --rooms tum --maps centroids --trials 10
    python benchmarks/registration_indoor.py --rooms tum,icl --maps centroids --classes 24
    python benchmarks/registration_indoor.py --rooms tum,icl --maps centroids --setting part
    python benchmarks/registration_indoor.py --rooms tum,icl,scan --maps centroids \
        --source-points 0 --methods gicp-se3,semantic-icp,open3d-gicp --map-phase random
    python benchmarks/registration_indoor.py --rooms tum,icl --maps centroids \
        --source-points 0 --methods gicp-se3,open3d-gicp --trials 6 --map-phases 10
    python benchmarks/registration_indoor.py --rooms icl --maps centroids --source-points 0 \
        --methods gicp-se3,semantic-icp,open3d-gicp --trials 20 --first-trial 6 --map-phases 3
    python benchmarks/registration_indoor.py --rooms tum,icl --maps centres --plane-tilt 0
    python benchmarks/registration_indoor.py --rooms scan,tum,icl --maps centroids --classes 24 \
        --wrong-blocks 0.3 --methods gicp-se3,semantic-icp,open3d-gicp --trials 10
    python benchmarks/registration_indoor.py --rooms scan --maps centroids --map-error none
    python benchmarks/registration_indoor.py --rooms scan --maps centres --lattice-noise none
    python benchmarks/registration_indoor.py --rooms tum,icl --maps centroids --methods \
        gicp-se3,open3d-gicp --trials 10 --phase-covariance 10
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.registration import D_FINAL, register_ours, run_open3d  # noqa: E402
from benchmarks.registration import OFFSETS as SIMULATOR_OFFSETS  # noqa: E402
from estimation.covariance import (  # noqa: E402
    CommonErrorSplit,
    chi2_bounds,
    crossed_bootstrap_interval,
    nees,
    nees_about_common,
)
from estimation.fileio import atomic_write  # noqa: E402
from estimation.registration import pose_error  # noqa: E402
from estimation.registration.metrics import offset_about_centroid  # noqa: E402
from perception.semantic_cloud import SemanticCloud  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
# folder, pinhole intrinsics (fx fy cx cy, 640 x 480), lens distortion (OpenCV order) or None
ROOMS = {"tum": ("tum_fr1_rpy", (517.3, 516.5, 318.6, 255.3),
                 (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
         "icl": ("icl_of_kt0", (481.2, 480.0, 319.5, 239.5), None),
         "scan": None}  # OctoMap's laser scan (scan_room)
SCAN_RANGE = 8.0  # m: the laser scan's points kept (beyond, its spacing is several pitches)
N_GEOMETRIC = 4  # the rooms' geometric classes (three axes and "other")
N_CLASSES = N_GEOMETRIC  # the classes of the run (--classes)
PITCH = 0.03
# m, deg, initial d_max: the simulator benchmark's two, and "near", a start at the final d_max
# (no annealing: what RegistrationConfig's defaults and `octofactor register` without
# --initial-corr do; Open3D: its two calls both at the final d_max)
OFFSETS = {**SIMULATOR_OFFSETS, "near": (0.05, 2.0, D_FINAL)}
METHODS = ("gicp-se3", "semantic-icp", "semantic-icp-once", "gicp-se3-nogate", "gicp-se3-nearest",
           "gicp-se3-midpoint", "gicp-se3-own", "open3d-gicp")
PART_OVERLAP = 1.0  # m: width of the slab two parts share (setting "part")
SOURCE_POINTS = 15000  # points drawn for a trial's source (--source-points; 0: all)
SOURCE_NOISE = 0.005  # the noise (m, per axis) added to a source of the map's points (--noise)


def labelled(points: np.ndarray, labels: np.ndarray) -> SemanticCloud:
    """The cloud with one-hot class probabilities (what the benchmark's run functions read)."""
    return SemanticCloud.from_labels(points, labels, N_CLASSES)


def room_cloud(name: str, step: int = 5, data: Path = DATA, start: int = 0,
               stop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return (points (N, 3), geometric class labels (N,)) of the room ``name`` fused from
    its frames ``start``, ``start + step``, ... before ``stop`` (default: the last)."""
    from perception.rgbd import CameraIntrinsics, TumRgbdSequence, backproject, voxel_filter

    if name == "scan":
        return scan_room(data.parent / "octomap" / "scan.dat.bz2")
    folder, (fx, fy, cx, cy), distortion = ROOMS[name]
    intr = CameraIntrinsics(fx, fy, cx, cy, 640, 480, 5000.0)
    seq = TumRgbdSequence(data / folder, intr, distortion=distortion)
    parts = []
    for index in range(start, len(seq) if stop is None else min(stop, len(seq)), step):
        frame = seq[index]
        if frame.T_world_camera_gt is None:
            continue
        depth = np.where(frame.depth_m <= 4.0, frame.depth_m, 0.0)
        T = frame.T_world_camera_gt.matrix()
        parts.append(backproject(depth, intr, 2).astype(float) @ T[:3, :3].T + T[:3, 3])
    points = voxel_filter(np.concatenate(parts), 0.005).astype(float)
    return points, geometric_labels(points, 0.05)


def scan_room(path: Path, max_range: float = SCAN_RANGE) -> tuple[np.ndarray, np.ndarray]:
    """Return (points, geometric class labels) of OctoMap's laser scan within ``max_range``
    (m) of its sensor (one ``x y z`` per line, read as float32 as OctoMap reads it)."""
    from benchmarks.registration_real import read_scan_dat

    points = read_scan_dat(path, np.float32)
    points = points[np.linalg.norm(points, axis=1) <= max_range]
    return points, geometric_labels(points, 0.15)


def geometric_labels(points: np.ndarray, radius: float) -> np.ndarray:
    """Return each point's geometric class: the axis its surface normal (Open3D, ``radius``
    m, at most 30 neighbours) is nearest to, or 3 ("other") where none is within about
    32 deg."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius, 30))
    normals = np.abs(np.asarray(cloud.normals))
    labels = np.argmax(normals, axis=1)
    labels[normals.max(axis=1) < 0.85] = 3
    return labels.astype(np.int64)


def object_labels(points: np.ndarray, labels: np.ndarray, n_classes: int,
                  block: float = 0.6) -> np.ndarray:
    """Return ``n_classes`` spatially coherent labels made from the geometric ``labels``
    (4 classes): each class within each ``block`` (m) cube is a segment, the segments
    spread over the classes by a hash of their cube."""
    cube = np.floor(points / block).astype(np.int64)
    spread = max(n_classes // N_GEOMETRIC, 1)
    segment = (cube[:, 0] * 73856093 ^ cube[:, 1] * 19349663 ^ cube[:, 2] * 83492791) % spread
    return ((segment * N_GEOMETRIC + labels) % n_classes).astype(np.int64)


def voxel_map(points: np.ndarray, labels: np.ndarray, kind: str, pitch: float = PITCH,
              shift: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return the ``pitch`` voxel map of a labelled cloud: (points, majority labels).

    ``shift`` (3,): the grid's phase, its cell walls at ``k pitch - shift`` (default 0)."""
    shift = np.zeros(3) if shift is None else np.asarray(shift, dtype=float)
    keys = np.floor((points + shift) / pitch).astype(np.int64)
    cells, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    votes = np.zeros((len(cells), N_CLASSES))
    np.add.at(votes, (inverse, labels), 1.0)
    if kind == "centres":
        centres = (cells + 0.5) * pitch - shift
    elif kind == "centroids":
        centres = np.zeros((len(cells), 3))
        np.add.at(centres, inverse, points)
        centres /= counts[:, None]
    else:
        raise ValueError(f"unknown map kind {kind!r}")
    return centres, votes.argmax(axis=1)


def half_room_source(points: np.ndarray, labels: np.ndarray, rng: np.random.Generator,
                     n: int = SOURCE_POINTS, noise: float = SOURCE_NOISE, wrong: float = 0.1,
                     wrong_blocks: float | None = None) -> tuple[SemanticCloud, np.ndarray]:
    """Return (source cloud in its own frame, T_target_source) of one trial."""
    source, T, _ = room_part_source(points, labels, rng, 0.0, n, noise, wrong, wrong_blocks)
    return source, T


def block_flips(points: np.ndarray, share: float, block: float, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """Return (flipped (N,) bool, class shift of each flipped point in 1 .. N_CLASSES - 1):
    the points' ``block``-metre cubes (a grid with a random phase), each flipped with
    probability ``share``, every point of a flipped cube shifted by the cube's one shift."""
    cube = np.floor((points + rng.uniform(0.0, block, 3)) / block).astype(np.int64)
    _, inverse = np.unique(cube, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    flipped = rng.random(int(inverse.max()) + 1) < share
    shift = rng.integers(1, N_CLASSES, size=len(flipped))
    flip = flipped[inverse]
    return flip, shift[inverse][flip]


def room_part_source(points: np.ndarray, labels: np.ndarray, rng: np.random.Generator,
                     overlap: float = PART_OVERLAP, n: int = SOURCE_POINTS,
                     noise: float = SOURCE_NOISE, wrong: float = 0.1,
                     wrong_blocks: float | None = None
                     ) -> tuple[SemanticCloud, np.ndarray, np.ndarray]:
    """Return (source cloud in its own frame, T_target_source, rows of the target's part).

    The source is drawn from the room's points with ``s > -overlap / 2``, s their distance
    along a random horizontal direction from the room's centroid; the target's part is the
    rows with ``s < overlap / 2`` (with ``overlap`` 0: the source is one half, and the
    target's rows are the other half, unused by the "half" setting). A share ``wrong`` of
    the labels is changed to another class: each point on its own, or with ``wrong_blocks``
    (m) whole blocks (:func:`block_flips`, from a stream of its own: the points, the
    truth and the start are those of the per-point draw).
    """
    angle = rng.uniform(0.0, 2.0 * np.pi)
    s = (points - points.mean(axis=0)) @ [np.cos(angle), np.sin(angle), 0]
    side = np.flatnonzero(s > -0.5 * overlap)
    rows = side if n <= 0 else rng.choice(side, size=min(n, len(side)), replace=False)
    source = points[rows] + rng.normal(scale=noise, size=(len(rows), 3))
    source_labels = labels[rows].copy()
    flip = rng.random(len(rows)) < wrong
    shift = rng.integers(1, N_CLASSES, size=int(flip.sum()))
    if wrong_blocks is not None:
        flip, shift = block_flips(points[rows], wrong, wrong_blocks, rng.spawn(1)[0])
    source_labels[flip] = (source_labels[flip] + shift) % N_CLASSES
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    T = gtsam.Pose3(gtsam.Rot3.Rodrigues(axis * np.deg2rad(rng.uniform(5.0, 30.0))),
                    rng.normal(size=3)).matrix()
    return (labelled((source - T[:3, 3]) @ T[:3, :3], source_labels), T,
            np.flatnonzero(s < 0.5 * overlap))


def phase_maps(points: np.ndarray, labels: np.ndarray, kind: str, phases: int, seed: int = 11,
               pitch: float = PITCH) -> list[np.ndarray]:
    """Return ``phases`` voxel maps of the room made with random grid phases (the same pitch)."""
    rng = np.random.default_rng(seed)
    return [voxel_map(points, labels, kind, pitch, rng.uniform(0.0, pitch, 3))[0]
            for _ in range(phases)]


def phase_shift(trial: int, pitch: float = PITCH) -> np.ndarray:
    """Return trial ``trial``'s random grid phase (``--map-phase random``), from its own
    random stream (the trial's source is drawn as with one fixed map)."""
    return np.random.default_rng([trial, 7]).uniform(0.0, pitch, 3)


def map_shift(index: int, pitch: float = PITCH) -> np.ndarray | None:
    """Return map ``index``'s grid phase (``--map-phases``): None (the default grid) for map
    0, a random phase from the map's own stream for the others."""
    return None if index == 0 else np.random.default_rng([index, 31]).uniform(0.0, pitch, 3)


def phase_covariance(source: np.ndarray, maps: list[np.ndarray], T: np.ndarray) -> np.ndarray:
    """Return the covariance of the estimates against ``maps`` (started at ``T``, one
    direction, final d_max), about their mean, in the tangent space at ``T``."""
    from estimation.registration import Registration, RegistrationConfig

    cfg = RegistrationConfig(max_correspondence_distance=D_FINAL, symmetric=False)
    at = gtsam.Pose3(T)
    xi = np.array([gtsam.Pose3.Logmap(at.between(gtsam.Pose3(
        Registration(source, m, cfg).run(T).T))) for m in maps])
    xi -= xi.mean(axis=0)
    return xi.T @ xi / (len(maps) - 1)


def half_room_trials(points: np.ndarray, labels: np.ndarray, target: SemanticCloud,
                     trials: int, options: dict[str, dict], source_points: int = SOURCE_POINTS,
                     offset: str = "small"):
    """Yield (key, RegistrationResult, T_target_source) of ours (GICP-SE(3)) for seeds 0 ..
    ``trials - 1``, each seed's half-room source and start registered once per ``options``
    key (further RegistrationConfig fields): paired comparisons of options on one map."""
    metres, degrees, d0 = OFFSETS[offset]
    for seed in range(trials):
        for key, extra in options.items():
            rng = np.random.default_rng(seed)
            source, T_gt = half_room_source(points, labels, rng, source_points)
            init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres,
                                                degrees)
            result, _ = register_ours(source, target, init, (d0, D_FINAL), **extra)
            yield key, result, T_gt


def run_cell(points, labels, kind, offset, trials, methods, seed0=0, setting="half",
             phases=0, source_points=SOURCE_POINTS, ours: dict | None = None,
             map_phase: str = "fixed", source_cloud: tuple | None = None,
             noise: float = SOURCE_NOISE, map_index: int = 0,
             wrong_blocks: float | None = None) -> dict:
    """Return every trial's numbers of one (room, map kind, offset, setting) cell.

    ``ours``: further RegistrationConfig fields for every method of ours. ``map_phase``
    "random": each trial's map is voxelised with a grid shifted by its own random phase
    (:func:`phase_shift`; the trial's source is the same as with "fixed").

    ``phases`` > 1 (GICP-SE(3), "half"): also the NEES with the grid-phase covariance
    (:func:`phase_covariance`) added, as ``nees_phase``.

    ``source_cloud`` (points, labels; "half"): draw each trial's half from this cloud (other
    depth frames of the room) instead of the map's own points.

    ``noise``: the standard deviation (m, per axis) of the Gaussian noise added to each
    trial's source (0: the drawn points themselves).

    ``map_index`` ("half", one map for every trial): the map's grid phase (:func:`map_shift`;
    0: the default grid).

    ``wrong_blocks`` (m): the sources' wrong labels in whole blocks (:func:`block_flips`).
    """
    # one map for every trial, or (a part's map, a random phase) one per trial below
    target = (labelled(*voxel_map(points, labels, kind, shift=map_shift(map_index)))
              if setting == "half" and map_phase == "fixed" else None)
    maps = phase_maps(points, labels, kind, phases) if phases > 1 and setting == "half" else []
    sizes, source_sizes = [], []
    metres, degrees, d0 = OFFSETS[offset]
    rows = {m: [] for m in methods}
    for trial in range(seed0, seed0 + trials):
        rng = np.random.default_rng(trial)
        shift = phase_shift(trial) if map_phase == "random" else None
        if setting == "part":
            source, T_gt, part = room_part_source(points, labels, rng, n=source_points,
                                                  noise=noise, wrong_blocks=wrong_blocks)
            target = labelled(*voxel_map(points[part], labels[part], kind, shift=shift))
        else:
            cloud = (points, labels) if source_cloud is None else source_cloud
            source, T_gt = half_room_source(*cloud, rng, source_points, noise,
                                            wrong_blocks=wrong_blocks)
            if shift is not None:
                target = labelled(*voxel_map(points, labels, kind, shift=shift))
        sizes.append(len(target.points))
        source_sizes.append(len(source.points))
        init = T_gt @ offset_about_centroid(rng, source.points.mean(axis=0), metres, degrees)
        for method in methods:
            if method == "open3d-gicp":
                T, seconds = run_open3d(source, target, init, (d0, D_FINAL))
                result = None
            else:
                options = {**(ours or {}), **{"gicp-se3-nogate": {"boundary_gate": None},
                                              "gicp-se3-nearest": {"voxel_matching": None},
                                              "gicp-se3-midpoint": {
                                                  "partial_voxel_matching": False},
                                              "gicp-se3-own": {
                                                  "pooled_source_covariance": False},
                                              "semantic-icp-once": {"semantic_rescue": False},
                                              }.get(method, {})}
                result, seconds = register_ours(source, target, init, (d0, D_FINAL),
                                                semantic=method.startswith("semantic-icp"),
                                                **options)
                T = result.T
            err = pose_error(T, T_gt)
            row = {"d_se3": err.d_se3, "t_err_m": err.t_err_m, "time_s": seconds}
            if result is not None:
                diagnostic = result.diagnostic
                # in the map's frame, where an error every trial shares is one vector
                adjoint = gtsam.Pose3(T_gt).AdjointMap()
                row.update(nees=float(nees(err.tangent, result.covariance)),
                           error_map=(adjoint @ err.tangent).tolist(),
                           covariance_map=(adjoint @ result.covariance @ adjoint.T).tolist(),
                           converged=bool(result.converged), rescued=bool(result.rescued),
                           trusted=bool(diagnostic is not None and diagnostic.trusted),
                           symmetric=bool(diagnostic is not None and diagnostic.symmetric))
                if diagnostic is not None:  # (what the trust rules read; NaN: not measured)
                    row.update(direction_gap=float(diagnostic.direction_gap),
                               off_surface=float(diagnostic.off_surface),
                               overlap=[float(v) for v in diagnostic.overlap],
                               correlation_ratio=float(diagnostic.correlation_ratio))
                if maps and method == "gicp-se3":
                    P = result.covariance + phase_covariance(source.points, maps, T)
                    row["nees_phase"] = float(nees(err.tangent, P))
            rows[method].append(row)
    return {"n_target": int(np.median(sizes)), "n_source": int(np.median(source_sizes)),
            "rows": rows}


def in_right_basin(row: dict) -> bool:
    """Whether a trial's ``row`` converged within 0.1 m of the truth (a row without a
    ``converged`` entry counts as converged)."""
    return row.get("converged", True) and row["t_err_m"] < 0.1


def right_basin_nees(rows: list[dict]) -> list[float]:
    """Return the NEES of ``rows``' converged runs within 0.1 m of the truth."""
    return [r["nees"] for r in rows if "nees" in r and in_right_basin(r)]


def report(name: str, kind: str, offset: str, cell: dict, setting: str = "half") -> None:
    rows = cell["rows"]
    ref = rows["open3d-gicp"]
    n = len(ref)
    lower, upper = chi2_bounds(6, n)
    what = ("half against the whole room's map" if setting == "half" else
            f"part against an overlapping part's map ({PART_OVERLAP:g} m slab)")
    print(f"\n{name} room, {what}, 3 cm voxel {kind} (median {cell['n_target']} points), "
          f"sources of {cell['n_source']} points (median), {offset} offset, {n} trials; "
          f"95 % bounds of the mean NEES of {n} "
          f"[{lower:.2f}, {upper:.2f}]; NEES and trusted over the converged runs")
    print("| method | success | converged | median d_SE3 mm | paired d_SE3 / open3d | "
          "median time s | paired time / open3d | NEES mean (median) | trusted | midpoint |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    t_ref = np.array([r["time_s"] for r in ref])
    for method, trials in rows.items():
        d = np.array([r["d_se3"] for r in trials])
        t = np.array([r["time_s"] for r in trials])
        ok = np.array([r["t_err_m"] < 0.1 for r in trials])
        converged = [r for r in trials if r.get("converged", True)]
        line = (f"| {method} | {ok.mean():.0%} | "
                f"{f'{len(converged)}/{n}' if 'converged' in trials[0] else '-'} | "
                f"{np.median(d) * 1e3:.2f} | "
                f"{np.median(d / [r['d_se3'] for r in ref]):.2f} | {np.median(t):.3f} | "
                f"{np.median(t / t_ref):.2f} | ")
        if "nees" in trials[0] and converged:
            v = np.array([r["nees"] for r in converged])
            line += (f"{v.mean():.2f} ({np.median(v):.2f}) | "
                     f"{sum(r['trusted'] for r in converged)}/{len(converged)} | "
                     f"{sum(r['symmetric'] for r in converged)}/{len(converged)} |")
        else:
            line += "- | - | - |"
        print(line)
        both = ok & np.array([r["t_err_m"] < 0.1 for r in ref])
        if method != "open3d-gicp" and 0 < both.sum() < n:
            # failed runs stop at different iteration caps (Open3D 30 a stage, ours 150):
            # the time where both found the right basin, apart
            ratio = np.median(t[both] / t_ref[both])
            print(f"  {method} where both found the right basin ({both.sum()} trials): paired "
                  f"time / open3d {ratio:.2f}")
        right = right_basin_nees(converged)
        if right and len(right) < len(converged):
            # a converged run in another basin carries a NEES in the thousands, which no
            # covariance covers: the calibration of the runs in the right basin, apart
            low, high = chi2_bounds(6, len(right))
            print(f"  {method} over its {len(right)} converged runs within 0.1 m: mean NEES "
                  f"{np.mean(right):.2f} (median {np.median(right):.2f}), 95 % bounds "
                  f"[{low:.2f}, {high:.2f}]")
        rescued = [r for r in trials if r.get("rescued")]
        if rescued:
            # Semantic-ICP's second start, geometric annealing, after an untrusted result
            print(f"  {method}: {len(rescued)} of {n} runs rescued by a second start with "
                  f"geometric annealing, {sum(r['t_err_m'] < 0.1 for r in rescued)} of them "
                  f"within 0.1 m")
        trusted = [r for r in converged if r.get("trusted")]
        if trusted:
            # what a user who keeps only the trusted results gets
            low, high = chi2_bounds(6, len(trusted))
            print(f"  {method} over its {len(trusted)} trusted runs: mean NEES "
                  f"{np.mean([r['nees'] for r in trusted]):.2f}, 95 % bounds [{low:.2f}, "
                  f"{high:.2f}]; {sum(r['t_err_m'] >= 0.1 for r in trusted)} of them 0.1 m "
                  f"or more off")
        right_runs = [r for r in converged if "error_map" in r and in_right_basin(r)]
        if len(right_runs) >= 2:
            # every trial of a cell registers to the same map (--map-phase fixed): the map's
            # error is common to them, one draw for all, which N trials do not average
            split = nees_about_common(np.array([r["error_map"] for r in right_runs]),
                                      np.array([r["covariance_map"] for r in right_runs]))
            print(f"  {method} about the common error of its {len(right_runs)} runs within "
                  f"0.1 m (map frame, [tx ty tz] mm "
                  f"{np.array2string(split.common[3:] * 1e3, precision=2)}, / its standard "
                  f"error {np.array2string(split.common / split.standard_error, precision=1)}"
                  f" [rx ry rz tx ty tz]): mean NEES {split.about_common:.2f} about it (the "
                  f"variation between runs), {split.common_part:.2f} of the common error "
                  f"alone (one draw for every run)")
        with_phase = [r["nees_phase"] for r in converged if "nees_phase" in r]
        if with_phase:
            print(f"  {method} with the grid-phase covariance of the room's points "
                  f"({len(with_phase)} converged trials): mean NEES {np.mean(with_phase):.2f} "
                  f"(median {np.median(with_phase):.2f})")


def report_maps(cells: list[dict]) -> None:
    """Print, per method of ours, each map's mean NEES over its converged runs within 0.1 m
    (``cells``: one :func:`run_cell` per map, the same trials), how many of those means lie
    inside the 95 % band of a mean of their count, and the mean over every map and run."""
    print(f"  over {len(cells)} maps (grid phases; map 0 the default grid), the converged "
          "runs within 0.1 m:")
    for method in cells[0]["rows"]:
        table = nees_by_map_and_trial(cells, method)
        per_map = [row[np.isfinite(row)].tolist() for row in table]
        if not any(per_map):
            continue
        means = [np.mean(v) if v else float("nan") for v in per_map]
        inside = 0
        for v in filter(None, per_map):
            low, high = chi2_bounds(6, len(v))
            inside += low <= np.mean(v) <= high
        every = np.concatenate([v for v in per_map if v])
        low, high = chi2_bounds(6, len(every))
        print(f"  {method}: mean NEES per map {' '.join(f'{m:.2f}' for m in means)} "
              f"(range {np.nanmin(means):.2f}-{np.nanmax(means):.2f}; {inside} of "
              f"{sum(bool(v) for v in per_map)} inside the band of their count); over every "
              f"map and run {every.mean():.2f} (median {np.median(every):.2f}, {len(every)} "
              f"runs), 95 % bounds [{low:.2f}, {high:.2f}]")
        # the runs share their map's grid phase and their trial's half: few draws
        low, high = crossed_bootstrap_interval(table)
        print(f"  {method}: that mean's 95 % interval with the maps and the trials resampled "
              f"(crossed bootstrap; runs of one map share its grid phase, runs of one trial "
              f"its half, noise, labels and start) [{low:.2f}, {high:.2f}]: 6 "
              + ("inside" if low <= 6.0 <= high else "outside"))
        splits = trial_splits(cells, method)
        if splits:
            # a trial's half, noise, labels and start are the same against every map: its
            # error common to the maps is that draw, its variation about it the grid phase's
            print(f"  {method} per trial over the maps, mean NEES (of the trial's common error:"
                  " its half, noise and start; about it: the grid phase's): "
                  + "; ".join(f"{t} {s.mean:.2f} ({s.common_part:.2f}; {s.about_common:.2f})"
                              for t, s, _ in splits))


def nees_by_map_and_trial(cells: list[dict], method: str) -> np.ndarray:
    """Return the (maps, trials) NEES of ``method``'s runs in ``cells`` (one :func:`run_cell`
    per map, the same trials), NaN where a run did not converge within 0.1 m."""
    return np.array([[r["nees"] if "nees" in r and in_right_basin(r) else np.nan
                      for r in cell["rows"][method]] for cell in cells])


def trial_splits(cells: list[dict], method: str
                 ) -> list[tuple[int, CommonErrorSplit, int]]:
    """Return (trial, :func:`nees_about_common` split, runs) of each trial with a converged
    run within 0.1 m against at least two of ``cells``' maps (the same trials in each), its
    errors and covariances in the map's frame."""
    out = []
    for trial in range(len(cells[0]["rows"][method])):
        runs = [r for r in (cell["rows"][method][trial] for cell in cells)
                if "error_map" in r and in_right_basin(r)]
        if len(runs) >= 2:
            out.append((trial, nees_about_common(np.array([r["error_map"] for r in runs]),
                                                 np.array([r["covariance_map"] for r in runs])),
                        len(runs)))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rooms", default="tum,icl",
                        help="comma-separated: tum,icl,scan (scan: OctoMap's laser scan)")
    parser.add_argument("--maps", default="centroids,centres",
                        help="comma-separated: centroids,centres")
    parser.add_argument("--offsets", default="small",
                        help="comma-separated: small,wide,near (near: 5 cm / 2 deg, "
                        "started at the final d_max)")
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--first-trial", type=int, default=0, metavar="K",
                        help="the trials' seeds are K .. K + TRIALS - 1 (each seed draws a "
                        "trial's half, noise, labels and start; the sizes of the map term were "
                        "chosen on seeds 0-5 of the raw halves)")
    parser.add_argument("--step", type=int, default=5, help="every STEP-th frame makes the room")
    parser.add_argument("--frames", default=None, metavar="START:STOP",
                        help="the RGB-D rooms fused from their frames START .. STOP - 1 only "
                        "(another view of the room from the same sequence; default: all)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--setting", default="half", choices=("half", "part"),
                        help="half: a half against the room's map; part: a part against the "
                        "map of an overlapping part")
    parser.add_argument("--classes", type=int, default=N_GEOMETRIC,
                        help="semantic classes: 4 = the geometric ones; more stand in for "
                        "object labels (each 0.6 m block's segments hashed over them)")
    parser.add_argument("--source-points", type=int, default=SOURCE_POINTS, metavar="N",
                        help="points drawn for each trial's source (0: every point of the "
                        "half, a raw half-room cloud)")
    parser.add_argument("--json", metavar="PATH", help="also write every trial's numbers")
    parser.add_argument("--phase-covariance", type=int, default=0, metavar="K",
                        help="also the NEES with the spread over K grid phases of the room's "
                        "own points added (GICP-SE(3), half setting; a diagnosis)")
    parser.add_argument("--plane-tilt", type=float, default=None, metavar="RAD",
                        help="RegistrationConfig.plane_tilt for ours (default: its own, "
                        "0.001, a real room's lattice map; 0: none)")
    parser.add_argument("--lattice-noise", default=None, metavar="M",
                        help="RegistrationConfig.lattice_noise for ours (m), or 'none' (the "
                        "sawtooth term of planes tilted against a lattice off; default: the "
                        "config's default)")
    parser.add_argument("--map-phase", default="fixed", choices=("fixed", "random"),
                        help="fixed: one map per room for every trial; random: each trial's "
                        "map voxelised with its own random grid phase (an independent draw "
                        "of the grid's part of the map's error)")
    parser.add_argument("--map-phases", type=int, default=1, metavar="M",
                        help="register every trial against M maps of the room: the default "
                        "grid and M - 1 random grid phases; prints each map's mean NEES "
                        "and the mean over all (half setting, --map-phase fixed)")
    parser.add_argument("--map-error", default=None, metavar="S",
                        help="RegistrationConfig.map_error for ours, in pitches, or 'none' "
                        "(the term off; default: the config's default)")
    parser.add_argument("--source-frames", default="map", choices=("map", "other"),
                        help="map: each half is drawn from the map's own points with 5 mm "
                        "of noise added; other: the map is fused from every 2*STEP-th "
                        "frame from the first, the halves from the frames between (an "
                        "independent scan of the room, its own sensor noise only; half "
                        "setting, RGB-D rooms)")
    parser.add_argument("--noise", type=float, default=None, metavar="M",
                        help="the Gaussian noise (m, per axis) added to a source drawn from "
                        f"the map's own points (default {SOURCE_NOISE:g}; 0: none; not with "
                        "--source-frames other, whose halves carry their own sensor noise "
                        "only)")
    parser.add_argument("--wrong-blocks", type=float, default=None, metavar="M",
                        help="change the sources' 10 %% wrong labels in whole M-metre blocks "
                        "(each block to one other class: a segmentation's errors come in "
                        "regions) instead of point by point")
    parser.add_argument("--systematic-sigma", default=None, metavar="S|SX,SY,SZ",
                        help="RegistrationConfig.systematic_sigma for ours (m): an offset "
                        "common to the whole source that the data cannot show (an "
                        "independent scan's disagreement with the map; default 0)")
    parser.add_argument("--coarse", default="normals", choices=("normals", "strided"),
                        help="ours' coarse subset: half of it over the surface normals' "
                        "directions (default), or all of it evenly strided (before the "
                        "twenty-first round; docs/registration_notes.md, 'Normal-space sampling "
                        "of the coarse subset')")
    args = parser.parse_args(argv)
    ours = {} if args.plane_tilt is None else {"plane_tilt": args.plane_tilt}
    for field in ("map_error", "lattice_noise"):
        value = getattr(args, field)
        if value is not None:
            try:
                ours[field] = None if value.lower() == "none" else float(value)
            except ValueError:
                parser.error(f"--{field.replace('_', '-')} must be a number or 'none', "
                             f"got {value!r}")
    if args.systematic_sigma is not None:
        from pipelines.validate import OptionError, systematic_sigma

        try:
            ours["systematic_sigma"] = systematic_sigma(args.systematic_sigma)
        except OptionError as exc:
            parser.error(str(exc))
    if set(args.rooms.split(",")) - set(ROOMS):
        parser.error(f"--rooms must be from {', '.join(ROOMS)}")
    if args.source_frames == "other" and (args.setting != "half" or "scan" in args.rooms):
        parser.error("--source-frames other needs --setting half and RGB-D rooms (tum, icl)")
    if args.noise is not None and args.source_frames == "other":
        parser.error("--noise applies to sources drawn from the map's own points, not to "
                     "--source-frames other")
    # (the other frames' halves carry their own sensor noise only)
    if args.noise is None:
        args.noise = 0.0 if args.source_frames == "other" else SOURCE_NOISE
    if not (np.isfinite(args.noise) and args.noise >= 0.0):
        parser.error(f"--noise must be a finite number >= 0, got {args.noise}")
    if args.wrong_blocks is not None and not (np.isfinite(args.wrong_blocks)
                                              and args.wrong_blocks > 0.0):
        parser.error(f"--wrong-blocks must be a finite number > 0, got {args.wrong_blocks}")
    start, stop = 0, None
    if args.frames is not None:
        try:
            start, stop = (int(v) for v in args.frames.split(":"))
        except ValueError:
            parser.error(f"--frames must be START:STOP (frame indices), got {args.frames!r}")
        if not 0 <= start < stop or "scan" in args.rooms:
            parser.error("--frames needs 0 <= START < STOP and RGB-D rooms (tum, icl)")
    if args.source_points < 0:
        parser.error("--source-points must be 0 (all) or positive")
    if args.classes < N_GEOMETRIC:
        parser.error(f"--classes must be at least {N_GEOMETRIC}")
    global N_CLASSES
    N_CLASSES = args.classes
    if args.first_trial < 0:
        parser.error(f"--first-trial must be at least 0, got {args.first_trial}")
    if args.map_phases < 1 or args.map_phases > 1 and (
            args.setting != "half" or args.map_phase != "fixed"):
        parser.error("--map-phases must be at least 1; above 1 it needs --setting half and "
                     "--map-phase fixed")
    if args.phase_covariance == 1 or args.phase_covariance < 0:
        parser.error("--phase-covariance needs at least 2 phases (or 0: off)")
    methods = args.methods.split(",")
    if "open3d-gicp" not in methods or set(methods) - set(METHODS):
        parser.error(f"--methods must be from {', '.join(METHODS)} and include open3d-gicp")
    if args.coarse == "strided":  # (for this process: the options are all checked)
        from estimation.registration import gicp

        gicp.NORMAL_SPACE_SAMPLING = False
    out = {}
    print(f"load average at start {os.getloadavg()[0]:.2f}")
    for name in args.rooms.split(","):
        other = args.source_frames == "other"
        points, labels = room_cloud(name, 2 * args.step if other else args.step, start=start,
                                    stop=stop)
        source_cloud = (room_cloud(name, 2 * args.step, start=start + args.step, stop=stop)
                        if other else None)
        if N_CLASSES > N_GEOMETRIC:
            labels = object_labels(points, labels, N_CLASSES)
            if other:
                source_cloud = (source_cloud[0], object_labels(*source_cloud, N_CLASSES))
        print(f"{name} room: {len(points)} points, classes {np.bincount(labels).tolist()}"
              + (f"; halves from the other frames' {len(source_cloud[0])} points"
                 if other else f"; sources with {args.noise * 1e3:g} mm of noise")
              + ("" if args.wrong_blocks is None
                 else f"; wrong labels in {args.wrong_blocks:g} m blocks"))
        # compile/load the numba kernels outside the timings
        warm = labelled(points[::50], labels[::50])
        register_ours(warm, warm, np.eye(4), (D_FINAL,))
        for kind in args.maps.split(","):
            for offset in args.offsets.split(","):
                cells = [run_cell(points, labels, kind, offset, args.trials, methods,
                                  seed0=args.first_trial, setting=args.setting,
                                  phases=args.phase_covariance,
                                  source_points=args.source_points, ours=ours,
                                  map_phase=args.map_phase, source_cloud=source_cloud,
                                  noise=args.noise, map_index=index,
                                  wrong_blocks=args.wrong_blocks)
                         for index in range(args.map_phases)]
                for index, cell in enumerate(cells):
                    if len(cells) > 1:
                        print(f"\nmap {index} of {len(cells)}"
                              + (" (the default grid)" if index == 0 else
                                 f" (grid phase {np.round(map_shift(index) * 1e3, 1)} mm)"))
                    report(name, kind, offset, cell, args.setting)
                key = f"{name}/{kind}/{offset}/{args.setting}"
                if len(cells) == 1:
                    out[key] = cells[0]
                else:
                    report_maps(cells)
                    out.update({f"{key}/map{index}": cell for index, cell in enumerate(cells)})
    print(f"\nload average at end {os.getloadavg()[0]:.2f}")
    if args.json:
        with atomic_write(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
