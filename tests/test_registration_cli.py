"""`octofactor register`: RESULT.json contents, ground-truth errors, exit codes."""
from __future__ import annotations

import json

import gtsam
import numpy as np
from test_registration import make_pair, one_hot

from estimation.registration import write_transform
from perception.semantic_cloud import SemanticCloud
from pipelines.cli import main


def write_pair(tmp_path, seed=11):
    source, labels_s, target, labels_t, T_gt = make_pair(seed, 2000)
    SemanticCloud(source, one_hot(labels_s, acc=0.9)).write_ply(tmp_path / "src.ply")
    SemanticCloud(target, one_hot(labels_t, acc=0.9)).write_ply(tmp_path / "tgt.ply")
    write_transform(tmp_path / "gt.txt", T_gt)
    return T_gt


def test_register_writes_result_with_errors(tmp_path):
    T_gt = write_pair(tmp_path)
    init = T_gt @ gtsam.Pose3(gtsam.Rot3.Yaw(0.03), np.array([0.05, 0, 0])).matrix()
    write_transform(tmp_path / "init.txt", init)
    for method in ("gicp", "semantic"):
        out = tmp_path / f"{method}.json"
        code = main(["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"),
                     "--method", method, "--init", str(tmp_path / "init.txt"),
                     "--gt", str(tmp_path / "gt.txt"), "--max-corr", "0.3",
                     "--surface-radius", "none" if method == "gicp" else "auto", "-o", str(out)])
        data = json.loads(out.read_text())
        assert code == 0 and data["converged"]
        assert data["method"] == method
        assert np.array(data["T"]).shape == (4, 4)
        assert np.array(data["covariance"]).shape == (6, 6)
        assert data["d_se3"] < 0.01 and data["t_err_m"] < 0.005 and data["r_err_rad"] < 0.002
        assert data["time_s"] > 0 and data["iterations"] >= 1
        assert data["rescued"] is False  # (no annealing: one start)
        diagnostic = data["covariance_diagnostic"]
        assert diagnostic["quantisation_pitch_m"] is None  # measured-like clouds: no lattice
        assert diagnostic["inplane_quantisation"] is False  # (a lattice term)
        assert isinstance(diagnostic["covariance_trusted"], bool)
        assert diagnostic["correlation_ratio"] > 0 and diagnostic["model_error_share"] == 0
        # off a lattice: the midpoint of both directions, with their disagreement
        assert diagnostic["symmetric"] is True and diagnostic["direction_gap"] > 0
        # every point on a surface both clouds sampled: none just off the target's
        assert 0.0 <= diagnostic["off_surface"] < 0.05


def test_register_bad_input_exits_2(tmp_path, capsys):
    write_pair(tmp_path)
    (tmp_path / "bad.txt").write_text("1 0 0\n0 1 0\n")
    code = main(["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"),
                 "--init", str(tmp_path / "bad.txt"), "-o", str(tmp_path / "r.json")])
    assert code == 2 and "4x4" in capsys.readouterr().err
    code = main(["register", str(tmp_path / "missing.ply"), str(tmp_path / "tgt.ply"),
                 "-o", str(tmp_path / "r.json")])
    assert code == 2
    assert not (tmp_path / "r.json").exists()
    for bad in ("-0.1", "wide"):
        code = main(["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"),
                     "--surface-radius", bad, "-o", str(tmp_path / "r.json")])
        assert code == 2 and "--surface-radius" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


def test_register_failure_exits_1_with_reason(tmp_path):
    write_pair(tmp_path)
    far = np.eye(4)
    far[:3, 3] = [40.0, 0, 0]
    write_transform(tmp_path / "far.txt", far)
    out = tmp_path / "r.json"
    code = main(["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"),
                 "--init", str(tmp_path / "far.txt"), "-o", str(out)])
    data = json.loads(out.read_text())
    assert code == 1 and not data["converged"] and "correspondences" in data["reason"]


