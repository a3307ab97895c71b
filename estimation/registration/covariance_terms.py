"""The registration covariance's terms that need no :class:`~.gicp.Registration`: the
sandwich's pieces (cluster sums, the bread's limits, the inverse with unconstrained
directions) and the model-error information of voxel maps (a lattice's quantisation, tilted
planes, the in-plane phase, a centroid map's cell crossings and grid-phase field).

The derivations and the measurements behind each constant are in docs/registration_notes.md
("Model error: a voxel map's quantisation" and the sections after it).
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.special import ndtr  # (loaded with scipy.spatial already)

from .factors import grouped_sums, inplane_sums

# Variance given to directions the data leave unconstrained (rad^2 or m^2): large enough to
# show "unknown", finite so that the matrix stays a valid covariance for a PoseGraph.
UNCONSTRAINED_VARIANCE = 1e4


def plane_groups(normals: np.ndarray, points: np.ndarray, thickness: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Return (group index (M,), sign (M,)): correspondences grouped by lattice-aligned slab.

    Each normal's dominant axis a (the lattice axis nearest to it) and the point's
    coordinate along a, binned by ``thickness``, make the group: the points of one plane
    parallel to the lattice share it (its coordinate along a is constant), and so do
    coplanar patches, which share its quantisation offset too. (Binning the offset
    ``n . x`` instead splits planes: normal noise times the distance from the origin moves
    it by more than a voxel.) ``sign`` orients each normal so that its component along a
    is positive.
    """
    big = np.argmax(np.abs(normals), axis=1)
    sign = np.where(normals[np.arange(len(normals)), big] < 0.0, -1.0, 1.0)
    offset = points[np.arange(len(points)), big]
    key = np.c_[big, np.round(offset / thickness)].astype(np.int64)
    return _row_groups(key), sign


# A slab group is a plane tilted against the lattice (no common quantisation offset) when
# its matched lattice points' layer coordinate follows a planar trend (R^2 at least
# TILT_MIN_R2) across at least TILT_MIN_LAYERS layers, through contiguous layers (each kept
# layer holding LAYER_MIN_SHARE of the group): docs/registration_notes.md, "Tilted planes"
TILT_MIN_R2 = 0.3
TILT_MIN_LAYERS = 1.0
LAYER_MIN_SHARE = 0.05


def _layer_regression(group: np.ndarray, axis: np.ndarray, centres: np.ndarray):
    """Per slab group, the least-squares plane of the layer coordinate ``u`` (along each
    member's dominant lattice ``axis``) of the lattice points ``centres`` over their two
    in-plane coordinates ``p``. Return (count (G,), u and p centred on their group's mean
    (M,) and (M, 2), slope (G, 2), ok (G,) bool: a well-posed fit, r2 (G,))."""
    n_groups = int(group.max()) + 1
    rows = np.arange(len(group))
    u = centres[rows, axis]
    p = np.c_[centres[rows, (axis + 1) % 3], centres[rows, (axis + 2) % 3]]
    count = np.bincount(group, minlength=n_groups).astype(float)
    u = u - (np.bincount(group, u, n_groups) / count)[group]
    p = p - np.c_[np.bincount(group, p[:, 0], n_groups),
                  np.bincount(group, p[:, 1], n_groups)][group] / count[group, None]
    S_pp = np.empty((n_groups, 2, 2))
    for i in range(2):
        for j in range(i, 2):
            S_pp[:, i, j] = S_pp[:, j, i] = np.bincount(group, p[:, i] * p[:, j], n_groups)
    S_pu = np.c_[np.bincount(group, p[:, 0] * u, n_groups),
                 np.bincount(group, p[:, 1] * u, n_groups)]
    S_uu = np.bincount(group, u * u, n_groups)
    det = S_pp[:, 0, 0] * S_pp[:, 1, 1] - S_pp[:, 0, 1] ** 2
    ok = (count >= 6) & (S_uu > 0.0) & (det > 1e-12 * np.maximum(
        S_pp[:, 0, 0] * S_pp[:, 1, 1], 1e-300))
    det = np.where(ok, det, 1.0)
    slope = np.c_[S_pp[:, 1, 1] * S_pu[:, 0] - S_pp[:, 0, 1] * S_pu[:, 1],
                  S_pp[:, 0, 0] * S_pu[:, 1] - S_pp[:, 0, 1] * S_pu[:, 0]] / det[:, None]
    r2 = np.einsum("gi,gi->g", slope, S_pu) / np.where(S_uu > 0.0, S_uu, 1.0)
    return count, u, p, slope, ok, r2


