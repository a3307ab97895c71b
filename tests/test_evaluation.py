"""Trajectory evaluation: association, Umeyama, APE/RPE, KITTI/TUM files, `octofactor eval`.

Hand-computed cases always run; the comparisons with evo (GPL, a test-only dependency)
are skipped when evo is not installed.
"""
from __future__ import annotations

import copy
import json
import subprocess
import sys
import tempfile
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimation.errors import EstimationError, FormatError
from estimation.evaluation import (
    TrajectoryMetrics,
    associate,
    evaluate_trajectory,
    rotation_angle,
    umeyama_alignment,
)
from estimation.io import read_tum_arrays
from estimation.trajectory_io import (
    detect_trajectory_format,
    matrices_from_tum,
    read_kitti_arrays,
    read_trajectory,
    tum_from_matrices,
    write_kitti,
    write_tum_arrays,
)
from pipelines.cli import main

TUM_RPY = "rgbd/tum_fr1_rpy"


# ---------------------------------------------------------------- helpers
def make_pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def random_rigid(rng: np.random.Generator) -> np.ndarray:
    return make_pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 3, 3))


def helix_poses(n: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """(n, 4, 4) poses on a helix (positions not collinear); random rotations if rng."""
    k = np.arange(n)
    positions = np.stack([np.cos(0.3 * k), np.sin(0.3 * k), 0.1 * k], axis=1)
    if rng is None:
        rotations = np.tile(np.eye(3), (n, 1, 1))
    else:
        rotations = Rotation.random(n, random_state=rng).as_matrix()
    return np.stack([make_pose(R, p) for R, p in zip(rotations, positions)])


def rz(angle: float) -> np.ndarray:
    return Rotation.from_euler("z", angle).as_matrix()


# ---------------------------------------------------------------- associate
def test_associate_offset_start_and_jitter():
    # Ground truth at 100 Hz from 0.5 s; the estimate at 30 Hz from 0 s with +-4 ms jitter.
    t_gt = 0.5 + 0.01 * np.arange(100)
    jitter = np.array([0.004, -0.003, 0.002, -0.004, 0.001] * 10)
    t_est = np.arange(50) / 30.0 + jitter
    idx_gt, idx_est = associate(t_gt, t_est, max_diff=0.02)
    # By hand, the ground truth spans [0.5, 1.49]: t_est[14] = 0.4677 is 32 ms early,
    # t_est[15] = 0.504 matches, t_est[45] = 1.504 is 14 ms late (matches), t_est[46] =
    # 1.5303 is 40 ms late. So estimates 15..45 match and the first 15 do not.
    assert idx_est.tolist() == list(range(15, 46))
    assert np.all(np.diff(t_gt[idx_gt]) > 0)
    # Each match is the nearest ground-truth stamp.
    nearest = np.abs(t_gt[None, :] - t_est[idx_est, None]).argmin(axis=1)
    assert idx_gt.tolist() == nearest.tolist()
    assert idx_gt[0] == int(round((t_est[15] - 0.5) / 0.01))


def test_associate_pairs_are_unique_closest_first():
    # first 1.000 and 1.004 both want second 1.003; the closer one (1.004, |dt| 1 ms) wins
    # and 1.000 takes its next-closest candidate 0.990 (10 ms).
    t_first = np.array([1.000, 1.004, 2.0])
    t_second = np.array([0.990, 1.003, 1.5, 2.015])
    idx_first, idx_second = associate(t_first, t_second, max_diff=0.02)
    assert idx_first.tolist() == [0, 1, 2]
    assert idx_second.tolist() == [0, 1, 3]
    # With max_diff 5 ms the loser has no candidate left and drops out.
    idx_first, idx_second = associate(t_first, t_second, max_diff=0.005)
    assert idx_first.tolist() == [1]
    assert idx_second.tolist() == [1]


def test_associate_offset_sorting_and_empty():
    t_first = np.array([3.0, 1.0, 2.0])                 # unsorted on purpose
    t_second = np.array([11.001, 12.002, 13.0])
    idx_first, idx_second = associate(t_first, t_second, max_diff=0.01, offset=-10.0)
    assert idx_first.tolist() == [1, 2, 0]              # sorted by t_first
    assert idx_second.tolist() == [0, 1, 2]
    assert associate(t_first, t_second, max_diff=0.01)[0].size == 0   # offset switched off
    assert associate(t_first, np.zeros(0))[0].size == 0
    # |dt| == max_diff is accepted.
    assert associate(np.array([0.0]), np.array([0.5]), max_diff=0.5)[0].tolist() == [0]


# ---------------------------------------------------------------- umeyama
def test_umeyama_recovers_random_se3_and_sim3():
    rng = np.random.default_rng(7)
    src = rng.normal(0, 2, (40, 3))
    R_true = Rotation.random(random_state=rng).as_matrix()
    t_true = rng.normal(0, 5, 3)
    dst = src @ R_true.T + t_true
    R, t, s = umeyama_alignment(src, dst)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == 1.0
    R, t, s = umeyama_alignment(src, 2.5 * dst, with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, 2.5 * t_true, atol=1e-11)
    assert s == pytest.approx(2.5, rel=1e-12)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(8)
    src = rng.normal(0, 1, (30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])              # a mirror image
    R, _, _ = umeyama_alignment(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize("src", [
    np.zeros((5, 3)),                                   # all equal
    np.outer(np.arange(5.0), [1.0, 2.0, 3.0]),          # collinear
    np.zeros((2, 3)),                                   # too few
    np.zeros((5, 2)),                                   # wrong shape
])
def test_umeyama_rejects_degenerate_input(src):
    with pytest.raises(EstimationError):
        umeyama_alignment(src, src)


def test_rotation_angle_is_accurate_near_zero_and_pi():
    for angle in (1e-9, 0.3, np.pi - 1e-7, np.pi):
        R = Rotation.from_rotvec(angle * np.array([0.6, 0.0, 0.8])).as_matrix()
        assert rotation_angle(R) == pytest.approx(angle, rel=1e-6, abs=1e-15)


# ---------------------------------------------------------------- evaluate_trajectory
def test_rigidly_moved_ground_truth_has_zero_aligned_error(rng):
    T_gt = helix_poses(30, rng)
    W = random_rigid(rng)                               # T_estworld_gtworld
    T_est = W @ T_gt
    stamps = 0.1 * np.arange(30)
    m = evaluate_trajectory(stamps, T_gt, stamps, T_est)
    assert m.matched == 30
    assert m.ate_aligned_rmse_m < 1e-12 and m.ate_aligned_max_m < 1e-12
    assert m.ate_origin_aligned_rmse_m < 1e-12
    assert m.rpe_trans_rmse_m < 1e-12 and m.rpe_rot_rmse_deg < 1e-6
    assert m.rot_err_max_deg < 1e-6 and m.aligned_rot_err_mean_deg < 1e-6
    np.testing.assert_allclose(np.array(m.T_gtworld_estworld), np.linalg.inv(W), atol=1e-12)
    # Unaligned: the distance each position moved, by hand.
    moved = np.linalg.norm(T_est[:, :3, 3] - T_gt[:, :3, 3], axis=1)
    assert m.ate_unaligned_rmse_m == pytest.approx(np.sqrt(np.mean(moved**2)), rel=1e-12)


def test_pure_translation_offset():
    T_gt = helix_poses(20)
    T_est = T_gt.copy()
    T_est[:, :3, 3] += [0.3, -0.4, 0.0]                 # |offset| = 0.5 m
    m = evaluate_trajectory(None, T_gt, None, T_est)
    assert m.ate_unaligned_rmse_m == pytest.approx(0.5, rel=1e-12)
    assert m.ate_aligned_rmse_m < 1e-12 and m.ate_origin_aligned_rmse_m < 1e-12
    assert m.max_matched_time_diff_s == 0.0


def test_rpe_and_rotation_error_of_a_rotation_drift():
    # Same positions, the estimate turns by a = 1 deg more per frame about z.
    n, a = 12, np.radians(1.0)
    T_gt = helix_poses(n)
    T_est = np.stack([make_pose(rz(k * a), T_gt[k, :3, 3]) for k in range(n)])
    m = evaluate_trajectory(None, T_gt, None, T_est)
    assert m.rpe_rot_rmse_deg == pytest.approx(1.0, rel=1e-9)
    # E_k = [Rz(a), Rz(-k a) d_k - d_k]: |.| = 2 |d_xy| sin(k a / 2), d the gt step.
    steps = np.diff(T_gt[:, :3, 3], axis=0)
    trans = 2 * np.linalg.norm(steps[:, :2], axis=1) * np.sin(np.arange(n - 1) * a / 2)
    assert m.rpe_trans_rmse_m == pytest.approx(np.sqrt(np.mean(trans**2)), rel=1e-9)
    # Relative to frame 0 the error at frame k is k degrees.
    assert m.rot_err_mean_deg == pytest.approx(np.mean(np.arange(n)), rel=1e-9)
    assert m.rot_err_max_deg == pytest.approx(n - 1, rel=1e-9)
    assert m.ate_unaligned_rmse_m == 0.0


def test_rpe_of_a_scale_drift_and_delta():
    T_gt = helix_poses(10)
    T_est = T_gt.copy()
    T_est[:, :3, 3] *= 1.1
    m = evaluate_trajectory(None, T_gt, None, T_est)
    steps = np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1)
    assert m.rpe_trans_rmse_m == pytest.approx(0.1 * np.sqrt(np.mean(steps**2)), rel=1e-9)
    assert m.rpe_rot_rmse_deg == 0.0 and m.rot_err_max_deg == 0.0
    m2 = evaluate_trajectory(None, T_gt, None, T_est, rpe_delta=2)
    assert (m.rpe_pairs, m2.rpe_pairs) == (9, 4)        # evo: (0,2) (2,4) (4,6) (6,8)
    steps2 = np.linalg.norm(T_gt[2:9:2, :3, 3] - T_gt[0:7:2, :3, 3], axis=1)
    assert m2.rpe_trans_rmse_m == pytest.approx(0.1 * np.sqrt(np.mean(steps2**2)), rel=1e-9)


def test_body_frame_rotation_offset_shows_only_after_alignment():
    # est_k = gt_k Rx(b): positions equal, so the alignment is the identity and every
    # frame is off by b; relative to frame 0 nothing changes (gt rotations are identity).
    b = np.radians(3.0)
    T_gt = helix_poses(15)
    T_est = T_gt @ make_pose(Rotation.from_euler("x", b).as_matrix(), np.zeros(3))
    m = evaluate_trajectory(None, T_gt, None, T_est)
    assert m.aligned_rot_err_mean_deg == pytest.approx(3.0, rel=1e-9)
    assert m.rot_err_max_deg < 1e-9


def test_ground_truth_starting_after_the_estimate(rng):
    T_est = helix_poses(40, rng)
    t_est = 0.1 * np.arange(40)
    t_gt = t_est[10:] + 0.003
    m = evaluate_trajectory(t_gt, T_est[10:], t_est, T_est)
    assert (m.matched, m.first_matched_est_index, m.first_matched_gt_index) == (30, 10, 0)
    assert m.max_matched_time_diff_s == pytest.approx(0.003)
    assert m.ate_aligned_rmse_m < 1e-12


def test_metrics_to_dict_is_json_ready():
    m = evaluate_trajectory(None, helix_poses(5), None, helix_poses(5))
    out = json.loads(json.dumps(m.to_dict()))
    assert set(out) == {f.name for f in fields(TrajectoryMetrics)}
    assert out["T_gtworld_estworld"][3] == [0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("case, message", [
    ("few", "only 2 pose pairs matched"),
    ("nan", "pose 1 has NaN"),
    ("shape", "(N, 4, 4)"),
    ("lengths", "matched by index"),
    ("one_stamp", "for both trajectories or for neither"),
    ("delta", "leaves no pose pair"),
    ("stamp_len", "differ in length"),
])
def test_evaluate_errors(case, message):
    T = helix_poses(5)
    stamps = np.arange(5.0)
    args = dict(t_gt=stamps, T_gt=T, t_est=stamps, T_est=T)
    if case == "few":
        args["t_est"] = np.array([0.0, 1.0, 20.0, 30.0, 40.0])
    elif case == "nan":
        args["T_est"] = T.copy()
        args["T_est"][1, 0, 3] = np.nan
    elif case == "shape":
        args["T_gt"] = T[:, :3, :]
    elif case == "lengths":
        args.update(t_gt=None, t_est=None, T_est=T[:4])
    elif case == "one_stamp":
        args["t_gt"] = None
    elif case == "delta":
        args["rpe_delta"] = 5
    elif case == "stamp_len":
        args["t_est"] = stamps[:4]
    with pytest.raises(EstimationError, match=message.replace("(", r"\(").replace(")", r"\)")):
        evaluate_trajectory(**args)


# ---------------------------------------------------------------- files
def test_kitti_round_trip_is_exact(tmp_path, rng):
    T = helix_poses(25, rng)
    T[:, :3, 3] += rng.normal(0, 1e3, (25, 3))
    write_kitti(tmp_path / "poses.txt", T)
    assert np.array_equal(read_kitti_arrays(tmp_path / "poses.txt"), T)
    assert detect_trajectory_format(tmp_path / "poses.txt") == "kitti"
    stamps, T_read = read_trajectory(tmp_path / "poses.txt")
    assert stamps is None and np.array_equal(T_read, T)


def test_tum_array_round_trip_is_exact(tmp_path, rng):
    stamps = 1305031229.528748 + np.cumsum(rng.uniform(0.02, 0.05, 25))
    poses = tum_from_matrices(helix_poses(25, rng))
    write_tum_arrays(tmp_path / "traj.txt", stamps, poses)
    stamps_read, poses_read = read_tum_arrays(tmp_path / "traj.txt")
    assert np.array_equal(stamps_read, stamps) and np.array_equal(poses_read, poses)
    assert detect_trajectory_format(tmp_path / "traj.txt") == "tum"


def test_tum_matrix_conversion_round_trip(rng):
    T = helix_poses(20, rng)
    np.testing.assert_allclose(matrices_from_tum(tum_from_matrices(T)), T, atol=1e-14)


_finite = st.floats(-1e9, 1e9, allow_nan=False)
_quaternion = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 0.1)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(_quaternion, st.tuples(_finite, _finite, _finite), _finite),
                min_size=1, max_size=5))
