"""A run that leaves part of the source beside the target's surfaces is not trusted.

In the right basin a source point either lies on a surface the target sampled too, or beyond
what the target covers (a partial overlap). In another basin part of the source lies near the
target's surfaces but beside them. `CovarianceDiagnostic.off_surface` is the share, among the
source's points within two of the overlap's radii of a target point, of those not within one
(`Registration.coverage`). Measured (issue 14, fourteenth round; docs/registration_notes.md, "Off
the surfaces"): right basins 0-0.086 where no other rule flags them (real rooms' halves, also
at 3 cm point noise, and parts; the real scan splits 0.033-0.041; KITTI at 0.1-0.5 m voxels
0.064-0.084); converged wrong basins of the rooms 0.073-0.46, those the direction gap missed
0.140-0.29 but two (0.073 and 0.094, still trusted) above the threshold, 0.11.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from test_registration_trust import assert_only_the_rule_flags, benchmark_start

from benchmarks.registration import D_FINAL, register_ours
from benchmarks.registration_indoor import labelled, voxel_map
from benchmarks.registration_real import DEFAULT_OCTOMAP, scan_setting
from estimation.errors import EstimationError
from estimation.registration import Registration, RegistrationConfig, pose_error
from estimation.registration.metrics import offset_about_centroid


@pytest.fixture(scope="module")
def office(centroid_room):
    return centroid_room("icl", 10)


def test_a_wrong_basin_with_a_small_direction_gap_is_not_trusted(office):
    # the test's office (every 10th frame), wide-offset start 8: converges 0.38 m off with
    # 49 % of the half on the map (so the midpoint, not the inside rule) and a direction gap
    # of 22.8 (below trust_gap); 31 % of its points near the map lie beside its surfaces
    points, labels, target = office
    source, T_gt, init, d0 = benchmark_start(points, labels, 8, offset="wide")
    result, _ = register_ours(source, target, init, (d0, D_FINAL))
    off, _ = register_ours(source, target, init, (d0, D_FINAL), trust_off_surface=math.inf)
    diagnostic = result.diagnostic
    assert result.converged and pose_error(result.T, T_gt).t_err_m > 0.1  # another basin
    assert diagnostic.symmetric and diagnostic.direction_gap < RegistrationConfig.trust_gap
    assert diagnostic.off_surface > 2.0 * RegistrationConfig.trust_off_surface
    # the off-surface share is what flags it: without the rule the same run was trusted
    assert_only_the_rule_flags(result, off)


@pytest.mark.usefixtures("strided_coarse_subset")
@pytest.mark.parametrize("seed", [0, 2])
def test_the_right_basin_leaves_no_point_just_off_the_map(office, seed):
    points, labels, target = office
    source, T_gt, init, d0 = benchmark_start(points, labels, seed, offset="wide")
    result, _ = register_ours(source, target, init, (d0, D_FINAL))
    assert pose_error(result.T, T_gt).t_err_m < 0.005
    assert result.diagnostic.off_surface < 0.01 and result.diagnostic.trusted


@pytest.fixture(scope="module")
def office_lattice(office):
    """The office's 3 cm voxel-centre map (as an octree stores it)."""
    points, labels, _ = office
    return labelled(*voxel_map(points, labels, "centres"))


@pytest.mark.parametrize("seed, wrong", [(8, True), (0, False)])
def test_the_share_flags_a_wrong_basin_on_a_lattice_map_too(office, office_lattice, seed,
                                                             wrong):
    # a lattice map has no overlap rule and no midpoint (no direction gap): before this
    # round only convergence and the correlation ratio could flag a run there. Wide start 8
    # converges 0.46 m off with a share of 0.32; start 0 in the right basin, 0.000
    points, labels, _ = office
    source, T_gt, init, d0 = benchmark_start(points, labels, seed, offset="wide")
    result, _ = register_ours(source, office_lattice, init, (d0, D_FINAL))
    off, _ = register_ours(source, office_lattice, init, (d0, D_FINAL),
                           trust_off_surface=math.inf)
    assert result.converged and result.diagnostic.quantisation_pitch is not None
    assert (pose_error(result.T, T_gt).t_err_m > 0.1) == wrong
    if wrong:
        assert result.diagnostic.off_surface > 2.0 * RegistrationConfig.trust_off_surface
        assert_only_the_rule_flags(result, off)
    else:
        assert result.diagnostic.off_surface < 0.01 and result.diagnostic.trusted


def test_a_real_partial_overlap_is_not_taken_for_another_basin():
    # two halves of OctoMap's real laser scan in overlapping sectors: a third of the source
    # lies beyond the target, but not beside its surfaces (measured 0.033-0.041 over splits)
    setting = scan_setting(DEFAULT_OCTOMAP, 100)
    metres, degrees, d0 = setting.offsets["small"]
    init = setting.T_gt @ offset_about_centroid(
        np.random.default_rng(100), setting.source.points.mean(axis=0), metres, degrees)
    result, _ = register_ours(setting.source, setting.target, init, (d0, setting.d_final))
    diagnostic = result.diagnostic
    assert pose_error(result.T, setting.T_gt).t_err_m < 0.005
    assert diagnostic.overlap[0] < 0.8  # a partial overlap
    assert diagnostic.off_surface < 0.5 * RegistrationConfig.trust_off_surface
    assert diagnostic.trusted


def test_the_share_counts_the_points_just_off_the_surfaces(rng):
    # a plane target; the source: 600 of its points, 150 of them again 1.5 radii above it
    # (beside the surface), 400 at 3 radii (beyond twice the radius: out of what the target
    # covers, not counted). The radius is the larger block edge: 0.1 m given, the source's
    # made negligible
    xy = rng.uniform(0.0, 4.0, (4000, 2))
    target = np.column_stack([xy, np.zeros(len(xy))])
    on = target[rng.choice(len(target), 600, replace=False)]
    source = np.vstack([on, on[:150] + [0.0, 0.0, 0.15], on[150:550] + [0.0, 0.0, 0.3]])
    config = RegistrationConfig(cluster_size=0.1, cluster_factor=1e-3)
    reg = Registration(source, target, config)
    covered, target_covered, share = reg.coverage(np.eye(4), 0.1)
    assert (covered, target_covered) == reg.overlap(np.eye(4), 0.1)
    assert covered == pytest.approx(600 / 1150)
    assert share == pytest.approx(150 / 750)
    assert math.isnan(reg.coverage(np.eye(4), 0.1, off_surface=False)[2])
    # no source point near the target: nothing to measure
    far = Registration(source + [0.0, 0.0, 10.0], target, config)
    assert math.isnan(far.coverage(np.eye(4), 0.1)[2])


@pytest.mark.parametrize("bad", [0.0, -0.1, "0.2", None])
def test_trust_off_surface_must_be_a_positive_number(bad):
    with pytest.raises(EstimationError, match="trust_off_surface"):
        RegistrationConfig(trust_off_surface=bad)