def tilted_groups(group: np.ndarray, axis: np.ndarray, centres: np.ndarray, pitch: float,
                  regression: tuple | None = None) -> np.ndarray:
    """Return (G,) bool: which slab groups are planes tilted against the lattice.

    For each group (:func:`plane_groups`; ``axis`` the dominant lattice axis of each member)
    the layer coordinate ``u`` of its matched lattice points ``centres`` (voxel centres) is
    regressed on their two in-plane coordinates. A plane tilted against the lattice crosses
    layers steadily: ``u`` follows the fit (R^2 >= TILT_MIN_R2), the fitted values span at
    least TILT_MIN_LAYERS pitches, and the layers it occupies are contiguous (every layer
    between the lowest and the highest kept one holds at least LAYER_MIN_SHARE of the
    points). A plane parallel to the lattice has one or two layers without a trend (R^2
    near 0); two parallel planes a few voxels apart in one slab (a step, e.g. a screen in
    front of a wall) can give a trend too but leave an empty layer between them.
    ``regression``: :func:`_layer_regression` of these arguments, if already computed.
    """
    n_groups = int(group.max()) + 1
    count, u, p, slope, ok, r2 = regression or _layer_regression(group, axis, centres)
    fitted = np.einsum("mi,mi->m", p, slope[group])
    high = np.full(n_groups, -np.inf)
    low = np.full(n_groups, np.inf)
    np.maximum.at(high, group, fitted)
    np.minimum.at(low, group, fitted)
    layers = (high - low) / pitch
    # occupied layers: each point's layer index from the group's lowest point
    lowest = np.full(n_groups, np.inf)
    np.minimum.at(lowest, group, u)
    index = np.round((u - lowest[group]) / pitch).astype(np.int64)
    width = int(index.max()) + 1
    occupancy = np.bincount(group * width + index, minlength=n_groups * width).reshape(
        n_groups, width)
    kept = occupancy >= LAYER_MIN_SHARE * count[:, None]
    first = np.argmax(kept, axis=1)
    last = width - 1 - np.argmax(kept[:, ::-1], axis=1)
    contiguous = kept.any(axis=1) & (last - first + 1 == kept.sum(axis=1))
    return ok & (r2 >= TILT_MIN_R2) & (layers >= TILT_MIN_LAYERS) & contiguous