def test_round_trips_property(rows):
    quats = np.array([q for q, _, _ in rows]) / np.linalg.norm([q for q, _, _ in rows],
                                                               axis=1, keepdims=True)
    translations = np.array([t for _, t, _ in rows])
    stamps = np.array([s for _, _, s in rows])
    T = matrices_from_tum(np.hstack([translations, quats]))
    with tempfile.TemporaryDirectory() as tmp:
        write_kitti(Path(tmp) / "k.txt", T)
        assert np.array_equal(read_kitti_arrays(Path(tmp) / "k.txt"), T)
        poses = np.hstack([translations, quats])
        write_tum_arrays(Path(tmp) / "t.txt", stamps, poses)
        stamps_read, poses_read = read_tum_arrays(Path(tmp) / "t.txt")
        assert np.array_equal(stamps_read, stamps) and np.array_equal(poses_read, poses)


_GOOD_KITTI = "1 0 0 0 0 1 0 0 0 0 1 0\n"


@pytest.mark.parametrize("bad_line, message", [
    ("1 0 0 0 0 1 0 0 0 0 1\n", "expected 12 numbers, found 11"),
    ("1 0 0 0 0 1 0 0 0 0 1 x\n", "could not convert"),
    ("1 0 0 nan 0 1 0 0 0 0 1 0\n", "NaN or inf"),
    ("1 0.1 0 0 0 1 0 0 0 0 1 0\n", "not orthonormal"),
    ("1 0 0 0 0 1 0 0 0 0 -1 0\n", "reflection"),
])
def test_kitti_bad_line_names_file_and_line(tmp_path, bad_line, message):
    path = tmp_path / "poses.txt"
    path.write_text(_GOOD_KITTI + "\n" + bad_line)
    with pytest.raises(FormatError, match=message) as info:
        read_kitti_arrays(path)
    assert str(info.value).startswith(f"{path}:3:")


