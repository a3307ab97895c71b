"""Vanishing points: seed method, Manhattan detector, covariance consistency, CLI."""
from __future__ import annotations

import csv
import dataclasses
import json

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.covariance import check_consistency, nees
from perception.errors import ImageError, PerceptionError
from perception.lines import read_image
from perception.vanishing_points import (
    ManhattanConfig,
    SeedConfig,
    VPResult,
    angle_between_directions,
    detect_manhattan,
    detect_seed,
    manhattan_from_segments,
)
from pipelines.cli import main

YUD_K = np.array([[674.917975, 0.0, 306.551305], [0.0, 674.917975, 250.454245], [0.0, 0.0, 1.0]])
K_SYN = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
INTRINSICS_YUD = "674.917975,674.917975,306.551305,250.454245"


# ----------------------------------------------------------------------------- helpers


def _random_rotation(rng: np.random.Generator, max_angle_deg: float = 30.0) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(5.0, max_angle_deg))
    R, _ = cv2.Rodrigues(axis * angle)
    return R


def _manhattan_segments(rng: np.random.Generator, R: np.ndarray, K: np.ndarray,
                        n_per_axis: int = 25, noise_px: float = 0.0,
                        shape=(480, 640)) -> np.ndarray:
    """Projected 3D segments along the columns of R (camera frame), inside the image."""
    h, w = shape
    segments = []
    for k in range(3):
        found = 0
        while found < n_per_axis:
            start = np.array([rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(3, 9)])
            end = start + R[:, k] * rng.uniform(0.8, 2.5)
            if end[2] < 1.0:
                continue
            p = np.array([start, end]) @ K.T
            uv = p[:, :2] / p[:, 2:]
            if not np.all((uv >= 5) & (uv <= [w - 6, h - 6])):
                continue
            if np.linalg.norm(uv[1] - uv[0]) < 40:
                continue
            segments.append(uv.ravel())
            found += 1
    segments = np.array(segments)
    return segments + rng.normal(scale=noise_px, size=segments.shape) if noise_px else segments


def _draw(segments: np.ndarray, shape=(480, 640)) -> np.ndarray:
    image = np.full(shape, 40, np.uint8)
    for x1, y1, x2, y2 in segments:
        cv2.line(image, (int(round(x1 * 16)), int(round(y1 * 16))),
                 (int(round(x2 * 16)), int(round(y2 * 16))), 220, 2, cv2.LINE_AA, shift=4)
    return image


def _yud(shared_data, every: int = 4, limit: int = 13):
    root = shared_data / "yud_train"
    with open(root / "ground_truth.csv", newline="") as handle:
        rows = sorted(csv.DictReader(handle), key=lambda r: r["image"])
    out = []
    for row in rows[::every][:limit]:
        dirs = np.array([[float(row[f"d{a}{k}"]) for a in "xyz"] for k in range(3)])
        out.append((root / row["image"] / f"{row['image']}.jpg", dirs))
    return out


def _forward_error_and_nees(result: VPResult, gt_dirs: np.ndarray, K: np.ndarray):
    gt = gt_dirs[int(np.argmax(np.abs(gt_dirs[:, 2])))]
    gt = gt if gt[2] >= 0 else -gt
    vp = min(result.vps, key=lambda v: float(angle_between_directions(v.direction, gt)))
    p = K @ gt
    err = vp.uv - p[:2] / p[2]
    error = float(angle_between_directions(vp.direction, gt))
    return error, float(nees(err[None], vp.cov[None])[0])


# ----------------------------------------------------------------------------- seed method


