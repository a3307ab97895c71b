"""The quantisation of planes tilted against a lattice (:func:`sawtooth_information`).

A plane tilted against a voxel lattice is stored as a staircase: its voxel centres lie off
the plane by a sawtooth of the plane's layer coordinate, shifted by the grid's unknown
phase. Densely and evenly sampled along its slope the sawtooth averages out; sampled along
a few scan lines (a single laser scan's lattice map) it does not, and the registration
error it leaves was not in the covariance: OctoMap's scan.dat as a 3 cm lattice map, mean
NEES 44 over 8 half-scan starts, every run trusted (docs/registration_notes.md, "A single laser
scan's map"). These tests check the term against a Monte Carlo over the grid's phase, with
and without the surface noise that dithers the staircase.
"""
from __future__ import annotations

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.registration import RegistrationConfig
from estimation.registration.covariance_terms import (
    _layer_regression,
    quantisation_information,
    sawtooth_information,
)

PITCH = 0.03


def tilted_plane(rng, x: np.ndarray, y: np.ndarray, slope: float = 0.05, height: float = 0.0):
    """(normals, centres, sensitivity, layer coordinate f) of the plane z = height + slope x
    sampled
    at (x, y): the lattice centres of its staircase (phase 0) and random score
    sensitivities."""
    f = height + slope * x
    centres = np.c_[x, y, (np.floor(f / PITCH) + 0.5) * PITCH]
    normal = np.array([-slope, 0.0, 1.0]) / np.hypot(slope, 1.0)
    normals = np.tile(normal, (len(x), 1))
    sensitivity = rng.normal(size=(len(x), 6)) * np.r_[1, 1, 1, 2, 2, 2]
    return normals, centres, sensitivity, f


def monte_carlo(f, v, noise, phases=4000, draws=400):
    """Covariance over a uniform grid phase of sum_k v_k q_k, q_k the staircase's offset at
    layer coordinate f_k (averaged over the surface noise: its coherent part)."""
    from scipy.special import ndtri

    eps = noise * ndtri((np.arange(draws) + 0.5) / draws) if noise > 0 else np.zeros(1)
    S = []
    for phi in np.arange(phases) / phases:
        q = PITCH * (0.5 - np.mod((f[:, None] + eps[None, :]) / PITCH + phi, 1.0))
        S.append(v.T @ q.mean(axis=1))
    S = np.array(S)
    return S.T @ S / len(S)


@pytest.mark.parametrize("noise", [0.0, 0.005])
def test_sawtooth_term_is_the_phase_covariance_of_scan_lines(rng, noise):
    # three scan lines across a 4 m plane tilted 0.05 (2.9 deg): sparse along the slope
    x = np.concatenate([np.linspace(0.2, 0.6, 40), np.linspace(1.9, 2.1, 30),
                        np.linspace(3.3, 3.4, 30)])
    y = rng.uniform(0, 1, len(x))
    normals, centres, sensitivity, f = tilted_plane(rng, x, y)
    group = np.zeros(len(x), dtype=np.int64)
    sign, axis = np.ones(len(x)), np.full(len(x), 2)
    info = sawtooth_information(group, np.ones(len(x), bool), sign, axis, normals,
                                sensitivity, centres, PITCH, noise)
    v = np.abs(normals[:, 2])[:, None] * sensitivity
    # the term reads the plane's slope off its staircase (the true one: 0.05)
    _, _, p, slope, ok, _ = _layer_regression(group, axis, centres)
    assert ok[0] and slope[0, 0] == pytest.approx(0.05, abs=0.002) and abs(slope[0, 1]) < 0.01
    expected = monte_carlo(p @ slope[0], v, noise)
    assert np.trace(info) == pytest.approx(np.trace(expected), rel=0.03)
    np.testing.assert_allclose(info, expected, atol=0.03 * np.abs(expected).max())
    # against the true plane's sawtooth: the lines are metres apart, so a slope error of
    # 0.001 shifts their phases by a tenth of a layer (measured: 4 % low without noise, 39 %
    # with 5 mm, where only the first harmonics are left)
    assert 0.5 < np.trace(info) / np.trace(monte_carlo(f, v, noise)) < 1.5


def test_sawtooth_of_a_densely_sampled_plane_averages_out(rng):
    x, y = rng.uniform(0, 4, 4000), rng.uniform(0, 1, 4000)
    normals, centres, sensitivity, _ = tilted_plane(rng, x, y)
    sensitivity[:] = [0, 0, 0, 0, 0, 1.0]  # one common sensitivity: the plane's offset
    group, members = np.zeros(4000, dtype=np.int64), np.ones(4000, bool)
    args = (np.ones(4000), np.full(4000, 2), normals, sensitivity, centres, PITCH)
    dense = sawtooth_information(group, members, *args, 0.0)
    common = PITCH ** 2 / 12 * np.outer(normals[:, 2].sum() * sensitivity[0],
                                        normals[:, 2].sum() * sensitivity[0])
    assert dense[5, 5] < 0.01 * common[5, 5]
    # the same points on one scan line (x within 1 cm) keep most of a common offset
    line = np.abs(x - 2.0) < 0.005
    sub = (np.ones(line.sum()), np.full(line.sum(), 2), normals[line], sensitivity[line],
           centres[line], PITCH)
    one = sawtooth_information(group[line], members[line], *sub, 0.0)
    assert one[5, 5] > 0.9 * PITCH ** 2 / 12 * normals[line, 2].sum() ** 2
    # and surface noise dithers it: 1 cm against a 3 cm pitch leaves little
    dithered = sawtooth_information(group[line], members[line], *sub, 0.01)
    assert dithered[5, 5] < 0.05 * one[5, 5]


def test_tilted_planes_get_the_sawtooth_term_only_with_noise_given(rng):
    # z from 6.5 to 11 cm: two layers, both occupied, within one slab: a tilted plane
    x = np.linspace(0.0, 0.9, 60)
    y = rng.uniform(0, 1, len(x))
    normals, centres, sensitivity, _ = tilted_plane(rng, x, y, slope=0.05, height=0.065)
    without = quantisation_information(normals, centres, sensitivity, PITCH, centres)
    with_term = quantisation_information(normals, centres, sensitivity, PITCH, centres,
                                         noise=0.0)
    np.testing.assert_array_equal(without, np.zeros((6, 6)))  # a tilted plane: no offset
    assert np.trace(with_term) > 0
    # without the matched lattice points every slab is one common offset, as before
    np.testing.assert_array_equal(
        quantisation_information(normals, centres, sensitivity, PITCH, None, noise=0.005),
        quantisation_information(normals, centres, sensitivity, PITCH))


@pytest.mark.parametrize("bad", [-0.001, float("nan"), float("inf"), "5 mm", True])
def test_lattice_noise_must_be_a_non_negative_number(bad):
    with pytest.raises(EstimationError, match="lattice_noise"):
        RegistrationConfig(lattice_noise=bad)
    assert RegistrationConfig(lattice_noise=None).lattice_noise is None
    assert RegistrationConfig().lattice_noise == 0.005
