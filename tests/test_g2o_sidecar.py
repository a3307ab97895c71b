"""The g2o sidecar X.g2o.json: what g2o cannot hold (timestamps, node covariances, priors,
direction factors) survives a write -> read; a sidecar that lies is an error; no made-up
timestamps."""
from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation import FormatError, OctofactorError, PoseGraph
from estimation.io import (
    g2o_sidecar_path,
    read_g2o,
    read_scan_graph,
    read_tum,
    write_g2o,
    write_scan_graph,
    write_tum,
)
from estimation.pose_graph import _ATTITUDE_FACTOR, node_key
from pipelines.cli import main


def _graph(rng, stamps, n_directions=3) -> PoseGraph:
    pg = PoseGraph()
    for k, stamp in enumerate(stamps):
        pose = gtsam.Pose3.Expmap(rng.normal(size=6) * [0.5, 0.5, 0.5, 3, 3, 3])
        A = rng.normal(size=(6, 6))
        pg.add_node(k, pose, timestamp=stamp, cov=A @ A.T * 1e-3 + np.eye(6) * 1e-6
                    if k % 2 else None)
    for k in range(len(stamps) - 1):
        T = pg.nodes[k].pose.between(pg.nodes[k + 1].pose)
        pg.add_between(k, k + 1, T, np.diag(rng.uniform(1e-4, 1e-2, size=6)))
    for _ in range(n_directions):
        k = int(rng.integers(len(stamps)))
        d_sensor = rng.normal(size=3)
        d_world = pg.nodes[k].pose.rotation().matrix() @ d_sensor + rng.normal(size=3) * 0.05
        B = rng.normal(size=(3, 3))
        pg.add_direction(k, d_sensor, d_world, B @ B.T * 1e-4)
    A = rng.normal(size=(6, 6))
    pg.add_prior(0, pg.nodes[0].pose.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * 0.01)),
                 A @ A.T * 1e-4 + np.eye(6) * 1e-8)
    return pg


def _assert_same_priors(back: PoseGraph, pg: PoseGraph) -> None:
    original = [r for r in pg.factors if r.kind == "prior"]
    read = [r for r in back.factors if r.kind == "prior"]
    assert len(read) == len(original) == 1
    values = pg.values()
    for a, b in zip(original, read):
        assert a.nodes == b.nodes
        assert b.measured.equals(a.measured, 1e-12)
        np.testing.assert_array_equal(b.covariance, a.covariance)
        assert b.factor.error(values) == pytest.approx(a.factor.error(values), rel=1e-9)


def _assert_same_directions(back: PoseGraph, pg: PoseGraph) -> None:
    original = [r for r in pg.factors if r.kind == "direction"]
    read = [r for r in back.factors if r.kind == "direction"]
    assert len(read) == len(original)
    values = pg.values()
    for a, b in zip(original, read):
        assert a.nodes == b.nodes
        for key in ("direction_sensor", "direction_world", "cov", "cov_tangent"):
            np.testing.assert_array_equal(b.metadata[key], a.metadata[key])
        assert b.factor.nRef().equals(a.factor.nRef(), 0)
        assert b.factor.bMeasured().equals(a.factor.bMeasured(), 0)
        assert b.factor.error(values) == a.factor.error(values)


@settings(max_examples=25, deadline=None)
@given(stamps=st.lists(st.floats(-1e10, 1e10, allow_nan=False), min_size=2, max_size=6),
       seed=st.integers(0, 2**31))
def test_sidecar_round_trip_is_exact(tmp_path_factory, stamps, seed):
    rng = np.random.default_rng(seed)
    pg = _graph(rng, stamps)
    path = tmp_path_factory.mktemp("g2o") / "graph.g2o"
    dropped = write_g2o(path, pg)
    assert "direction factors" not in " ".join(dropped) and "timestamps" not in dropped
    back = read_g2o(path)
    assert back.timestamps_missing is None
    for k, stamp in enumerate(stamps):
        assert back.nodes[k].timestamp == stamp  # bit for bit
        assert back.nodes[k].pose.equals(pg.nodes[k].pose, 1e-12)
        if pg.nodes[k].cov is None:
            assert back.nodes[k].cov is None
        else:
            np.testing.assert_array_equal(back.nodes[k].cov, pg.nodes[k].cov)
    _assert_same_directions(back, pg)
    _assert_same_priors(back, pg)
    assert back.factor_counts() == {"odometry": len(stamps) - 1, "direction": 3, "prior": 1}