def test_seed_finds_rendered_vp_and_drops_axis_parallel_lines():
    rng = np.random.default_rng(1)
    vp = np.array([402.3, 231.7])
    segments = []
    for angle in np.radians(np.r_[rng.uniform(20, 70, 8), rng.uniform(110, 160, 8),
                                  rng.uniform(200, 250, 8), rng.uniform(290, 340, 8)]):
        direction = np.array([np.cos(angle), np.sin(angle)])
        r0, r1 = rng.uniform(40, 90), rng.uniform(160, 300)
        segments.append(np.r_[vp + r0 * direction, vp + r1 * direction])
    # door frames / posters: axis-parallel lines that do not pass through the VP
    segments += [[100, 50, 100, 400], [500, 60, 500, 420], [60, 30, 600, 30], [80, 450, 560, 450]]
    segments = np.clip(np.array(segments), 2, [637, 477, 637, 477])
    image = _draw(segments)
    result = detect_seed(image, K=K_SYN)
    assert len(result.vps) == 1
    found = result.vps[0]
    assert np.linalg.norm(found.uv - vp) < 1.0  # sub-pixel
    # the axis-parallel lines were dropped: no kept segment is within the tolerance of an axis
    kept = result.segments[found.inliers]
    folded = np.degrees(np.arctan2(np.abs(kept[:, 3] - kept[:, 1]),
                                   np.abs(kept[:, 2] - kept[:, 0])))
    assert np.all((folded > 10.0) & (folded < 80.0))
    # the covariance is an honest least-squares covariance: positive definite, pixel scale
    assert np.all(np.linalg.eigvalsh(found.cov) > 0)
    np.testing.assert_allclose(found.direction, np.linalg.solve(K_SYN, np.r_[found.uv, 1.0])
                               / np.linalg.norm(np.linalg.solve(K_SYN, np.r_[found.uv, 1.0])))


def test_seed_empty_on_blank_and_axis_only_images():
    assert detect_seed(np.zeros((480, 640), np.uint8)).vps == []
    grid = _draw(np.array([[100, 50, 100, 400], [60, 30, 600, 30], [300, 40, 300, 450]], float))
    assert detect_seed(grid, SeedConfig(axis_tolerance_deg=10.0)).vps == []


# ----------------------------------------------------------------------------- Manhattan


@pytest.mark.parametrize("seed", [3, 7])
def test_manhattan_recovers_rendered_rotation(seed):
    rng = np.random.default_rng(seed)
    R = _random_rotation(rng)
    image = _draw(_manhattan_segments(rng, R, K_SYN))
    result = detect_manhattan(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), K_SYN)
    assert len(result.vps) == 3
    found = np.array([vp.direction for vp in result.vps])
    errors = angle_between_directions(R.T[:, None, :], found[None, :, :]).min(axis=1)
    assert np.all(errors < 0.5), errors
    for vp in result.vps:
        assert vp.direction[2] >= 0 and abs(np.linalg.norm(vp.direction) - 1) < 1e-12
        assert len(vp.inliers) >= 10
        if vp.uv is not None:
            p = K_SYN @ vp.direction
            np.testing.assert_allclose(vp.uv, p[:2] / p[2], rtol=1e-9)
            assert np.all(np.linalg.eigvalsh(vp.cov) > 0)
    # forward = largest |dz|; results are deterministic (seeded RANSAC)
    assert result.forward() is max(result.vps, key=lambda v: abs(v.direction[2]))
    again = detect_manhattan(image, K_SYN)
    assert len(again.vps) == len(result.vps)
    for a, b in zip(result.vps, again.vps, strict=True):
        np.testing.assert_array_equal(a.direction, b.direction)
        np.testing.assert_array_equal(a.inliers, b.inliers)


def test_manhattan_covariance_is_consistent_for_endpoint_noise():
    """Monte Carlo NEES of the forward VP pixel with independent endpoint noise (0.3 px, the
    sub-pixel scale of LSD endpoints; much larger noise gets truncated by the inlier angle,
    which biases the residual variance low).

    With cov_scale=1 the propagated least-squares covariance must pass the chi-square test;
    the mis-tuned negative controls (5x over- and under-confident) must fail it."""
    rng = np.random.default_rng(2024)
    R = _random_rotation(rng, 25.0)
    clean = _manhattan_segments(rng, R, K_SYN, n_per_axis=20)
    forward = R[:, int(np.argmax(np.abs(R[2])))]
    forward = forward if forward[2] > 0 else -forward
    p = K_SYN @ forward
    truth_uv = p[:2] / p[2]
    values = {1.0: [], 0.2: [], 5.0: []}
    base = ManhattanConfig(cov_scale=1.0)
    for _ in range(150):
        noisy = clean + rng.normal(scale=0.3, size=clean.shape)
        result = manhattan_from_segments(noisy, K_SYN, base)
        vp = min(result.vps, key=lambda v: float(angle_between_directions(v.direction, forward)))
        err = vp.uv - truth_uv
        for scale in values:
            values[scale].append(float(nees(err[None], (scale * vp.cov)[None])[0]))
    assert check_consistency(np.array(values[1.0]), dof=2).passed
    assert not check_consistency(np.array(values[0.2]), dof=2).passed
    assert not check_consistency(np.array(values[5.0]), dof=2).passed


