"""Writers and readers at the file level: atomic replace, temporaries, special files, API errors."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from estimation.errors import EstimationError, FormatError, OctofactorError
from estimation.fileio import (
    atomic_path,
    atomic_write,
    check_input_file,
    read_input_bytes,
    remove_stale_temporaries,
)

REPO_ROOT = Path(__file__).resolve().parents[1]


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".octofactor-" in p.name)


def test_exception_keeps_the_destination_and_removes_the_temporary(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as handle:
            handle.write("new\n")
            assert _temporaries(tmp_path) == [f".x.txt.octofactor-{os.getpid()}.tmp"]
            raise RuntimeError("boom")
    assert target.read_text() == "old\n"
    assert _temporaries(tmp_path) == []


def test_stale_temporary_of_a_dead_process_is_removed_by_the_next_write(tmp_path):
    """A SIGKILLed writer leaves its temporary; the next run writing the same path removes it
    (and keeps a live process's one)."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    stale = tmp_path / f".x.txt.octofactor-{int(dead.stdout)}.tmp"
    stale.write_text("partial")
    live = tmp_path / f".x.txt.octofactor-{os.getppid()}.tmp"  # our parent is alive
    live.write_text("being written")
    other = tmp_path / f".y.txt.octofactor-{int(dead.stdout)}.tmp"  # another destination
    other.write_text("partial")
    with atomic_write(tmp_path / "x.txt", "w") as handle:
        handle.write("done\n")
    assert (tmp_path / "x.txt").read_text() == "done\n"
    assert not stale.exists() and live.exists() and other.exists()
    assert remove_stale_temporaries(tmp_path / "y.txt") == [other]


def test_sigterm_removes_the_temporary_and_keeps_the_destination(tmp_path):
    """SIGTERM during a write (the CLI turns it into SystemExit): exit 143, old file intact."""
    target = tmp_path / "x.txt"
    target.write_text("old\n")
    script = textwrap.dedent(f"""
        import os, signal, time
        from estimation.fileio import atomic_write
        from pipelines.cli import run_command

        def command(args):
            with atomic_write({str(target)!r}, "w") as handle:
                handle.write("half of it")
                handle.flush()
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(30)
            return 0

        raise SystemExit(run_command(command, None))
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)), timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    assert target.read_text() == "old\n"
    assert _temporaries(tmp_path) == []


@pytest.mark.parametrize("kind", ["symlink", "fifo", "directory"])
def test_outputs_that_are_not_regular_files_are_refused(tmp_path, kind):
    path = tmp_path / "out.txt"
    if kind == "symlink":
        (tmp_path / "target.txt").write_text("kept\n")
        os.symlink("target.txt", path)
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        path.mkdir()
    with pytest.raises(OctofactorError, match="out.txt"):
        with atomic_write(path, "w") as handle:
            handle.write("x")
    if kind == "symlink":
        assert path.is_symlink() and (tmp_path / "target.txt").read_text() == "kept\n"
    assert _temporaries(tmp_path) == []


def test_device_output_is_refused():
    with pytest.raises(OctofactorError, match="/dev/null"):
        with atomic_write("/dev/null", "w") as handle:
            handle.write("x")


def test_write_errors_name_the_destination_not_the_temporary(tmp_path):
    long_name = tmp_path / ("n" * 300 + ".txt")
    with pytest.raises(OctofactorError) as info:
        with atomic_write(long_name, "w") as handle:
            handle.write("x")
    assert "n" * 300 + ".txt" in str(info.value) and ".octofactor-" not in str(info.value)


def test_atomic_path_renames_only_on_success(tmp_path):
    target = tmp_path / "cloud.ply"
    with atomic_path(target, suffix=".ply") as tmp:
        assert tmp.name.startswith(".cloud.ply.octofactor-") and tmp.suffix == ".ply"
        tmp.write_bytes(b"ply\n")
    assert target.read_bytes() == b"ply\n" and _temporaries(tmp_path) == []


def test_inputs_must_be_regular_files_of_bounded_size(tmp_path):
    with pytest.raises(FormatError, match="not a regular file"):
        read_input_bytes("/dev/zero")
    with pytest.raises(FormatError, match="directory"):
        check_input_file(tmp_path)
    (tmp_path / "f").write_bytes(b"x" * 100)
    with pytest.raises(FormatError, match="limit"):
        check_input_file(tmp_path / "f", max_bytes=99)
    assert read_input_bytes(tmp_path / "f", max_bytes=100) == b"x" * 100


def test_mapped_inputs_are_checked_alike_and_fall_back_to_reading(tmp_path, monkeypatch):
    """map_input_file: the same refusals as read_input_bytes, the same bytes, an empty file,
    and a plain read where the file system cannot map files."""
    import mmap

    from estimation.fileio import map_input_file

    with pytest.raises(FormatError, match="not a regular file"):
        map_input_file("/dev/zero")
    (tmp_path / "f").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(FormatError, match="limit"):
        map_input_file(tmp_path / "f", max_bytes=1023)
    mapped = map_input_file(tmp_path / "f")
    assert isinstance(mapped, mmap.mmap) and bytes(mapped) == bytes(range(256)) * 4
    (tmp_path / "empty").write_bytes(b"")
    assert bytes(map_input_file(tmp_path / "empty")) == b""

    def no_mmap(*args, **kwargs):
        raise OSError(19, "No such device")

    monkeypatch.setattr(mmap, "mmap", no_mmap)
    assert map_input_file(tmp_path / "f") == bytes(range(256)) * 4


# ------------------------------------------------------------------ API errors name the argument
def _api_cases():
    import gtsam

    from estimation.covariance import nees
    from estimation.pose_graph import PoseGraph
    from estimation.registration import Registration, RegistrationConfig
    from estimation.vp_ekf import VanishingPointEKF
    from estimation.vp_eskf import VanishingPointESKF
    from mapping import OcTree
    from perception.rgbd import CameraIntrinsics
    from perception.semantic_cloud import SemanticCloud
    from perception.vanishing_points import detect_manhattan

    def graph_with_lonely_node():
        graph = PoseGraph()
        for node_id in range(3):
            graph.add_node(node_id, gtsam.Pose3())
        graph.add_between(0, 1, gtsam.Pose3(), np.eye(6) * 0.01)
        return graph

    return {
        "octree prob_hit=1": (lambda: OcTree(0.1, prob_hit=1.0), "prob_hit"),
        "octree prob_miss=0": (lambda: OcTree(0.1, prob_miss=0.0), "prob_miss"),
        "octree resolution 1e300": (lambda: OcTree(1e300), "resolution"),
        "octree points (N, 2)": (
            lambda: OcTree(0.1).insert_point_cloud(np.zeros((5, 2)), np.zeros(3)), "points"),
        "octree origin (2,)": (
            lambda: OcTree(0.1).insert_point_cloud(np.zeros((5, 3)), np.zeros(2)), "origin"),
        "marginal of a node without factor": (
            lambda: graph_with_lonely_node().marginal_covariance(2), "node 2 has no factor"),
        "self-loop between factor": (
            lambda: graph_with_lonely_node().add_between(1, 1, gtsam.Pose3(), np.eye(6)),
            "self-loop"),
        "node id 2^60": (lambda: PoseGraph().add_node(2**60, gtsam.Pose3()), "node_id"),
        "EKF fx = 0": (lambda: VanishingPointEKF(np.diag([0.0, 1.0, 1.0])), "fx"),
        "ESKF K (2, 2)": (lambda: VanishingPointESKF(np.eye(2)), "K must be a 3x3"),
        "EKF cov_pose (3, 3)": (lambda: VanishingPointEKF(np.eye(3), cov_pose=np.eye(3)),
                                "cov_pose"),
        "registration alpha nan": (lambda: RegistrationConfig(cauchy_alpha=float("nan")),
                                   "cauchy_alpha"),
        "registration points (N, 2)": (
            lambda: Registration(np.zeros((30, 2)), np.zeros((30, 3))), "source points"),
        "nees shapes": (lambda: nees(np.zeros(3), np.eye(6)), "covariances"),
        "intrinsics fx = 0": (lambda: CameraIntrinsics(0.0, 1.0, 1.0, 1.0, 10, 10), "fx"),
        "labels 2e9": (lambda: SemanticCloud.from_labels(np.zeros((2, 3)), [0, 2_000_000_000]),
                       "n_classes"),
        "detector focal 1e300": (
            lambda: detect_manhattan(np.zeros((48, 64), np.uint8),
                                     np.diag([1e300, 1e300, 1.0])), "focal lengths"),
        "detector 1x1 image": (lambda: detect_manhattan(np.zeros((1, 1), np.uint8), np.eye(3)),
                               "1x1"),
    }


@pytest.mark.parametrize("name", sorted(_api_cases()))
def test_api_errors_are_octofactor_errors_naming_the_argument(name):
    call, expected = _api_cases()[name]
    with pytest.raises(OctofactorError, match=expected) as info:
        call()
    assert isinstance(info.value, OctofactorError)


def test_pose_graph_marginal_still_works_for_connected_nodes():
    """The negative control of the lonely-node check: a constrained node has a marginal."""
    import gtsam

    from estimation.pose_graph import PoseGraph

    graph = PoseGraph()
    graph.add_node(0, gtsam.Pose3())
    graph.add_node(1, gtsam.Pose3())
    graph.add_between(0, 1, gtsam.Pose3(), np.eye(6) * 0.01)
    graph.optimize()
    cov = graph.marginal_covariance(1)
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    with pytest.raises(EstimationError):
        graph.marginal_covariance(7)