def quantisation_information(normals: np.ndarray, points: np.ndarray, sensitivity: np.ndarray,
                             pitch: float, centres: np.ndarray | None = None,
                             tilt: float | None = None, noise: float | None = None,
                             neighbourhood=None, inplane: tuple | None = None) -> np.ndarray:
    """Return the (6, 6) score covariance ``pitch^2 / 12 V^T V`` of a lattice's quantisation.

    Model: a surface stored as voxel centres (an octree map) is off the true surface by an
    offset along its normal, uniform over one voxel (variance pitch^2 / 12) and common to a
    whole plane (:func:`plane_groups`, slabs 3 pitches thick): a plane parallel to the
    lattice keeps one phase everywhere. Offsets of different planes are independent. They
    move the estimate by ``A^-1 sum_p v_p delta_p`` (v_p the plane's summed score
    sensitivity), so the pose covariance gains ``pitch^2 / 12 A^-1 V^T V A^-1``.

    With ``centres`` (the matched lattice points, e.g. voxel centres), slabs that are planes
    tilted against the lattice (:func:`tilted_groups`) get no common offset: such a plane
    crosses layers along itself, so its quantisation offset is a sawtooth along the plane.
    Without ``centres`` every slab counts (for tilted planes an upper bound: pessimistic;
    docs/registration_notes.md). With ``noise`` (m, not None) too, what of the sawtooth is common
    to the plane is added (:func:`sawtooth_information`): on a dense map it averages out
    along the plane, on a sparse one (a single laser scan) it does not.

    ``tilt`` (rad): a plane that stays within its layer is stored flat, whatever its tilt
    against the lattice up to about ``pitch / L`` (L its extent), so the map loses that
    tilt too. Each slab that gets an offset term also gets two independent tilts about its
    centroid, one per in-plane axis, of variance ``min(tilt^2, pitch^2 / (12 L^2))`` (L the
    extent of a uniform spread with the group's variance along that axis): the score sums
    gain ``sum_p sum_a var_pa t_pa t_pa^T``, ``t_pa = sum_{k in p} sign_k (x_ka - mean_a)
    sensitivity_k``. (ICL-NUIM's floor lies 2.1 mrad off its lattice plane and the 3 cm
    lattice map keeps it flat: docs/registration_notes.md, "Lattice maps of real rooms".)

    ``inplane`` (the pairs' Jacobians (M, 3, 6), whitening U^T (M, 3, 3) and weights (M,)):
    each slab's offsets along its in-plane lattice axes too (:func:`inplane_information`).
    """
    group, sign = plane_groups(normals, points, 3.0 * pitch)
    n_groups = int(group.max()) + 1
    V = np.zeros((n_groups, 6))
    np.add.at(V, group, sign[:, None] * sensitivity)
    axis = np.argmax(np.abs(normals), axis=1)
    aligned = np.ones(n_groups, dtype=bool)
    if centres is not None:
        regression = _layer_regression(group, axis, centres)
        aligned = ~tilted_groups(group, axis, centres, pitch, regression)
    V[~aligned] = 0.0
    info = pitch ** 2 / 12.0 * V.T @ V
    if centres is not None and noise is not None and not aligned.all():
        info = info + sawtooth_information(group, ~aligned[group], sign, axis, normals,
                                           sensitivity, centres, pitch, noise, neighbourhood,
                                           regression)
    if tilt:
        count = np.bincount(group, minlength=n_groups).astype(float)
        rows = np.arange(len(group))
        for step in (1, 2):  # the two in-plane axes of each group's dominant axis
            x = points[rows, (axis + step) % 3]
            dx = x - (np.bincount(group, x, n_groups) / count)[group]
            extent2 = 12.0 * np.bincount(group, dx * dx, n_groups) / count
            variance = np.where(aligned & (extent2 > 0.0), np.minimum(
                tilt ** 2, pitch ** 2 / (12.0 * np.maximum(extent2, 1e-300))), 0.0)
            T_a = np.zeros((n_groups, 6))
            np.add.at(T_a, group, (sign * dx)[:, None] * sensitivity)
            info = info + (T_a * variance[:, None]).T @ T_a
    if inplane is not None:
        info = info + inplane_information(group, axis, *inplane, pitch, aligned)
    return info


def inplane_information(group: np.ndarray, axis: np.ndarray, jacobians: np.ndarray,
                        whitening: np.ndarray, w: np.ndarray, pitch: float,
                        aligned: np.ndarray | None = None) -> np.ndarray:
    """Return the (6, 6) score covariance of the slabs' in-plane lattice phases.

    A plane stored on a lattice is a grid of voxel centres; the surface it was made from has
    no such grid. GICP's in-plane residuals (weighted epsilon against the normal's, but
    summed over a whole plane) hold the source to the grid's phase along the plane, so a
    direction that few surfaces face is held by where the grid happens to lie. Model: each
    slab ``group`` (dominant lattice ``axis`` of each pair) is off along each of its two
    in-plane axes b by an offset uniform over one voxel (variance pitch^2 / 12), common to
    the slab and independent between slabs and axes. A target offset along e_b changes a
    pair's score by ``w_k J_k^T U_k^T e_b``; the score sums gain
    ``pitch^2 / 12 sum_p sum_b t_pb t_pb^T``, t_pb that change summed over the slab.

    ``aligned`` (G,): the slabs parallel to the lattice (all: None). A plane tilted against
    it (:func:`tilted_groups`) is a staircase whose grid shifts along the plane from step to
    step, so it holds no one phase (a dense voxel map of planes tilted 0.3 rad, 30 trials:
    mean NEES 5.39 without the term, 5.23 with it, 1.73 with it on every slab).
    """
    # (G, 3, 6): per slab and axis b, the score's change per metre of target shift along e_b
    # summed over the slab's pairs whose plane contains b
    t = inplane_sums(jacobians, whitening, w, group, axis)
    if aligned is not None:
        t[~aligned] = 0.0
    t = t.reshape(-1, 6)
    return pitch ** 2 / 12.0 * t.T @ t


