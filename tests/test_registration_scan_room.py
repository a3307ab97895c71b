"""Registration on a third real room: a single laser scan's 3 cm voxel maps.

OctoMap's ``scan.dat`` (one real 3-D laser scan of a corridor, no fusion) within 8 m of its
sensor, half of it against the whole scan's 3 cm map, 5 mm noise, 10 % wrong labels: issue
14's held-out protocol on a room of another kind than the two RGB-D rooms the map terms were
chosen on. A voxel of this map holds about 2 points (the RGB-D rooms' about 10), and its
surfaces are 2-6 mm thick (theirs 13-17 mm as 3 cm centroid maps) (docs/registration_notes.md,
"A single laser scan's map").

Centroid map: the point-noise covariance alone is about right here (mean NEES 4.4 over 20
starts). The map term sized in pitches alone (the tenth round's) over-covered it 3-6x (1.3 at
15k source points, 0.8 with the raw half); scaled by the map's local thickness it leaves it
nearly alone.

Lattice map (voxel centres, as an octree stores it): the scan's planes are tilted against
the lattice and sampled along a few scan lines, so their staircases do not average out;
without the sawtooth term (``lattice_noise=None``) mean NEES 44, every run trusted; with it
(5 mm) 13.6 (median 8.0). The rest is a known gap (strict xfail).
"""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.registration_indoor import half_room_trials, labelled, scan_room, voxel_map
from estimation.covariance import check_consistency, nees
from estimation.registration import RegistrationConfig, pose_error

N_TRIALS = 8


@pytest.fixture(scope="module")
def scan(shared_data):
    points, labels = scan_room(shared_data / "octomap" / "scan.dat.bz2")
    return points, labels, labelled(*voxel_map(points, labels, "centroids"))


@pytest.fixture(scope="module")
def lattice_nees(scan):
    """NEES of the same N_TRIALS half-scan starts against the scan's lattice map, with the
    default config (the sawtooth term of tilted planes, 5 mm) and without the term."""
    points, labels, _ = scan
    target = labelled(*voxel_map(points, labels, "centres"))
    out = {"default": [], "no sawtooth": []}
    options = {"default": {}, "no sawtooth": {"lattice_noise": None}}
    for key, result, T_gt in half_room_trials(points, labels, target, N_TRIALS, options,
                                              15000):
        assert result.converged, result.reason
        assert result.diagnostic.quantisation_pitch == pytest.approx(0.03)
        assert result.diagnostic.lattice_noise == options[key].get("lattice_noise", 0.005)
        out[key].append(nees(pose_error(result.T, T_gt).tangent[None],
                             result.covariance[None])[0])
    return {key: np.array(value) for key, value in out.items()}


def test_sawtooth_term_covers_most_of_the_lattice_gap(lattice_nees):
    # measured (8 starts): median NEES 8.0 with the term, 23.4 without; means 13.6 and 44
    with_term, without = lattice_nees["default"], lattice_nees["no sawtooth"]
    assert np.median(with_term) < 12.0 and np.median(without) > 16.0, lattice_nees
    assert np.mean(with_term) < 0.5 * np.mean(without)


@pytest.mark.xfail(strict=True, reason="issue 14, open: the lattice map of a single laser "
                   "scan, mean NEES 13.6 with the sawtooth term (44 without)")
def test_covariance_is_consistent_on_a_single_scan_lattice_map(lattice_nees):
    assert check_consistency(lattice_nees["default"], dof=6).passed


@pytest.fixture(scope="module")
def nees_by_option(scan):
    """NEES of the same N_TRIALS half-scan starts with the default config and with the map
    term off (``map_error=None``)."""
    out = {"default": [], "no map term": []}
    options = {"default": {}, "no map term": {"map_error": None}}
    for key, result, T_gt in half_room_trials(*scan, N_TRIALS, options, 15000):
        assert result.converged, result.reason
        assert pose_error(result.T, T_gt).t_err_m < 0.01
        if key == "default":
            # the map's grid is found, so the term is in and the run is trusted
            assert result.diagnostic.map_error == pytest.approx(
                RegistrationConfig().map_error * 0.03, rel=1e-3)
            assert result.diagnostic.trusted
        out[key].append(nees(pose_error(result.T, T_gt).tangent[None],
                             result.covariance[None])[0])
    return {key: np.array(value) for key, value in out.items()}


def test_scan_room_is_a_sparse_single_scan(scan):
    # what sets it apart from the RGB-D rooms: about 2 points per 3 cm voxel (they have 7-10)
    points, _, target = scan
    assert 60000 < len(points) < 75000
    assert 1.5 < len(points) / len(target.points) < 2.5


def test_point_noise_covariance_is_near_calibrated_on_a_single_scan(nees_by_option):
    # without the map term: mean NEES 4.04 over these 8 starts (4.38 over 20), the band
    # of a mean of 8 [3.84, 8.63]. A sandwich that lost its clustering or its re-matched
    # bread would be over-confident here; a covariance inflated 2x would fall below 3.
    assert 3.0 < np.mean(nees_by_option["no map term"]) < 8.63, nees_by_option


def test_thickness_scaled_map_term_leaves_a_thin_scan_map_near_the_point_noise(nees_by_option):
    # measured (8 starts): 3.76 with the term, 4.04 without; the term in pitches alone (the
    # tenth round's 0.03, before its scaling by the map's local thickness) gave 1.30
    with_term, without = (np.mean(nees_by_option[k]) for k in ("default", "no map term"))
    assert with_term > 0.8 * without, nees_by_option
    assert 3.0 < with_term < 8.63