def test_manhattan_empty_results_without_exception():
    assert detect_manhattan(np.zeros((480, 640), np.uint8), K_SYN).vps == []
    assert detect_manhattan(np.full((8, 8), 255, np.uint8), K_SYN).vps == []
    assert manhattan_from_segments(np.zeros((0, 4)), K_SYN).vps == []
    two = np.array([[10, 10, 200, 100], [10, 300, 200, 200]], float)
    assert manhattan_from_segments(two, K_SYN).vps == []


def test_yud_accuracy_and_covariance_calibration(shared_data):
    """Aggregates over the 51 real York Urban training images: accuracy and NEES calibration.

    The default covariance (cov_scale=20) must put >= 80 % of the forward-VP NEES values under
    the 95 % chi-square(2) quantile (label noise of the ground truth included); the bare
    least-squares covariance (cov_scale=1) is the negative control that must fail the same
    check."""
    cv2.setNumThreads(1)
    bare_config = dataclasses.replace(ManhattanConfig(), cov_scale=1.0)
    errors, nees_default, nees_bare = [], [], []
    for path, gt_dirs in _yud(shared_data, every=1, limit=51):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        error, value = _forward_error_and_nees(detect_manhattan(image, YUD_K), gt_dirs, YUD_K)
        errors.append(error)
        nees_default.append(value)
        bare = detect_manhattan(image, YUD_K, bare_config)
        nees_bare.append(_forward_error_and_nees(bare, gt_dirs, YUD_K)[1])
    errors = np.array(errors)
    assert len(errors) == 51
    assert np.median(errors) < 0.8, np.median(errors)
    assert np.mean(errors < 5.0) >= 0.96, errors
    chi2_95 = 5.991
    assert np.mean(np.array(nees_default) < chi2_95) >= 0.8, nees_default
    assert not np.mean(np.array(nees_bare) < chi2_95) >= 0.8, nees_bare


# ----------------------------------------------------------------------------- files and CLI