# Harmonics of the sawtooth term (its variance's tail beyond m is about 1 / (2 pi^2 m) of
# pitch^2, under 1 % of the uniform offset's at m = 64); fewer where the noise damped them
SAWTOOTH_HARMONICS = 64
# the 3x3x3 block of lattice cells a local surface mean averages (docs: surface_radius)
BLOCK_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1)
                          for k in (-1, 0, 1)], dtype=np.int64)
BLOCK_OFFSETS_CENTRE = np.all(BLOCK_OFFSETS == 0, axis=1)
# per lattice axis a: the block's offsets along the two in-plane axes (a + 1, a + 2), (27, 2)
BLOCK_INPLANE = np.stack([BLOCK_OFFSETS[:, [(a + 1) % 3, (a + 2) % 3]] for a in range(3)]
                         ).astype(float)


def sawtooth_information(group: np.ndarray, members: np.ndarray, sign: np.ndarray,
                         axis: np.ndarray, normals: np.ndarray, sensitivity: np.ndarray,
                         centres: np.ndarray, pitch: float, noise: float,
                         neighbourhood=None, regression: tuple | None = None) -> np.ndarray:
    """Return the (6, 6) score covariance of the quantisation of planes tilted against a
    lattice: the part of each plane's sawtooth that its matched points do not average out.

    A plane tilted against the lattice is stored as a staircase: at in-plane position x its
    voxel centre lies ``pitch (1/2 - frac(f(x) / pitch + phi))`` off the plane along the
    lattice axis, f the plane's layer coordinate there (each group's least-squares plane of
    its matched ``centres``, :func:`_layer_regression`) and phi the grid's unknown phase,
    uniform. Over phi, two such offsets at f_j and f_k covary as ``pitch^2 K(f_j - f_k)``,
    ``K(d) = sum_m cos(2 pi m d / pitch) / (2 pi^2 m^2)``, so the score sums gain

        pitch^2 sum_m (|Re Z_m|^2 + |Im Z_m|^2) / (2 pi^2 m^2) per plane,
        Z_m = sum_k c_m z_mk v_k,   v_k = sign_k |n_k,axis| sensitivity_k.

    ``z_mk = exp(2 pi i m f_k / pitch)``, averaged over the lattice points whose mean is the
    pair's matched position where ``neighbourhood`` gives them (the local surface means:
    ``neighbourhood(rows)`` returns a (R, 27) mask of the occupied cells of each pair's
    3x3x3 block, :data:`BLOCK_OFFSETS`; they average the staircase over the block).
    ``c_m = exp(-2 pi^2 m^2 noise^2 / pitch^2)``: the surface the map was made from is
    spread along the axis with standard deviation ``noise``, which dithers the staircase
    (the offset's mean over that noise is the sawtooth smoothed by it; the rest varies point
    by point, as point noise does). A plane sampled densely and evenly along its slope sums
    to about zero, one sampled sparsely or along a few scan lines does not. ``members``:
    the pairs of tilted planes; ``regression``: :func:`_layer_regression` of ``group``,
    ``axis`` and ``centres``, if already computed.
    """
    rows = np.flatnonzero(members)
    if len(rows) == 0:
        return np.zeros((6, 6))
    _, _, p, slope, _, _ = regression or _layer_regression(group, axis, centres)
    g, a = group[rows], axis[rows]
    # the pair's own layer coordinate on its plane, and the averaged block's phase offsets
    # (the block's cells lie whole pitches along the plane's two in-plane axes)
    f = np.einsum("rj,rj->r", p[rows], slope[g]) / pitch
    occupied = (np.ones((len(rows), 1), dtype=bool) if neighbourhood is None
                else neighbourhood(rows))
    if neighbourhood is None:
        d = np.zeros((len(rows), 1))
    else:  # (R, 27): each block cell's whole pitches along the plane's in-plane axes
        inplane = BLOCK_INPLANE[a]
        d = inplane[..., 0] * slope[g, 0, None] + inplane[..., 1] * slope[g, 1, None]
    weight = occupied / occupied.sum(axis=1, keepdims=True)
    v = (sign[rows] * np.abs(normals[rows, a]))[:, None] * sensitivity[rows]
    # per-plane sums by sorted group (np.add.at is slow)
    order = np.argsort(g, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(g[order]) != 0])
    base, step_k = np.exp(2j * np.pi * f), np.exp(2j * np.pi * d)
    z_own, z_block = np.ones(len(rows), complex), np.ones(d.shape, complex)
    info = np.zeros((6, 6))
    for m in range(1, SAWTOOTH_HARMONICS + 1):
        damping = np.exp(-2.0 * np.pi ** 2 * m ** 2 * noise ** 2 / pitch ** 2)
        if damping < 1e-4:
            break
        z_own = z_own * base
        z_block = z_block * step_k
        z = damping * z_own * (weight * z_block).sum(axis=1)
        Z = np.add.reduceat(z[order, None] * v[order], starts, axis=0)
        info += (Z.real.T @ Z.real + Z.imag.T @ Z.imag) / (2.0 * np.pi ** 2 * m ** 2)
    return pitch ** 2 * info