def test_sidecar_name_and_schema(tmp_path):
    pg = _graph(np.random.default_rng(0), [1305031102.175304, 1305031102.2])
    write_g2o(tmp_path / "run.g2o", pg)
    assert g2o_sidecar_path(tmp_path / "run.g2o") == tmp_path / "run.g2o.json"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.g2o", "run.g2o.json"]
    document = json.loads((tmp_path / "run.g2o.json").read_text())
    assert document["format"] == "octofactor-g2o-sidecar" and document["version"] == 2
    assert document["g2o"] == "run.g2o"
    assert [n["id"] for n in document["nodes"]] == [0, 1]
    assert document["nodes"][0]["timestamp"] == 1305031102.175304
    assert document["nodes"][0]["cov"] is None and len(document["nodes"][1]["cov"]) == 6
    direction = document["directions"][0]
    assert set(direction) == {"node", "direction_sensor", "direction_world", "cov",
                              "cov_tangent"}
    prior = document["priors"][0]
    assert set(prior) == {"node", "kind", "pose", "cov"} and prior["node"] == 0


def test_version_1_sidecar_without_priors_is_still_read(tmp_path):
    pg = _graph(np.random.default_rng(3), [1.0, 2.0, 3.0])
    write_g2o(tmp_path / "g.g2o", pg)
    sidecar = tmp_path / "g.g2o.json"
    document = json.loads(sidecar.read_text())
    document["version"] = 1
    del document["priors"]
    sidecar.write_text(json.dumps(document))
    back = read_g2o(tmp_path / "g.g2o")
    assert back.factor_counts() == {"odometry": 2, "direction": 3}
    _assert_same_directions(back, pg)


def test_direction_factors_still_optimise_after_a_round_trip(tmp_path):
    truth = gtsam.Pose3(gtsam.Rot3.Ypr(0.4, 0.1, 0.0), np.zeros(3))
    pg = PoseGraph()
    pg.add_node(0, gtsam.Pose3(gtsam.Rot3.Ypr(0.1, 0.0, 0.0), np.zeros(3)))
    for d_world in np.eye(3)[:2]:
        pg.add_direction(0, truth.rotation().unrotate(d_world), d_world, np.eye(3) * 1e-6)
    write_g2o(tmp_path / "g.g2o", pg)
    back = read_g2o(tmp_path / "g.g2o")
    back.optimize()
    assert back.nodes[0].pose.rotation().equals(truth.rotation(), 1e-6)


def _bad_sidecar(tmp_path, edit) -> tuple:
    pg = _graph(np.random.default_rng(1), [1.0, 2.0, 3.0])
    path = tmp_path / "g.g2o"
    write_g2o(path, pg)
    sidecar = g2o_sidecar_path(path)
    text = sidecar.read_text()
    if callable(edit):
        document = json.loads(text)
        edit(document)
        text = json.dumps(document)
    else:
        text = edit
    sidecar.write_text(text)
    return path, sidecar


def _set(path: str, value):
    def edit(document):
        target = document
        keys = path.split("/")
        for key in keys[:-1]:
            target = target[int(key) if key.isdigit() else key]
        last = keys[-1]
        target[int(last) if last.isdigit() else last] = value
    return edit


@pytest.mark.parametrize("edit, message", [
    ('{"format": "octofactor-g2o-sidecar", "nodes": [', r"g.g2o.json:1: not valid JSON"),
    ("[]", "not an octofactor g2o sidecar"),
    (_set("version", 3), "sidecar version 3"),
    (_set("version", True), "sidecar version True"),
    (_set("priors", {}), "'priors' must be a list"),
    (_set("priors/0/node", 9), r"priors\[0\].node must be a node id"),
    (_set("priors/0/pose", [0.0] * 6), r"priors\[0\].pose must be an array of shape \(7,\)"),
    (_set("priors/0/pose", [0.0] * 7),
     r"priors\[0\].pose: quaternion qx qy qz qw has norm 0, not 1"),
    (_set("priors/0/cov", np.diag([1.0, 1, 1, 1, 1, -1]).tolist()), "not positive definite"),
    (_set("nodes/2/id", 7), r"node ids do not match the g2o file .*only in the sidecar: \[7\]"),
    (lambda d: d["nodes"].pop(), r"node ids do not match .*only in the g2o file: \[2\]"),
    (_set("nodes/1/id", 0), "duplicate ids"),
    (_set("nodes/0/timestamp", "1.0"), r"nodes\[0\].timestamp must be a finite number"),
    (_set("nodes/0/timestamp", True), r"nodes\[0\].timestamp must be a finite number"),
    (_set("nodes/0/timestamp", None), "some nodes have a timestamp and others null"),
    (_set("nodes/1/cov", [[1.0] * 5] * 6), r"nodes\[1\].cov must be an array of shape \(6, 6\)"),
    (_set("nodes/1/cov", np.diag([1.0, 1, 1, 1, 1, -1]).tolist()), "not positive definite"),
    (_set("directions/0/direction_world", [1.0, 0.0]),
     r"directions\[0\].direction_world must be an array of shape \(3,\), got shape \(2,\)"),
    (_set("directions/0/cov", [[1.0, 0.0, 0.0]] * 2 + [[0.0, 0.0]]),
     r"directions\[0\].cov must be an array of shape \(3, 3\), got rows of different"),
    (_set("directions/0/direction_world", [1.0, 1.0, 0.0]), "is not a unit vector"),
    (_set("directions/0/node", 9), r"directions\[0\].node must be a node id"),
    (_set("directions/0/cov_tangent", [[1.0, 0.0], [0.0, -1.0]]), "not positive definite"),
    (_set("directions", {}), "'directions' must be a list"),
])
def test_sidecar_that_does_not_match_is_a_format_error(tmp_path, edit, message):
    path, sidecar = _bad_sidecar(tmp_path, edit)
    with pytest.raises(FormatError, match=message) as info:
        read_g2o(path)
    assert str(info.value).startswith(str(sidecar))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_sidecar_non_finite_numbers_are_rejected(tmp_path, token):
    def edit(text):
        document = json.loads(text)
        document["nodes"][1]["timestamp"] = "PLACEHOLDER"
        return json.dumps(document).replace('"PLACEHOLDER"', token)

    pg = _graph(np.random.default_rng(1), [1.0, 2.0])
    write_g2o(tmp_path / "g.g2o", pg)
    sidecar = tmp_path / "g.g2o.json"
    sidecar.write_text(edit(sidecar.read_text()))
    with pytest.raises(FormatError, match="g.g2o.json: .*(non-finite|finite number)"):
        read_g2o(tmp_path / "g.g2o")