def test_detect_format_rejects_other_column_counts(tmp_path):
    path = tmp_path / "x.txt"
    path.write_text("# header\n1 2 3\n")
    with pytest.raises(FormatError, match=r"x.txt:2: 3 values"):
        detect_trajectory_format(path)
    path.write_text("# only a comment\n")
    with pytest.raises(FormatError, match="no poses found"):
        read_trajectory(path)


# ---------------------------------------------------------------- CLI
def _write_pair(tmp_path: Path, rng) -> tuple[Path, Path]:
    T_gt = helix_poses(20, rng)
    stamps = 0.1 * np.arange(20)
    T_est = random_rigid(rng) @ T_gt
    T_est[:, :3, 3] += rng.normal(0, 0.01, (20, 3))
    write_tum_arrays(tmp_path / "gt.txt", stamps, tum_from_matrices(T_gt))
    write_tum_arrays(tmp_path / "est.txt", stamps + 0.004, tum_from_matrices(T_est))
    return tmp_path / "gt.txt", tmp_path / "est.txt"


def test_cli_eval_prints_table_and_writes_json(tmp_path, rng, capsys):
    gt, est = _write_pair(tmp_path, rng)
    out = tmp_path / "metrics.json"
    assert main(["eval", str(gt), str(est), "-o", str(out)]) == 0
    table = capsys.readouterr().out
    for label in ("matched:", "ATE aligned:", "ATE unaligned:", "ATE origin-align:",
                  "RPE (delta 1):", "rotation error:"):
        assert label in table
    data = json.loads(out.read_text())
    assert set(data) == {f.name for f in fields(TrajectoryMetrics)}
    assert data["matched"] == 20
    assert 0 < data["ate_aligned_rmse_m"] < 0.05 < data["ate_unaligned_rmse_m"]
    # --quiet prints nothing; --max-diff below the 4 ms offset leaves nothing to match.
    assert main(["eval", str(gt), str(est), "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert main(["eval", str(gt), str(est), "--max-diff", "0.001"]) == 2
    assert "only 0 pose pairs matched" in capsys.readouterr().err


def test_cli_eval_kitti(tmp_path, rng, capsys):
    T_gt = helix_poses(12, rng)
    write_kitti(tmp_path / "gt.txt", T_gt)
    write_kitti(tmp_path / "est.txt", random_rigid(rng) @ T_gt)
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"),
                 "--format", "kitti", "--delta", "2", "-o", str(tmp_path / "m.json")]) == 0
    data = json.loads((tmp_path / "m.json").read_text())
    assert data["matched"] == 12 and data["rpe_pairs"] == 5
    assert data["ate_aligned_rmse_m"] < 1e-9
    # A TUM file against a KITTI file is refused.
    (tmp_path / "tum").mkdir()
    gt_tum, _ = _write_pair(tmp_path / "tum", rng)
    assert main(["eval", str(gt_tum), str(tmp_path / "est.txt")]) == 2
    assert "same format" in capsys.readouterr().err