# Cell crossings of same-voxel matching (docs/registration_notes.md, "Cell crossings"): a cell
# holds a layer's points where it gets at least CROSSING_OCCUPIED of them (a 3 cm cell of a
# plane sampled every 5 mm gets about 36); fewer than MIN_CROSSING_PAIRS pairs within
# voxel_matching of a grid axis get no term
CROSSING_OCCUPIED = 0.01
MIN_CROSSING_PAIRS = 30


def systematic_covariance(sigma: float | tuple[float, float, float], R: np.ndarray,
                          rotation_sigma: float = 0.0) -> np.ndarray:
    """Return the (6, 6) covariance, [rotation, translation] in the body frame of ``T Exp(xi)``,
    of errors common to the whole source that its data cannot show:
    - an offset u ~ N(0, diag(sigma^2)) (target frame; one ``sigma`` = isotropic):
      ``T' = [R, t + u] = T Exp([0, R^T u])``, the translation block ``R^T diag(sigma^2) R``;
    - a rotation delta ~ N(0, rotation_sigma^2 I) about the source frame's origin:
      ``T' = T Exp([delta, 0])``, the rotation block ``rotation_sigma^2 I``.
    The two are independent: the cross blocks are zero."""
    variance = np.broadcast_to(np.square(np.asarray(sigma, dtype=float)), (3,))
    cov = np.zeros((6, 6))
    cov[:3, :3] = rotation_sigma ** 2 * np.eye(3)
    cov[3:, 3:] = (R.T * variance) @ R
    return cov


def grid_phase_information(G: np.ndarray, points: np.ndarray, origin: np.ndarray,
                           pitch: float) -> np.ndarray:
    """Return the (6, 6) score covariance of a displacement field along each grid axis a,
    ``u_a(x) = sqrt(2) cos(2 pi (x_a - origin_a) / pitch + phi_a)`` per unit amplitude, phi_a
    uniform and independent between axes, at the target ``points`` (M, 3) whose score
    sensitivities to a shift along x, y, z are ``G`` (M, 6, 3):
    ``sum_a Re Y_a Re Y_a^T + Im Y_a Im Y_a^T``, ``Y_a = sum_k G_k[:, a] exp(2 pi i x_ka / pitch)``.
    Points on a plane parallel to the grid share one phase and add coherently; on a tilted
    plane the phases turn and cancel."""
    angle = (2.0 * np.pi / pitch) * (points - origin)
    # one product over the pairs, (18, M) @ (M, 6), of which the (i, a) x (a) entries are
    # used (a raw half room's 350k pairs: 114 ms as two einsums)
    sums = G.reshape(len(G), 18).T @ np.hstack([np.cos(angle), np.sin(angle)])
    sums = sums.reshape(6, 3, 6)
    axes = np.arange(3)
    re, im = sums[:, axes, axes], sums[:, axes, axes + 3]  # (6, 3) each
    return re @ re.T + im @ im.T