# ---------------------------------------------------------------- no made-up timestamps
def _foreign_g2o(tmp_path):
    """A g2o file as another tool writes it: no sidecar."""
    path = tmp_path / "foreign.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                    "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 "
                    + " ".join(str(v) for v in np.eye(6)[np.triu_indices(6)]) + "\n")
    return path


def test_g2o_without_sidecar_has_no_timestamps(tmp_path):
    graph = read_g2o(_foreign_g2o(tmp_path))
    assert "g2o cannot store timestamps" in graph.timestamps_missing
    with pytest.raises(OctofactorError, match="a TUM trajectory needs timestamps"):
        write_tum(tmp_path / "t.txt", graph)
    assert not (tmp_path / "t.txt").exists()
    # the sidecar written next keeps "unknown" rather than zeros
    write_g2o(tmp_path / "again.g2o", graph)
    stamps = [n["timestamp"] for n in json.loads((tmp_path / "again.g2o.json").read_text())[
        "nodes"]]
    assert stamps == [None, None]
    assert read_g2o(tmp_path / "again.g2o").timestamps_missing is not None


def test_scan_graph_has_no_timestamps(tmp_path):
    pg = PoseGraph()
    pg.add_node(0, gtsam.Pose3(), timestamp=5.0)
    write_scan_graph(tmp_path / "g.graph", pg)
    assert read_scan_graph(tmp_path / "g.graph").timestamps_missing is not None


def test_convert_g2o_to_tum_uses_the_sidecar(tmp_path, capsys):
    stamps = [1305031102.175304, 1305031102.211214, 1305031102.243211]
    pg = _graph(np.random.default_rng(2), stamps)
    write_g2o(tmp_path / "x.g2o", pg)
    assert main(["graph", "convert", str(tmp_path / "x.g2o"), "-o",
                 str(tmp_path / "traj.txt")]) == 0
    back = read_tum(tmp_path / "traj.txt")
    assert [back.nodes[k].timestamp for k in range(3)] == stamps
    assert main(["graph", "info", str(tmp_path / "x.g2o")]) == 0
    assert "direction 3" in capsys.readouterr().out


def test_convert_foreign_g2o_to_tum_refuses_in_one_line(tmp_path, capsys):
    source = _foreign_g2o(tmp_path)
    assert main(["graph", "convert", str(source), "-o", str(tmp_path / "traj.txt")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"octofactor: error: {tmp_path / 'traj.txt'}: a TUM trajectory needs "
                          f"timestamps, but {source} has none (g2o cannot store timestamps)")
    assert "foreign.g2o.json" in err  # how to get them: the sidecar octofactor writes
    assert not (tmp_path / "traj.txt").exists()
    assert main(["graph", "info", str(source)]) == 0
    assert "time:    unknown" in capsys.readouterr().out


def test_direction_factors_are_reported_dropped_by_scan_graph(tmp_path):
    pg = _graph(np.random.default_rng(3), [0.0, 1.0])
    assert "direction factors" in write_scan_graph(tmp_path / "g.graph", pg)
    assert write_g2o(tmp_path / "g.g2o", pg) == []
    # a direction factor added as a plain GTSAM factor is "custom": g2o still drops it
    factor = _ATTITUDE_FACTOR(node_key(0), gtsam.Unit3(np.array([1.0, 0, 0])),
                              gtsam.noiseModel.Isotropic.Sigma(2, 0.1))
    pg.add_factor(factor)
    assert write_g2o(tmp_path / "g.g2o", pg) == ["custom factors"]
