"""The `octofactor` CLI: fast help, graph subcommands, one-line errors."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from estimation.io import read_g2o, write_g2o
from estimation.simulation import simulate_loop_graph
from pipelines.cli import main


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipelines", *args], capture_output=True,
                          text=True, timeout=300)


def test_help_imports_nothing_heavy():
    code = ("import sys; from pipelines.cli import build_parser; build_parser(); "
            "heavy = [m for m in ('open3d', 'cv2', 'numba', 'gtsam', 'matplotlib') "
            "if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
    help_text = run_cli("--help").stdout
    assert "graph" in help_text


def test_graph_convert_spherical_scan_is_byte_identical(shared_data, tmp_path):
    source = shared_data / "octomap" / "spherical_scan.graph"
    out = tmp_path / "x.graph"
    assert main(["graph", "convert", str(source), "-o", str(out)]) == 0
    assert out.read_bytes() == source.read_bytes()


def test_graph_info(shared_data, capsys):
    assert main(["graph", "info", str(shared_data / "octomap" / "spherical_scan.graph")]) == 0
    out = capsys.readouterr().out
    assert "nodes:   1" in out and "points:  10201 in 1 scans" in out


def test_graph_convert_reports_what_is_dropped(shared_data, tmp_path):
    result = run_cli("graph", "convert", str(shared_data / "octomap" / "spherical_scan.graph"),
                     "-o", str(tmp_path / "x.g2o"))
    assert result.returncode == 0
    assert "scans" in result.stderr and "dropped" in result.stderr


def test_graph_optimize_prints_errors_and_reduces_them(tmp_path, capsys):
    sim = simulate_loop_graph(np.random.default_rng(0), n_poses=12)
    write_g2o(tmp_path / "in.g2o", sim.graph)
    assert main(["graph", "optimize", str(tmp_path / "in.g2o"), "-o",
                 str(tmp_path / "out.g2o")]) == 0
    lines = capsys.readouterr().out.splitlines()
    initial = float(lines[0].split(":")[1])
    final = float(lines[1].split(":")[1].split()[0])
    assert final < initial
    assert read_g2o(tmp_path / "out.g2o").error() == pytest.approx(final, rel=1e-6)


@pytest.mark.parametrize("args, message", [
    (["graph", "info", "missing.graph"], "missing.graph: no such file"),
    (["graph", "info", "x.bin"], "unknown pose-graph format"),
])
def test_errors_are_one_line_and_exit_2(tmp_path, args, message):
    result = subprocess.run([sys.executable, "-m", "pipelines", *args], capture_output=True,
                            text=True, cwd=tmp_path, timeout=120)
    assert result.returncode == 2
    assert message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert "Traceback" not in result.stderr


def test_corrupt_file_error_names_file_and_offset(tmp_path):
    bad = tmp_path / "bad.graph"
    bad.write_bytes(b"\x05\x00\x00\x00garbage")
    result = run_cli("graph", "info", str(bad))
    assert result.returncode == 2
    assert f"{bad} (byte 4)" in result.stderr


def test_demo_writes_pose_graph_outputs(tmp_path):
    from pipelines.demo import pose_graph_demo

    summary = pose_graph_demo(tmp_path)
    for name in summary.files:
        assert (tmp_path / name).stat().st_size > 0
    assert summary.final_error < summary.initial_error
    assert summary.ate_optimized_m < summary.ate_initial_m


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--quick", "-o", str(out)]) == 0
    return out


@pytest.mark.slow
def test_quick_demo_writes_every_stage(quick_demo):
    tmp_path = quick_demo
    report = (tmp_path / "report.md").read_text()
    for heading in ("Pose graph", "VP-EKF SLAM", "Octree map", "calibration", "Consistency"):
        assert heading in report
    for name in ("pose_graph.png", "vpslam_comparison.png", "map_slice.png",
                 "vpslam_with_vp/map.bt", "vpslam_with_vp/map.ot", "vpslam_with_vp/trajectory.txt",
                 "report.json", "shared_graph/headset.json", "shared_graph/graph.g2o",
                 "shared_graph/graph.graph", "shared_graph/map.bt"):
        assert (tmp_path / name).stat().st_size > 0
    assert "One pose graph: SLAM, headset calibration and map" in report


@pytest.mark.slow
def test_quick_demo_headset_pose_and_marginal_come_from_the_one_graph(quick_demo):
    """The demo's headset.json: the headset pose near the truth, and its covariance the
    marginal of the saved joint graph (SLAM factors + calibration factor)."""
    import json

    tmp_path = quick_demo
    headset = json.loads((tmp_path / "shared_graph" / "headset.json").read_text())
    assert headset["registration_converged"]
    assert headset["t_err_m"] < 0.05 and headset["r_err_deg"] < 1.0
    cov = np.array(headset["covariance"])
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    graph = read_g2o(tmp_path / "shared_graph" / "graph.g2o")
    kinds = graph.factor_counts()
    assert kinds["prior"] == 1 and kinds["direction"] > 10
    node = headset["headset_node"]
    assert len(graph.nodes) == node + 1
    np.testing.assert_allclose(graph.nodes[node].pose.matrix(), headset["T_world_headset"],
                               atol=1e-9)
    np.testing.assert_allclose(graph.marginal_covariance(node), cov, rtol=1e-6, atol=1e-14)
    # the joint marginal includes the SLAM's uncertainty at the anchor: wider than the
    # registration alone
    registration = np.array(headset["registration_covariance"])
    assert np.trace(cov[3:, 3:]) > np.trace(registration[3:, 3:])