def test_cli_eval_bad_file_is_one_line_exit_2(tmp_path, rng):
    gt, _ = _write_pair(tmp_path, rng)
    bad = tmp_path / "bad.txt"
    bad.write_text("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 2\n")   # quaternion norm 2
    result = subprocess.run([sys.executable, "-m", "pipelines", "eval", str(gt), str(bad)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1
    assert f"{bad}:2:" in result.stderr and "Traceback" not in result.stderr


# ---------------------------------------------------------------- comparison with evo
@pytest.fixture(scope="module")
def evo_modules():
    pytest.importorskip("evo")
    from evo.core import geometry, metrics, sync
    from evo.tools import file_interface

    return geometry, metrics, sync, file_interface


@pytest.fixture
def tum_pair(shared_data, tmp_path):
    """Real TUM fr1/rpy ground truth and a perturbed, rigidly moved copy at the rgb stamps.

    The estimate's poses are the ground-truth poses nearest to each rgb timestamp, with
    1 cm / 0.6 deg noise, in another world frame; so association, alignment and every
    metric matter.
    """
    gt_path = shared_data / TUM_RPY / "groundtruth.txt"
    t_gt, poses_gt = read_tum_arrays(gt_path)
    t_rgb = np.loadtxt(shared_data / TUM_RPY / "rgb.txt", usecols=0, comments="#")
    rng = np.random.default_rng(2024)
    T_gt = matrices_from_tum(poses_gt)
    T_est = T_gt[np.abs(t_gt[None, :] - t_rgb[:, None]).argmin(axis=1)]
    noise = Rotation.from_rotvec(rng.normal(0, 0.01, (len(t_rgb), 3))).as_matrix()
    T_est[:, :3, :3] = noise @ T_est[:, :3, :3]
    T_est[:, :3, 3] += rng.normal(0, 0.01, (len(t_rgb), 3))
    T_est = random_rigid(rng) @ T_est
    est_path = tmp_path / "est.txt"
    write_tum_arrays(est_path, t_rgb, tum_from_matrices(T_est))
    return gt_path, est_path


@pytest.mark.reference
@pytest.mark.parametrize("offset", [0.0, 0.25])
def test_associate_matches_evo(evo_modules, tum_pair, offset):
    _, _, sync, file_interface = evo_modules
    gt_path, est_path = tum_pair
    t_gt, _ = read_tum_arrays(gt_path)
    t_est, _ = read_tum_arrays(est_path)
    idx_gt, idx_est = associate(t_gt, t_est, max_diff=0.02, offset=offset)
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref_sync, est_sync = sync.associate_trajectories(ref, est, max_diff=0.02, offset_2=offset)
    assert len(idx_gt) == ref_sync.num_poses > 100
    np.testing.assert_array_equal(t_gt[idx_gt], ref_sync.timestamps)
    np.testing.assert_array_equal(t_est[idx_est], est_sync.timestamps)


@pytest.mark.reference
def test_umeyama_matches_evo(evo_modules):
    geometry = evo_modules[0]
    rng = np.random.default_rng(11)
    src = rng.normal(0, 1, (50, 3))
    dst = 1.7 * src @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(0, 1, 3)
    dst += rng.normal(0, 0.05, dst.shape)
    for with_scale in (False, True):
        ours = umeyama_alignment(src, dst, with_scale)
        theirs = geometry.umeyama_alignment(src.T, dst.T, with_scale)
        for a, b in zip(ours, theirs):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def _evo_synced(evo_modules, gt_path, est_path, t_gt_min=None):
    _, _, sync, file_interface = evo_modules
    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    if t_gt_min is not None:
        ref.reduce_to_ids(np.flatnonzero(ref.timestamps >= t_gt_min))
    return sync.associate_trajectories(ref, est, max_diff=0.02)


def _evo_rmse(metric, data) -> float:
    metric.process_data(data)
    return metric.get_all_statistics()


@pytest.mark.reference
@pytest.mark.parametrize("cut_gt_start", [False, True])
def test_ape_and_rpe_match_evo(evo_modules, tum_pair, cut_gt_start):
    _, metrics, _, _ = evo_modules
    gt_path, est_path = tum_pair
    t_gt, poses_gt = read_tum_arrays(gt_path)
    t_est, poses_est = read_tum_arrays(est_path)
    t_gt_min = t_est[10] if cut_gt_start else None  # ground truth starting after the estimate
    keep = slice(None) if t_gt_min is None else t_gt >= t_gt_min
    ours = evaluate_trajectory(t_gt[keep], matrices_from_tum(poses_gt[keep]), t_est,
                               matrices_from_tum(poses_est), max_diff=0.02)
    ref, est = _evo_synced(evo_modules, gt_path, est_path, t_gt_min)
    assert ours.matched == ref.num_poses
    assert ours.first_matched_est_index == (10 if cut_gt_start else 0)

    translation = metrics.PoseRelation.translation_part
    unaligned = _evo_rmse(metrics.APE(translation), (ref, est))
    assert ours.ate_unaligned_rmse_m == pytest.approx(unaligned["rmse"], rel=1e-10)
    assert ours.ate_unaligned_rmse_m > 0.5              # the estimate is in another frame

    est_aligned = copy.deepcopy(est)
    est_aligned.align(ref, correct_scale=False)
    aligned = _evo_rmse(metrics.APE(translation), (ref, est_aligned))
    for key in ("rmse", "mean", "median", "max"):
        assert getattr(ours, f"ate_aligned_{key}_m") == pytest.approx(aligned[key], rel=1e-9)
    assert 0.005 < ours.ate_aligned_rmse_m < 0.05

    est_origin = copy.deepcopy(est)
    est_origin.align_origin(ref)
    origin = _evo_rmse(metrics.APE(translation), (ref, est_origin))
    assert ours.ate_origin_aligned_rmse_m == pytest.approx(origin["rmse"], rel=1e-9)

    for delta in (1, 3):
        ours_delta = evaluate_trajectory(t_gt[keep], matrices_from_tum(poses_gt[keep]), t_est,
                                         matrices_from_tum(poses_est), rpe_delta=delta)
        rpe_t = _evo_rmse(metrics.RPE(translation, delta, metrics.Unit.frames), (ref, est))
        rpe_r = _evo_rmse(metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta,
                                      metrics.Unit.frames), (ref, est))
        assert ours_delta.rpe_trans_rmse_m == pytest.approx(rpe_t["rmse"], rel=1e-9)
        assert ours_delta.rpe_rot_rmse_deg == pytest.approx(rpe_r["rmse"], rel=1e-9)


@pytest.mark.reference
def test_kitti_reader_matches_evo(evo_modules, tmp_path, rng):
    file_interface = evo_modules[3]
    T = helix_poses(10, rng)
    write_kitti(tmp_path / "poses.txt", T)
    theirs = file_interface.read_kitti_poses_file(str(tmp_path / "poses.txt"))
    np.testing.assert_array_equal(np.array(theirs.poses_se3), read_kitti_arrays(
        tmp_path / "poses.txt"))