def test_the_summary_says_why_the_covariance_is_not_trusted():
    from pipelines.register_cmd import _summary

    out = {"method": "gicp", "converged": True, "reason": "converged", "iterations": 7,
           "inliers": 100, "time_s": 0.1,
           "covariance_diagnostic": {"covariance_trusted": False, "correlation_ratio": 0.99,
                                     "overlap": [1.0, 0.3]}}
    assert "inside a map whose voxel grid was not found" in _summary(out)
    out["covariance_diagnostic"].update(map_error_m=0.0009, overlap=[0.985, 0.3])
    assert "only 98.5% of it on the map's surfaces" in _summary(out)
    out["covariance_diagnostic"].update(overlap=[1.0, 0.3], correlation_ratio=4.5)
    assert "ratio 4.50" in _summary(out)
    out["covariance_diagnostic"].update(overlap=[0.7, 0.7], correlation_ratio=5.2)
    assert "residuals correlated beyond its blocks: ratio 5.20" in _summary(out)
    out["covariance_diagnostic"]["overlap"] = None
    assert "ratio 5.20" in _summary(out)
    out["covariance_diagnostic"]["direction_gap"] = 337.0
    assert "the two directions found different solutions: gap 337" in _summary(out)
    out["covariance_diagnostic"].update(direction_gap=22.8, off_surface=0.31)
    assert "31% of the source's points near the target lie just off its surfaces" in \
        _summary(out)
    out["converged"] = False
    assert "the estimate did not converge" in _summary(out)
    out["converged"] = True
    out["covariance_diagnostic"]["covariance_trusted"] = True
    assert "not trusted" not in _summary(out)
    assert "second start" not in _summary(out)
    out["rescued"] = True  # (Semantic-ICP's second start, geometric annealing)
    assert "second start with geometric annealing" in _summary(out)


def test_a_lattice_map_takes_a_real_rooms_plane_tilt_unless_told(tmp_path, capsys):
    """Against a voxel-lattice map the covariance allows its planes a real room's tilts
    within a layer by default (``plane_tilt`` 1 mrad, reported); ``--plane-tilt 0`` (the
    simulator's planes, exactly on the lattice) takes that term out: the estimate is the
    same, the covariance smaller. No note either way."""
    source, labels_s, target, labels_t, T_gt = make_pair(5, 6000)
    centres, rows = np.unique(np.floor(target / 0.03), axis=0, return_index=True)
    SemanticCloud(source[::3], one_hot(labels_s[::3])).write_ply(tmp_path / "src.ply")
    SemanticCloud((centres + 0.5) * 0.03, one_hot(labels_t[rows])).write_ply(
        tmp_path / "map.ply")
    write_transform(tmp_path / "gt.txt", T_gt)
    common = ["register", str(tmp_path / "src.ply"), str(tmp_path / "map.ply"), "--init",
              str(tmp_path / "gt.txt"), "--max-corr", "0.3"]
    results = {}
    for name, extra in (("default", []), ("tilt", ["--plane-tilt", "0.001"]),
                        ("zero", ["--plane-tilt", "0"])):
        capsys.readouterr()
        assert main([*common, *extra, "-o", str(tmp_path / f"{name}.json")]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        results[name] = json.loads((tmp_path / f"{name}.json").read_text()), lines
    data, lines = results["default"]
    assert abs(data["covariance_diagnostic"]["quantisation_pitch_m"] - 0.03) < 1e-6  # (float32)
    assert data["covariance_diagnostic"]["plane_tilt_rad"] == 0.001
    tilt, tilt_lines = results["tilt"]
    assert tilt["covariance"] == data["covariance"]
    zero, zero_lines = results["zero"]
    assert zero["covariance_diagnostic"]["plane_tilt_rad"] is None
    assert np.array_equal(zero["T"], data["T"])
    assert np.trace(np.array(zero["covariance"])) < np.trace(np.array(data["covariance"]))
    assert not any("note:" in line for line in lines + tilt_lines + zero_lines)
    # off a lattice: no tilt term, no note
    write_pair(tmp_path)
    capsys.readouterr()
    assert main(["register", str(tmp_path / "src.ply"), str(tmp_path / "tgt.ply"), "--init",
                 str(tmp_path / "gt.txt"), "-o", str(tmp_path / "off.json")]) == 0
    assert "note:" not in capsys.readouterr().out
    off = json.loads((tmp_path / "off.json").read_text())["covariance_diagnostic"]
    assert off["quantisation_pitch_m"] is None and off["plane_tilt_rad"] is None
    for bad in ("-0.001", "nan", "4"):
        assert main([*common, "--plane-tilt", bad, "-o", str(tmp_path / "bad.json")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--plane-tilt" in err[0], err
    assert not (tmp_path / "bad.json").exists()