def crossing_bias(sigma: float, tau: np.ndarray, pitch: float, phase: np.ndarray
                  ) -> np.ndarray:
    """Return the mean residual (m, along the grid axis) of same-voxel matching on a surface
    layer whose points are normal with standard deviation ``tau`` about a plane parallel to
    the grid, with cell centres at ``phase + k pitch`` (m; the plane at 0), when the source
    points carry normal noise ``sigma`` along the axis (``tau`` and ``phase`` broadcast).

    Each occupied cell (at least CROSSING_OCCUPIED of the layer) holds the centroid of its
    part of the layer; a source point is compared with the centroid of the cell it lands in,
    or, beyond the occupied cells, with the nearest occupied cell's. Without noise the
    residuals sum to zero; with it, the cells' shares of the source differ from their shares
    of the layer. The mean residual is ``-sum_k P(s in k) m_k`` (the layer's mean is 0).
    """
    tau = np.asarray(tau, dtype=float)[..., None]
    phase = np.asarray(phase, dtype=float)[..., None]
    reach = int(np.ceil(4.0 * (np.max(tau) + sigma) / pitch)) + 1
    k = np.arange(-reach, reach + 1)
    lo = (k - 0.5) * pitch + phase
    hi = lo + pitch
    layer = ndtr(hi / tau) - ndtr(lo / tau)
    pdf = np.exp(-0.5 * (lo / tau) ** 2) - np.exp(-0.5 * (hi / tau) ** 2)
    occupied = layer > CROSSING_OCCUPIED
    centroid = np.where(occupied, tau * pdf / np.sqrt(2.0 * np.pi) / np.where(
        occupied, layer, 1.0), 0.0)
    spread = np.sqrt(tau ** 2 + sigma ** 2)
    landed = ndtr(hi / spread) - ndtr(lo / spread)
    # a point landing beyond the occupied cells is compared with the nearest occupied one
    ks = np.broadcast_to(k, occupied.shape)
    first = np.where(occupied, ks, k[-1]).min(axis=-1, keepdims=True)
    last = np.where(occupied, ks, k[0]).max(axis=-1, keepdims=True)
    compared = np.take_along_axis(centroid, np.clip(ks, first, last) + reach, axis=-1)
    return -np.sum(landed * compared, axis=-1)


@functools.lru_cache(maxsize=256)
def _crossing_rms(sigma_over_pitch: float) -> float:
    tau = np.linspace(0.01, 0.5, 50)[:, None]
    phase = (np.arange(64) / 64.0)[None, :]
    bias = crossing_bias(sigma_over_pitch, tau, 1.0, phase)
    return float(np.sqrt(np.mean(bias ** 2, axis=1)).max())


def crossing_bias_rms(sigma: float, pitch: float) -> float:
    """Return the root-mean-square (over the grid's phase) of :func:`crossing_bias` for the
    worst layer thickness (tau from 0.01 to 0.5 pitch): the plane offset's scale (m) in the
    cell-crossing term. Measured: 0.14 / 0.26 / 0.56 / 1.15 mm at sigma 2 / 3 / 5 / 8 mm on
    a 3 cm grid (the worst tau 1-5 mm)."""
    if not sigma > 0.0:
        return 0.0
    return pitch * _crossing_rms(round(min(sigma / pitch, 2.0), 3))


def _row_groups(keys: np.ndarray) -> np.ndarray:
    """Return the group index (0..G-1) of each row of the (M, d) int64 ``keys``.

    The rows are packed into one int64 (mixed radix over their ranges) so that a 1-D
    ``np.unique`` does the grouping (``np.unique(axis=0)`` sorts a structured view, ~10x
    slower); falls back to it when the ranges do not fit in 63 bits.
    """
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if np.sum(np.log2(span.astype(float))) < 62:
        radix = np.concatenate([np.cumprod(span[::-1])[::-1][1:], [1]])
        packed = (keys - lo) @ radix
        _, group = np.unique(packed, return_inverse=True)
    else:
        _, group = np.unique(keys, axis=0, return_inverse=True)
    return group.reshape(-1)


