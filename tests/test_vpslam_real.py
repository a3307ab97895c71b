"""vpslam on the real RGB-D development sequences (../shared/data/rgbd, TUM layout)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipelines.cli import main

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
ICL = DATA / "icl_of_kt0"
ICL_K = "481.2,480,319.5,239.5"
TUM = DATA / "tum_fr1_rpy"
TUM_K = "517.3,516.5,318.6,255.3"

pytestmark = pytest.mark.skipif(not ICL.is_dir(), reason="../shared/data/rgbd is missing")


def _run(seq, out, *flags, frames=40, intrinsics=ICL_K):
    code = main(["vpslam", str(seq), "-o", str(out), "--quiet", "--no-map", "--intrinsics",
                 intrinsics, "--max-frames", str(frames), *flags])
    assert code == 0
    return json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def icl_runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("icl")
    return {name: _run(ICL, base / name, *flags) for name, flags in (
        ("default", ()), ("no_vp", ("--no-vp",)), ("lines", ("--detector", "lines")),
        ("normals", ("--detector", "normals")), ("keyframes", ("--keyframes",)))}


def test_the_vp_update_reduces_the_rotation_drift_on_icl(icl_runs):
    """Fails when the VP update is switched off: the directions must cut the VO's
    rotation drift (measured on 40 frames: 0.61 deg without, ~0.1-0.2 deg with)."""
    default, no_vp = icl_runs["default"], icl_runs["no_vp"]
    assert default["vp_updates"] > 50
    assert default["rot_err_mean_deg"] < 0.5 * no_vp["rot_err_mean_deg"]
    assert default["ate_aligned_rmse_m"] <= no_vp["ate_aligned_rmse_m"] * 1.05
    # each direction source alone helps too
    for name in ("lines", "normals"):
        assert icl_runs[name]["rot_err_mean_deg"] < no_vp["rot_err_mean_deg"]


def test_keyframe_odometry_runs_and_keeps_the_rotation(icl_runs):
    """--keyframes: fewer keyframes than frames, the same directions, ATE near frame to frame
    (measured on 40 frames: within 15 %)."""
    kf, default = icl_runs["keyframes"], icl_runs["default"]
    assert default["keyframes"] is None
    assert 1 <= kf["keyframes"] < kf["frames"] // 2
    assert kf["rot_err_mean_deg"] < 0.5 * icl_runs["no_vp"]["rot_err_mean_deg"]
    assert kf["ate_aligned_rmse_m"] < 1.5 * default["ate_aligned_rmse_m"]


def test_report_is_evo_style_with_groundtruth(icl_runs):
    report = icl_runs["default"]
    assert report["matched"] == 40
    assert report["world_frame"] == "groundtruth"
    assert 0 < report["ate_aligned_rmse_m"] <= report["ate_unaligned_rmse_m"] + 1e-12
    assert report["rpe_trans_rmse_m"] > 0 and report["rpe_rot_rmse_deg"] > 0


def test_tum_groundtruth_starting_late_is_matched_by_time(tmp_path):
    report = _run(TUM, tmp_path / "tum", frames=30, intrinsics=TUM_K)
    # the motion capture starts after the first colour frames: fewer matches than frames
    assert 0 < report["matched"] <= report["frames"] == 30
    assert report["ate_aligned_rmse_m"] < 0.05
    assert report["ate_unaligned_rmse_m"] < 0.2  # anchored at the first frame's GT pose


def test_intrinsics_flag_wins_over_a_camera_file_of_another_layout(tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(ICL, seq)
    (seq / "camera.txt").write_text("fx=481.2 fy=480\ncx=319.5 cy=239.5\n")
    report = _run(seq, tmp_path / "out", frames=3)
    assert report["frames"] == 3


def test_intrinsics_that_do_not_fit_the_images_are_one_line_errors(tmp_path, capsys):
    for intrinsics, words in (("481.2,480,1319.5,239.5", "outside"),
                              ("1e9,480,319.5,239.5", "does not fit")):
        code = main(["vpslam", str(ICL), "-o", str(tmp_path / "o"), "--quiet", "--no-map",
                     "--intrinsics", intrinsics, "--max-frames", "2"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and words in err[0], err


def test_a_corrupt_frame_is_named_skipped_and_counted(tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(ICL, seq)
    names = [line.split()[1] for line in (seq / "rgb.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    (seq / names[2]).write_bytes(b"not a png")
    report = _run(seq, tmp_path / "out", frames=5)
    err = capsys.readouterr().err
    assert "skipped frame 2" in err and names[2].split("/")[-1] in err
    assert report["frames"] == 4 and sum(report["skipped_frames"].values()) == 1


@pytest.fixture(scope="module")
def tum_runs():
    """tum_fr1_rpy, all 150 frames, three filters on one shared odometry."""
    from dataclasses import replace

    from perception.rgbd import CameraIntrinsics
    from pipelines.vpslam import VpSlamConfig, run_vpslam

    intr = CameraIntrinsics(*(float(v) for v in TUM_K.split(",")), 640, 480, 5000.0)
    cache: dict = {}
    default = VpSlamConfig(build_map=False)
    configs = {"default": default,
               "motion": replace(default, odometry=replace(default.odometry,
                                                           cov_model="motion")),
               "no_vp": replace(default, vp_model="none")}
    return {name: run_vpslam(TUM, None, config, intrinsics=intr, progress=False,
                             odometry_cache=cache).report for name, config in configs.items()}


def test_directions_never_cost_aligned_ate_on_the_whole_icl_sequence():
    """All 100 ICL-NUIM frames: the directions cut the rotation error below the issue's
    0.36 deg and the aligned ATE stays at most VO alone's. Fails with the VO covariance's
    coupling at 0.5 (measured: 0.574 cm against VO alone's 0.567) or with the directions off
    (rotation 0.86 deg); with 0.3: 0.556 cm, 0.13 deg."""
    from dataclasses import replace

    from perception.rgbd import CameraIntrinsics
    from pipelines.vpslam import VpSlamConfig, run_vpslam

    intr = CameraIntrinsics(*(float(v) for v in ICL_K.split(",")), 640, 480, 5000.0)
    cache: dict = {}
    default = VpSlamConfig(build_map=False)
    runs = {name: run_vpslam(ICL, None, config, intrinsics=intr, progress=False,
                             odometry_cache=cache).report
            for name, config in (("default", default),
                                 ("no_vp", replace(default, vp_model="none")))}
    default, no_vp = runs["default"], runs["no_vp"]
    assert default["matched"] == no_vp["matched"] == 100
    assert default["rot_err_mean_deg"] < min(0.36, no_vp["rot_err_mean_deg"])
    assert default["ate_aligned_rmse_m"] <= no_vp["ate_aligned_rmse_m"]


def test_directions_improve_rotation_and_translation_on_tum(tum_runs):
    """On a hand-held Kinect sequence the directions must beat VO alone in rotation and in
    aligned ATE; the latter needs the VO covariance's rotation-translation coupling (measured:
    ATE 5.0 cm coupled, 5.7 cm uncorrelated, 5.7 cm VO alone)."""
    default, motion, no_vp = tum_runs["default"], tum_runs["motion"], tum_runs["no_vp"]
    assert default["rot_err_mean_deg"] < no_vp["rot_err_mean_deg"]
    assert default["ate_aligned_rmse_m"] < 0.95 * no_vp["ate_aligned_rmse_m"]
    assert default["ate_aligned_rmse_m"] < 0.95 * motion["ate_aligned_rmse_m"]
    # VO alone is consistent on this sequence; the filter's NEES is reported, not hidden
    assert no_vp["pose_nees_mean"] is not None and no_vp["pose_nees_mean"] < 12


def test_directions_only_on_changed_views(tmp_path):
    """--vp-min-motion: frames that hardly moved since the last measured one are not
    measured again (counted as vp_same_view); the directions still cut the rotation drift."""
    report = _run(ICL, tmp_path / "gated", "--vp-min-motion", "2,0.02")
    assert report["vp_same_view"] > 10
    assert report["vp_updates"] > 0
    assert report["config"]["vp_min_motion"] == [2.0, 0.02]
    no_vp = _run(ICL, tmp_path / "no_vp", "--no-vp")
    assert report["rot_err_mean_deg"] < no_vp["rot_err_mean_deg"]


def test_overlapped_detection_gives_the_same_trajectory():
    """config.overlap runs the detectors' prediction-free work in a worker thread while the
    odometry runs: with one Open3D thread (the deterministic mode, another process) the
    trajectory is bit-identical to the sequential run, for each detector."""
    import subprocess
    import sys

    script = f"""
import numpy as np
from perception.rgbd import CameraIntrinsics
from pipelines.runtime import set_deterministic
from pipelines.vpslam import VpSlamConfig, run_vpslam
set_deterministic(0)
intr = CameraIntrinsics({ICL_K}, 640, 480, 5000.0)
for kw in (dict(), dict(detector="normals"), dict(detector="lines"),
           dict(vp_model="point", detector="seed")):
    T = [run_vpslam({str(ICL)!r}, None, VpSlamConfig(build_map=False, overlap=o, **kw),
                    intrinsics=intr, progress=False, max_frames=8).T_world_camera
         for o in (True, False)]
    print(kw, np.array_equal(T[0], T[1]))
"""
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 4 and all(line.endswith("True") for line in lines), lines