def test_corrupt_and_missing_files_name_the_file(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(ImageError, match="broken.png"):
        read_image(bad)
    with pytest.raises(PerceptionError, match="missing.jpg"):
        read_image(tmp_path / "missing.jpg")
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    with pytest.raises(ImageError, match="empty.jpg"):
        read_image(empty)


def test_cli_json_schema_and_plot(shared_data, tmp_path, capsys):
    image = shared_data / "yud_train" / "P1020177" / "P1020177.jpg"
    assert main(["vp", str(image), str(image), "--intrinsics", INTRINSICS_YUD, "--json",
                 "-o", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    record = json.loads(lines[0])
    assert set(record) == {"image", "ms", "vps"}
    assert record["image"] == str(image) and isinstance(record["ms"], float)
    assert 1 <= len(record["vps"]) <= 3
    for vp in record["vps"]:
        assert set(vp) == {"u", "v", "direction", "cov", "inliers"}
        assert len(vp["direction"]) == 3 and vp["direction"][2] >= 0
        assert np.isclose(np.linalg.norm(vp["direction"]), 1.0)
        assert np.array(vp["cov"]).shape == (2, 2) and isinstance(vp["inliers"], int)
        assert (vp["u"] is None) == (vp["v"] is None)
    overlay = cv2.imread(str(tmp_path / "P1020177_vp.png"))
    assert overlay is not None and overlay.shape == (480, 640, 3)

    assert main(["vp", str(image), "--intrinsics", INTRINSICS_YUD, "--method", "seed",
                 "--json"]) == 0
    seed_record = json.loads(capsys.readouterr().out)
    assert len(seed_record["vps"]) <= 1


def test_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "corrupt.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0 definitely not a jpeg")
    assert main(["vp", str(bad), "--intrinsics", "500,500,320,240"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "corrupt.jpg" in err[0]
    assert main(["vp", str(bad), "--intrinsics", "500,500,320"]) == 2
    assert "--intrinsics" in capsys.readouterr().err


@settings(max_examples=25, deadline=None)
@given(rotvec=st.tuples(*[st.floats(-0.6, 0.6)] * 3), seed=st.integers(0, 2 ** 16))
def test_noise_free_segments_give_the_exact_rotation(rotvec, seed):
    """Property: noise-free Manhattan segments of any (moderate) rotation give its axes back."""
    R, _ = cv2.Rodrigues(np.array(rotvec))
    segments = _manhattan_segments(np.random.default_rng(seed), R, K_SYN, n_per_axis=8)
    result = manhattan_from_segments(segments, K_SYN)
    assert len(result.vps) == 3
    found = np.array([vp.direction for vp in result.vps])
    errors = angle_between_directions(R.T[:, None, :], found[None, :, :]).min(axis=1)
    assert np.all(errors < 1e-4), errors


def test_bad_inputs_raise_perception_errors():
    with pytest.raises(PerceptionError, match="K must be"):
        detect_manhattan(np.zeros((48, 64), np.uint8), np.eye(3) * 0.0)
    with pytest.raises(PerceptionError, match="shape"):
        detect_seed(np.zeros((4, 4, 4, 4), np.uint8))


def test_lone_vertical_vp_is_not_forward_and_junctions_are_not_vps():
    """A camera facing a wall sees only verticals (one VP, not 'forward'); long segments
    meeting at a junction must not be taken for a VP (a segment's image never reaches its
    VP). Control: with the on-segment check disabled the junction wins."""
    verticals = np.array([[x, 100, x, 220] for x in (40, 300, 420, 520, 600)], float)
    angles = np.radians([10, 75, 160, 200, 250, 320])
    junction = np.column_stack([np.full(6, 330.0), np.full(6, 260.0),
                                330 + 200 * np.cos(angles), 260 + 200 * np.sin(angles)])
    segments = np.vstack([verticals, junction])
    result = manhattan_from_segments(segments, K_SYN)
    assert len(result.vps) == 1
    assert abs(result.vps[0].direction[1]) > 0.99 and len(result.vps[0].inliers) == 5
    assert result.forward() is None
    assert result.forward(min_abs_dz=0.0) is result.vps[0]
    unchecked = manhattan_from_segments(segments, K_SYN, ManhattanConfig(vp_gap_px=-1e4))
    assert np.linalg.norm(unchecked.forward().uv - [330, 260]) < 1.0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 20), n=st.integers(0, 40), repeat=st.integers(1, 4),
       collinear=st.booleans())
def test_arbitrary_segments_never_raise(seed, n, repeat, collinear):
    """Property: any segment set (duplicates, collinear pieces, zero length) gives a result,
    never an exception, and every reported VP is well formed."""
    rng = np.random.default_rng(seed)
    segments = rng.uniform(0, 640, size=(n, 4))
    if collinear and n:
        # pieces of a few lines only: degenerate interpretation planes
        base = segments[: max(1, n // 8)]
        t = rng.uniform(0, 1, size=(n, 2))
        pick = base[rng.integers(0, len(base), n)]
        start = pick[:, :2] + t[:, :1] * (pick[:, 2:] - pick[:, :2])
        end = pick[:, :2] + t[:, 1:] * (pick[:, 2:] - pick[:, :2])
        segments = np.hstack([start, end])
    segments = np.vstack([segments] * repeat)
    result = manhattan_from_segments(segments, K_SYN)
    assert len(result.vps) <= 3
    for vp in result.vps:
        assert np.isclose(np.linalg.norm(vp.direction), 1.0) and vp.direction[2] >= 0
        assert vp.cov.shape == (2, 2) and not np.any(np.isnan(vp.cov))


@pytest.mark.parametrize("scale", [0.5, 0.8, 1.0])
def test_lsd_segments_use_integer_pixel_centres(scale):
    from perception.lines import lsd_segments

    for edge in (77, 101, 150):  # dark columns < edge, bright from edge on: boundary at edge-0.5
        image = np.zeros((200, 300), np.uint8)
        image[:, edge:] = 200
        segments = lsd_segments(image, scale=scale)
        assert len(segments) >= 1
        assert abs(segments[0, 0] - (edge - 0.5)) < 0.15