def cluster_sums(points: np.ndarray, values: np.ndarray, size: float) -> np.ndarray:
    """Return ``values`` (M, d) summed over the cubic blocks of edge ``size`` holding ``points``."""
    if not size > 0:  # identical points: a neighbourhood radius of 0, one block
        return values.sum(axis=0, keepdims=True)
    keys = np.floor(points / size).astype(np.int64)
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if np.prod(span.astype(float)) <= 4 * len(keys) + 1024:
        # one pass over a table of the blocks' box: the same sums, row for row, as the
        # grouping and bincount below (a raw half-room's 435k pairs: 35 -> 8 ms a call)
        return grouped_sums(keys, lo, span, values)
    block = _row_groups(keys)
    n_blocks, d = int(block.max()) + 1, values.shape[1]
    # one bincount over (block, column) pairs: several times faster than np.add.at
    index = (block.reshape(-1, 1) * d + np.arange(d)).reshape(-1)
    return np.bincount(index, np.asarray(values, dtype=float).reshape(-1),
                       n_blocks * d).reshape(n_blocks, d)


def loewner_max(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Return the smallest covariance R with R >= P and R >= Q along the directions in which
    the two are simultaneously diagonal (the generalised eigenvectors of (Q, P)): each
    eigenvalue of P^-1 Q is raised to at least 1."""
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    W = V / np.sqrt(np.maximum(lam, 1e-300))  # W^T P W = I
    mu, U = np.linalg.eigh(W.T @ (0.5 * (Q + Q.T)) @ W)
    W_inv = np.linalg.inv(W)
    R = W_inv.T @ (U * np.maximum(mu, 1.0)) @ U.T @ W_inv
    return 0.5 * (R + R.T)


def bread_within(A: np.ndarray, D: np.ndarray, floor: float) -> np.ndarray:
    """Return ``D`` (symmetrised) with its eigenvalues relative to the positive definite
    ``A`` limited to [``floor``, 1] (``A`` itself if it is not positive definite): with
    ``A = L L^T`` and ``S = L^-1 D L^-T``, the result is ``L clip(S) L^T``. Limiting a
    result again to a higher floor gives what that floor gives from ``D``."""
    lam_A, V_A = np.linalg.eigh(A)
    if lam_A.min() <= 0.0:
        return A
    L = V_A * np.sqrt(lam_A)
    L_inv = (V_A / np.sqrt(lam_A)).T
    S = L_inv @ (0.5 * (D + D.T)) @ L_inv.T
    lam, U = np.linalg.eigh(0.5 * (S + S.T))
    return L @ (U * np.clip(lam, floor, 1.0)) @ U.T @ L.T


def covariance_from_information(H: np.ndarray, B: np.ndarray | None, scale: float,
                                H_normal: np.ndarray | None = None,
                                degeneracy_ratio: float = 1e-4) -> tuple[np.ndarray, int]:
    """Return (covariance, number of unconstrained directions) from the Gauss-Newton data.

    ``B is None`` gives the raw inverse Hessian ``H^-1``; otherwise the sandwich
    ``H^-1 B H^-1``. Rotations are scaled by the cloud radius ``scale`` before comparing
    eigenvalues, so metres and radians weigh alike. Directions whose (point-to-plane)
    information is below ``degeneracy_ratio`` of the largest get UNCONSTRAINED_VARIANCE.
    """
    S = np.diag([scale] * 3 + [1.0] * 3)
    test = H if H_normal is None else H_normal
    lam, vecs = np.linalg.eigh(np.linalg.inv(S) @ test @ np.linalg.inv(S))
    bad = lam < degeneracy_ratio * max(lam.max(), 1e-300)
    n_bad = int(bad.sum())
    Hs = np.linalg.inv(S) @ H @ np.linalg.inv(S)
    if n_bad:
        # project out the unconstrained subspace, invert in the rest, put a huge variance there
        good = vecs[:, ~bad]
        Hg = good.T @ Hs @ good
        Hinv_s = good @ np.linalg.inv(Hg) @ good.T
    else:
        Hinv_s = np.linalg.inv(Hs)
    Hinv = np.linalg.inv(S) @ Hinv_s @ np.linalg.inv(S)
    cov = Hinv if B is None else Hinv @ B @ Hinv
    if n_bad:
        null = np.linalg.inv(S) @ vecs[:, bad]
        null = null / np.linalg.norm(null, axis=0)
        cov = cov + UNCONSTRAINED_VARIANCE * null @ null.T
    cov = 0.5 * (cov + cov.T)
    # a floor keeps the matrix positive definite when a direction has no residual at all
    cov += np.eye(6) * 1e-12
    return cov, n_bad
