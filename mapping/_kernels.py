"""Numba kernels of the octree: keys, the exact ray DDA, batched node updates, queries, file codecs.

The tree lives in flat arrays (see :class:`mapping.octree.OcTree`):

* ``val[n]``   float32 log-odds of node ``n``;
* ``first[n]`` index of the first of the 8 contiguous child slots of ``n`` (``-1`` = no children);
* ``cmask[n]`` bit ``i`` set when child ``i`` exists (child ``i`` lives at ``first[n] + i``).

Node 0 is the root; child slots are handed out in blocks of 8 (block ``b`` = slots ``8b..8b+7``;
block 0 holds the root). Freed blocks go on a stack ``free_blocks`` and are reused.

Everything that decides a log-odds value or a key follows liboctomap 1.9.7's float/double mix
(../shared/formats/OCTOMAP.md sections 0, 4, 5) so that the maps are bit-identical.

Sections, in order: Morton codes, keys, the ray DDA, per-scan key sets (marking), tree updates,
traversal, whole-tree passes, queries, file payloads. They stay in one file although it is
long: the marking, the updates and the queries inline helpers of earlier sections, and
numba's on-disk cache (``cache=True``, the JIT path) is invalidated only by its own file's
timestamp. It does not see a change to a function defined in another file, nor to a global
(numba's developer notes, "Notes on Caching", cache limitations). Split into files, an edited
key helper would leave the JIT running the marking compiled with the old one. The compiled
module (estimation/aot.py) would be rebuilt, since it hashes this file.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

TREE_DEPTH = 16
KEY_OFFSET = 32768
FLT_MAX = np.float32(3.4028234663852886e38)
DBL_MAX = 1.7976931348623157e308

# --------------------------------------------------------------------------- Morton codes


@njit(cache=True, inline="always")
def _part1by2(v):
    v = np.uint64(v) & np.uint64(0xFFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x0C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x249249249249)
    return v


@njit(cache=True, inline="always")
def _compact1by2(v):
    v = v & np.uint64(0x249249249249)
    v = (v | (v >> np.uint64(2))) & np.uint64(0x0C30C30C30C3)
    v = (v | (v >> np.uint64(4))) & np.uint64(0x00F00F00F00F)
    v = (v | (v >> np.uint64(8))) & np.uint64(0x0000FF0000FF)
    v = (v | (v >> np.uint64(16))) & np.uint64(0xFFFF)
    return v


@njit(cache=True, inline="always")
def morton(kx, ky, kz):
    """Morton code whose 3-bit groups (MSB first) are OctoMap's child indices root -> leaf."""
    return _part1by2(kx) | (_part1by2(ky) << np.uint64(1)) | (_part1by2(kz) << np.uint64(2))


@njit(cache=True)
def keys_to_codes(keys):
    n = keys.shape[0]
    out = np.empty(n, np.uint64)
    for i in range(n):
        out[i] = morton(keys[i, 0], keys[i, 1], keys[i, 2])
    return out


@njit(cache=True)
def codes_to_keys(codes):
    n = codes.shape[0]
    out = np.empty((n, 3), np.uint16)
    for i in range(n):
        c = codes[i]
        out[i, 0] = _compact1by2(c)
        out[i, 1] = _compact1by2(c >> np.uint64(1))
        out[i, 2] = _compact1by2(c >> np.uint64(2))
    return out


# --------------------------------------------------------------------------- keys


@njit(cache=True, inline="always")
def _key_checked(c, rf):
    """coordToKeyChecked for one axis: key or -1 (double product, floor, range check)."""
    f = math.floor(rf * np.float64(c))
    if f >= -32768.0 and f < 32768.0:
        return np.int64(f) + 32768
    return -1


@njit(cache=True, inline="always")
def _ray_end(px, py, pz, ox, oy, oz, max_range):
    """The free ray of one point as insertPointCloud computes it (float32 like liboctomap).

    Returns (dx, dy, dz, norm, hit, ex, ey, ez): the direction (point - origin), its length,
    whether the end cell is a hit (False when the ray is cut at ``max_range``) and the end
    point (the point itself, or origin + max_range along the unit direction).
    """
    ddx = np.float32(px - ox)
    ddy = np.float32(py - oy)
    ddz = np.float32(pz - oz)
    nrm = math.sqrt(np.float64(np.float32(np.float32(ddx * ddx + ddy * ddy) + ddz * ddz)))
    if max_range >= 0.0 and not (nrm <= max_range):
        if nrm > 0:
            fl = np.float32(nrm)
            ndx = np.float32(ddx / fl)
            ndy = np.float32(ddy / fl)
            ndz = np.float32(ddz / fl)
        else:
            ndx = ddx
            ndy = ddy
            ndz = ddz
        mr = np.float32(max_range)
        return (ddx, ddy, ddz, nrm, False, np.float32(ox + np.float32(ndx * mr)),
                np.float32(oy + np.float32(ndy * mr)), np.float32(oz + np.float32(ndz * mr)))
    return ddx, ddy, ddz, nrm, True, px, py, pz


@njit(cache=True)
def coords_to_keys(points, rf):
    """(N,3) float32 points -> (N,3) int64 keys, -1 where coordToKeyChecked fails."""
    n = points.shape[0]
    out = np.empty((n, 3), np.int64)
    for i in range(n):
        for a in range(3):
            out[i, a] = _key_checked(points[i, a], rf)
    return out


@njit(cache=True, inline="always")
def _key_to_coord(k, res):
    return (np.float64(np.int64(k) - 32768) + 0.5) * res


# --------------------------------------------------------------------------- ray DDA


@njit(cache=True, inline="always")
def _ray_setup(ox, oy, oz, ex, ey, ez, k0, res):
    """Direction, length, step, tMax, tDelta exactly as computeRayKeys (float direction)."""
    dx = np.float32(ex - ox)
    dy = np.float32(ey - oy)
    dz = np.float32(ez - oz)
    nsq = np.float32(np.float32(dx * dx + dy * dy) + dz * dz)
    length = np.float32(math.sqrt(np.float64(nsq)))
    dx = np.float32(dx / length)
    dy = np.float32(dy / length)
    dz = np.float32(dz / length)
    d = (dx, dy, dz)
    o = (ox, oy, oz)
    step = np.zeros(3, np.int64)
    tmax = np.empty(3, np.float64)
    tdelta = np.empty(3, np.float64)
    for i in range(3):
        di = d[i]
        if di > 0:
            step[i] = 1
        elif di < 0:
            step[i] = -1
        if step[i] != 0:
            border = _key_to_coord(k0[i], res)
            border += np.float64(np.float32(step[i] * res * 0.5))
            tmax[i] = (border - np.float64(o[i])) / np.float64(di)
            tdelta[i] = res / np.float64(abs(di))
        else:
            tmax[i] = DBL_MAX
            tdelta[i] = DBL_MAX
    return length, step, tmax, tdelta


@njit(cache=True, inline="always")
def _axis_setup(di, k, o, res):
    """(step, tMax, tDelta) of one axis as computeRayKeys (float direction, float half-step)."""
    if di > 0:
        step = 1
    elif di < 0:
        step = -1
    else:
        return 0, DBL_MAX, DBL_MAX
    border = _key_to_coord(k, res) + np.float64(np.float32(step * res * 0.5))
    return step, (border - np.float64(o)) / np.float64(di), res / np.float64(abs(di))


@njit(cache=True, inline="always")
def _axis_border(k, o, res):
    """(border - origin) of :func:`_axis_setup` for a positive and a negative step."""
    c = _key_to_coord(k, res)
    bpos = (c + np.float64(np.float32(res * 0.5))) - np.float64(o)
    bneg = (c + np.float64(np.float32(-1 * res * 0.5))) - np.float64(o)
    return bpos, bneg


@njit(cache=True, inline="always")
def _axis_setup_pre(di, bpos, bneg, res):
    """:func:`_axis_setup` with the borders of the origin cell precomputed (same values)."""
    if di > 0:
        return 1, bpos / np.float64(di), res / np.float64(di)
    elif di < 0:
        return -1, bneg / np.float64(di), res / np.float64(-di)
    return 0, DBL_MAX, DBL_MAX


@njit(cache=True)
def ray_keys(ox, oy, oz, ex, ey, ez, res, out):
    """computeRayKeys: fill ``out`` (M,3) with the ray's keys; return count (-1 = out of bounds)."""
    rf = 1.0 / res
    k0 = np.empty(3, np.int64)
    k1 = np.empty(3, np.int64)
    o = (ox, oy, oz)
    e = (ex, ey, ez)
    for a in range(3):
        k0[a] = _key_checked(o[a], rf)
        k1[a] = _key_checked(e[a], rf)
        if k0[a] < 0 or k1[a] < 0:
            return -1
    if k0[0] == k1[0] and k0[1] == k1[1] and k0[2] == k1[2]:
        return 0
    length, step, tmax, tdelta = _ray_setup(ox, oy, oz, ex, ey, ez, k0, res)
    cur = k0.copy()
    n = 0
    if n < out.shape[0]:
        out[n, 0] = cur[0]
        out[n, 1] = cur[1]
        out[n, 2] = cur[2]
    n += 1
    while True:
        if tmax[0] < tmax[1]:
            dim = 0 if tmax[0] < tmax[2] else 2
        else:
            dim = 1 if tmax[1] < tmax[2] else 2
        cur[dim] = (cur[dim] + step[dim]) & 0xFFFF
        tmax[dim] += tdelta[dim]
        if cur[0] == k1[0] and cur[1] == k1[1] and cur[2] == k1[2]:
            break
        if min(tmax[0], min(tmax[1], tmax[2])) > length:
            break
        if n < out.shape[0]:
            out[n, 0] = cur[0]
            out[n, 1] = cur[1]
            out[n, 2] = cur[2]
        n += 1
        if n > 200000:  # liboctomap asserts at 100000 keys; never loop forever
            break
    return n


# --------------------------------------------------------------------------- per-scan key sets
# Free/occupied cells of a scan are marked in 8^3-cell bricks (a brick = a depth-13 node),
# found through an open-addressing hash on the brick's Morton code. Marking deduplicates for
# free, and the bricks are emitted in Morton order, so the tree update gets sorted codes.

_BRICK = 8
_EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, inline="always")
def _hash(c, mask):
    h = c * np.uint64(0x9E3779B97F4A7C15)
    return np.int64((h >> np.uint64(29)) & np.uint64(mask))


@njit(cache=True)
def _brick_find(tab_keys, tab_vals, bcode, mask):
    h = _hash(bcode, mask)
    while True:
        k = tab_keys[h]
        if k == bcode:
            return tab_vals[h], h
        if k == _EMPTY:
            return -1, h
        h = (h + 1) & mask


@njit(cache=True)
def _mark_rays(pts, ox, oy, oz, ok0, res, max_range, i0, tab_keys, tab_vals, pool, bcodes,
               nbr, counters):
    """Mark the free cells (1) and hit cells (2) of rays i0.. into bricks.

    ``nbr[6 * b + face]`` caches the brick next to brick ``b`` across ``face`` (2 * axis + 1 for
    the + side; -1 = not looked up yet): a ray changes brick every few steps, and rays of one
    scan cross the same brick faces again and again, so this replaces most hash look-ups.
    counters = [n_bricks, n_nonfinite, n_out_of_bounds, n_failed]. Returns the index of the
    ray that found no room for a new brick (the caller grows the arrays and calls again: marking
    is idempotent, so re-walking that ray is harmless), or the number of points when done.
    """
    rf = 1.0 / res
    n = pts.shape[0]
    cap = tab_keys.shape[0]
    mask = cap - 1
    pool_cap = bcodes.shape[0]
    nb = counters[0]
    k1 = np.empty(3, np.int64)
    # every ray starts in the origin's brick, and most end next to the last brick they walked:
    # remember both instead of hashing them again
    obx = ok0[0] >> 3
    oby = ok0[1] >> 3
    obz = ok0[2] >> 3
    o_idx = -1
    cbx = -1
    cby = -1
    cbz = -1
    c_idx = -1
    for i in range(i0, n):
        px = np.float32(pts[i, 0])
        py = np.float32(pts[i, 1])
        pz = np.float32(pts[i, 2])
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            counters[1] += 1
            continue
        # endpoint of the free ray, and whether the end cell is a hit
        ddx, ddy, ddz, nrm, hit, ex, ey, ez = _ray_end(px, py, pz, ox, oy, oz, max_range)
        k1[0] = _key_checked(ex, rf)
        k1[1] = _key_checked(ey, rf)
        k1[2] = _key_checked(ez, rf)
        end_ok = k1[0] >= 0 and k1[1] >= 0 and k1[2] >= 0
        ray_ok = end_ok and ok0[0] >= 0 and ok0[1] >= 0 and ok0[2] >= 0
        if ray_ok and not (ok0[0] == k1[0] and ok0[1] == k1[1] and ok0[2] == k1[2]):
            if hit:
                # the ray ends at the point: same differences and norm as computed above
                rdx = ddx
                rdy = ddy
                rdz = ddz
                length = np.float32(nrm)
            else:
                rdx = np.float32(ex - ox)
                rdy = np.float32(ey - oy)
                rdz = np.float32(ez - oz)
                nsq = np.float32(np.float32(rdx * rdx + rdy * rdy) + rdz * rdz)
                length = np.float32(math.sqrt(np.float64(nsq)))
            kx = ok0[0]
            ky = ok0[1]
            kz = ok0[2]
            sx, tx, dtx = _axis_setup(np.float32(rdx / length), kx, ox, res)
            sy, ty, dty = _axis_setup(np.float32(rdy / length), ky, oy, res)
            sz, tz, dtz = _axis_setup(np.float32(rdz / length), kz, oz, res)
            ex_k = k1[0]
            ey_k = k1[1]
            ez_k = k1[2]
            lend = np.float64(length)
            # brick-local coordinates; a step that leaves 0..7 on its axis changes brick
            need_brick = True
            face = -1
            base = 0
            lx = kx & 7
            ly = ky & 7
            lz = kz & 7
            while True:
                if need_brick:
                    bx = kx >> 3
                    by = ky >> 3
                    bz = kz >> 3
                    idx = -1
                    if face >= 0:
                        idx = nbr[c_idx * 6 + face]
                    if idx >= 0:
                        pass
                    elif o_idx >= 0 and bx == obx and by == oby and bz == obz:
                        idx = o_idx
                    else:
                        bc = morton(bx, by, bz)
                        idx, h = _brick_find(tab_keys, tab_vals, bc, mask)
                        if idx < 0:
                            if nb >= pool_cap or (nb + 1) * 2 > cap:
                                counters[0] = nb
                                return i
                            idx = nb
                            bcodes[nb] = bc
                            nb += 1
                            tab_keys[h] = bc
                            tab_vals[h] = idx
                        if bx == obx and by == oby and bz == obz:
                            o_idx = idx
                    if face >= 0:
                        nbr[c_idx * 6 + face] = idx
                        nbr[idx * 6 + (face ^ 1)] = c_idx
                    cbx = bx
                    cby = by
                    cbz = bz
                    c_idx = idx
                    base = idx * 512
                    need_brick = False
                # bit 0 = free; the occupied bit 2 is kept (occupied wins)
                li = base + lx + (ly << 3) + (lz << 6)
                pool[li] |= 1
                # advance (the first cell is the origin cell, already in the ray)
                if tx < ty:
                    if tx < tz:
                        kx = (kx + sx) & 0xFFFF
                        tx += dtx
                        lx += sx
                        if lx & ~7:
                            lx &= 7
                            need_brick = True
                            face = 1 if sx > 0 else 0
                    else:
                        kz = (kz + sz) & 0xFFFF
                        tz += dtz
                        lz += sz
                        if lz & ~7:
                            lz &= 7
                            need_brick = True
                            face = 5 if sz > 0 else 4
                else:
                    if ty < tz:
                        ky = (ky + sy) & 0xFFFF
                        ty += dty
                        ly += sy
                        if ly & ~7:
                            ly &= 7
                            need_brick = True
                            face = 3 if sy > 0 else 2
                    else:
                        kz = (kz + sz) & 0xFFFF
                        tz += dtz
                        lz += sz
                        if lz & ~7:
                            lz &= 7
                            need_brick = True
                            face = 5 if sz > 0 else 4
                if kx == ex_k and ky == ey_k and kz == ez_k:
                    break
                if tx > lend and ty > lend and tz > lend:
                    break
        if hit and end_ok:
            # occupied endpoint: state 2 wins over free
            bx = k1[0] >> 3
            by = k1[1] >> 3
            bz = k1[2] >> 3
            if c_idx >= 0 and bx == cbx and by == cby and bz == cbz:
                idx = c_idx
            elif o_idx >= 0 and bx == obx and by == oby and bz == obz:
                idx = o_idx
            else:
                bc = morton(bx, by, bz)
                idx, h = _brick_find(tab_keys, tab_vals, bc, mask)
            if idx < 0:
                if nb >= pool_cap or (nb + 1) * 2 > cap:
                    counters[0] = nb
                    return i
                idx = nb
                bcodes[nb] = bc
                nb += 1
                tab_keys[h] = bc
                tab_vals[h] = idx
            pool[idx * 512 + (k1[0] & 7) + ((k1[1] & 7) << 3) + ((k1[2] & 7) << 6)] |= 2
        if hit and not end_ok:
            counters[2] += 1
        if not ray_ok:
            counters[3] += 1
    counters[0] = nb
    return n


@njit(cache=True)
def _mark_rays_grid(pts, ox, oy, oz, ok0, res, max_range, i0, pool, bcodes, counters, gdir, glo,
                    ghi, gdx, gdxy, slow):
    """Mark the rays i0.. that lie in the brick grid (fast path); list the others in ``slow``.

    The grid directory ``gdir`` maps each 8^3 brick of the key box [glo, glo + 8 * dims) to its
    brick index (-1 = none yet), so a step finds its cell without a per-step brick test. A ray
    is walked here when its origin and end keys are in [glo + 2, ghi - 2] (ghi <= 65535): a
    computeRayKeys walk never leaves the key box of its two end cells by more than one cell,
    so it stays in the grid and no key wraps around. The walk replays computeRayKeys exactly:
    the next step is on the axis of smallest tMax (ties to z, then y), the first step is always
    taken, and a cell is on the ray when the ray leaves it no later than its length (the
    loop's tMax > length test) and it is not the end cell, which can only be reached after
    |dkx| + |dky| + |dkz| steps (each axis moves one way). New bricks get the next index and
    their code in ``bcodes`` (the caller puts them in the hash table afterwards).
    counters = [n_bricks, n_nonfinite, n_out_of_bounds, n_failed, n_slow]. Returns the index
    of the ray that found no room for a new brick (the caller grows the arrays and calls
    again: marking is idempotent), or n.
    """
    rf = 1.0 / res
    n = pts.shape[0]
    pool_cap = bcodes.shape[0]
    nb = counters[0]
    glx = glo[0]
    gly = glo[1]
    glz = glo[2]
    for i in range(i0, n):
        px = np.float32(pts[i, 0])
        py = np.float32(pts[i, 1])
        pz = np.float32(pts[i, 2])
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            counters[1] += 1
            continue
        ddx, ddy, ddz, nrm, hit, ex, ey, ez = _ray_end(px, py, pz, ox, oy, oz, max_range)
        ex_k = _key_checked(ex, rf)
        ey_k = _key_checked(ey, rf)
        ez_k = _key_checked(ez, rf)
        if not (ex_k >= glo[0] + 2 and ex_k <= ghi[0] - 2 and ey_k >= glo[1] + 2
                and ey_k <= ghi[1] - 2 and ez_k >= glo[2] + 2 and ez_k <= ghi[2] - 2):
            slow[counters[4]] = i
            counters[4] += 1
            continue
        if not (ok0[0] == ex_k and ok0[1] == ey_k and ok0[2] == ez_k):
            if hit:
                rdx = ddx
                rdy = ddy
                rdz = ddz
                length = np.float32(nrm)
            else:
                rdx = np.float32(ex - ox)
                rdy = np.float32(ey - oy)
                rdz = np.float32(ez - oz)
                nsq = np.float32(np.float32(rdx * rdx + rdy * rdy) + rdz * rdz)
                length = np.float32(math.sqrt(np.float64(nsq)))
            kx = ok0[0]
            ky = ok0[1]
            kz = ok0[2]
            sx, tx, dtx = _axis_setup(np.float32(rdx / length), kx, ox, res)
            sy, ty, dty = _axis_setup(np.float32(rdy / length), ky, oy, res)
            sz, tz, dtz = _axis_setup(np.float32(rdz / length), kz, oz, res)
            lend = np.float64(length)
            rem = abs(ex_k - kx) + abs(ey_k - ky) + abs(ez_k - kz)
            lim = DBL_MAX  # the first step is taken whatever its tMax
            # keys relative to the grid corner (a multiple of 8: brick-local bits unchanged)
            kx -= glx
            ky -= gly
            kz -= glz
            ex_r = ex_k - glx
            ey_r = ey_k - gly
            ez_r = ez_k - glz
            while True:
                # mark the current cell (bit 0 = free; an occupied bit 1 is kept), then step.
                # The mark is repeated in each of the four axis branches on purpose: choosing
                # the axis first and marking once measured 5-10 % slower (CPU, one thread,
                # scan.dat through this path at 0.1 and 0.05 m), and the find-or-add of the
                # brick as an inline="always" helper returning (brick, count) 5x slower
                # (scan.dat, 0.1 m, max range -1: 0.45 vs 2.3 Mpts/s, one thread)
                if tx < ty:
                    if tx < tz:
                        if tx > lim:
                            break
                        bi = (kx >> 3) + (ky >> 3) * gdx + (kz >> 3) * gdxy
                        b = gdir[bi]
                        if b < 0:
                            if nb >= pool_cap:
                                counters[0] = nb
                                return i
                            b = nb
                            bcodes[nb] = morton((kx + glx) >> 3, (ky + gly) >> 3,
                                                (kz + glz) >> 3)
                            gdir[bi] = b
                            nb += 1
                        pool[(b << 9) + (kx & 7) + ((ky & 7) << 3) + ((kz & 7) << 6)] |= 1
                        kx += sx
                        tx += dtx
                    else:
                        if tz > lim:
                            break
                        bi = (kx >> 3) + (ky >> 3) * gdx + (kz >> 3) * gdxy
                        b = gdir[bi]
                        if b < 0:
                            if nb >= pool_cap:
                                counters[0] = nb
                                return i
                            b = nb
                            bcodes[nb] = morton((kx + glx) >> 3, (ky + gly) >> 3,
                                                (kz + glz) >> 3)
                            gdir[bi] = b
                            nb += 1
                        pool[(b << 9) + (kx & 7) + ((ky & 7) << 3) + ((kz & 7) << 6)] |= 1
                        kz += sz
                        tz += dtz
                else:
                    if ty < tz:
                        if ty > lim:
                            break
                        bi = (kx >> 3) + (ky >> 3) * gdx + (kz >> 3) * gdxy
                        b = gdir[bi]
                        if b < 0:
                            if nb >= pool_cap:
                                counters[0] = nb
                                return i
                            b = nb
                            bcodes[nb] = morton((kx + glx) >> 3, (ky + gly) >> 3,
                                                (kz + glz) >> 3)
                            gdir[bi] = b
                            nb += 1
                        pool[(b << 9) + (kx & 7) + ((ky & 7) << 3) + ((kz & 7) << 6)] |= 1
                        ky += sy
                        ty += dty
                    else:
                        if tz > lim:
                            break
                        bi = (kx >> 3) + (ky >> 3) * gdx + (kz >> 3) * gdxy
                        b = gdir[bi]
                        if b < 0:
                            if nb >= pool_cap:
                                counters[0] = nb
                                return i
                            b = nb
                            bcodes[nb] = morton((kx + glx) >> 3, (ky + gly) >> 3,
                                                (kz + glz) >> 3)
                            gdir[bi] = b
                            nb += 1
                        pool[(b << 9) + (kx & 7) + ((ky & 7) << 3) + ((kz & 7) << 6)] |= 1
                        kz += sz
                        tz += dtz
                lim = lend
                rem -= 1
                if rem == 0 and kx == ex_r and ky == ey_r and kz == ez_r:
                    break
        if hit:
            bi = ((ex_k - glx) >> 3) + ((ey_k - gly) >> 3) * gdx + ((ez_k - glz) >> 3) * gdxy
            b = gdir[bi]
            if b < 0:
                if nb >= pool_cap:
                    counters[0] = nb
                    return i
                b = nb
                bcodes[nb] = morton(ex_k >> 3, ey_k >> 3, ez_k >> 3)
                gdir[bi] = b
                nb += 1
            pool[(b << 9) + (ex_k & 7) + ((ey_k & 7) << 3) + ((ez_k & 7) << 6)] |= 2
    counters[0] = nb
    return n


@njit(cache=True, nogil=True)
def transform_points_f32(points, q, t):
    """graph2tree's point transform: ``q * (0, p) * conj(q) + t`` in float32, each product
    and sum rounded in liboctomap's term order (``Quaternion::operator*``), per point.

    ``points`` (N, 3) float32, ``q`` (4,) float32 (w, x, y, z), ``t`` (3,) float32. The same
    arithmetic as :func:`mapping.fusion._rotate` on arrays (the reference), without its
    temporaries.
    """
    n = points.shape[0]
    out = np.empty((n, 3), np.float32)
    au, ax, ay, az = q[0], q[1], q[2], q[3]
    iu, ix, iy, iz = q[0], -q[1], -q[2], -q[3]
    zero = np.float32(0.0)
    for i in range(n):
        bx, by, bz = points[i, 0], points[i, 1], points[i, 2]
        # qv = q * (0, p)
        u = (((au * zero) - (ax * bx)) - (ay * by)) - (az * bz)
        x = (((ay * bz) - (by * az)) + (au * bx)) + (zero * ax)
        y = (((az * bx) - (bz * ax)) + (au * by)) + (zero * ay)
        z = (((ax * by) - (bx * ay)) + (au * bz)) + (zero * az)
        # r = qv * conj(q); only the vector part
        rx = (((y * iz) - (iy * z)) + (u * ix)) + (iu * x)
        ry = (((z * ix) - (iz * x)) + (u * iy)) + (iu * y)
        rz = (((x * iy) - (ix * y)) + (u * iz)) + (iu * z)
        out[i, 0] = rx + t[0]
        out[i, 1] = ry + t[1]
        out[i, 2] = rz + t[2]
    return out


# rays per block of _mark_rays_dense (set-ups, then walks); its scratch stays in L1
_DENSE_BLOCK = 256

# direction buckets of sort_rays: per cube face, _DIR_BINS x 4 _DIR_BINS cells
_DIR_BINS = 32


@njit(cache=True, nogil=True)
def sort_rays(points, origin):
    """The points reordered by the direction of their ray from ``origin`` (a cube map).

    The DDA's step pattern depends on the direction; marking alike rays one after the other
    lets the branch predictor and the caches follow (the 0.1 m corridor marks about 1.6x
    faster than unsorted, and 5-10% faster than sorted by endpoint Morton code). The key is
    the cube face of the dominant axis, then the two other components over it in 32 x 128
    bins, the second running back and forth (a snake, so that neighbouring buckets stay
    alike). The key sets are a union over the rays, so any order gives the same result. One
    counting-sort pass.
    """
    n = points.shape[0]
    out = np.empty_like(points)
    nbu = _DIR_BINS
    nbv = 4 * _DIR_BINS
    n_buckets = 6 * nbu * nbv
    # float32 and one reciprocal per ray: the key only groups alike directions, it need not
    # be exact (any order gives the same key sets)
    ox = np.float32(origin[0])
    oy = np.float32(origin[1])
    oz = np.float32(origin[2])
    hu = np.float32(0.5 * nbu)
    hv = np.float32(0.5 * nbv)
    one = np.float32(1.0)
    key = np.empty(n, np.int32)
    start = np.zeros(n_buckets + 1, np.int64)
    for i in range(n):
        dx = np.float32(points[i, 0]) - ox
        dy = np.float32(points[i, 1]) - oy
        dz = np.float32(points[i, 2]) - oz
        ax = abs(dx)
        ay = abs(dy)
        az = abs(dz)
        # dominant axis by selects, not branches (random directions would mispredict them)
        xdom = (ax >= ay) & (ax >= az)
        ydom = (not xdom) & (ay >= az)
        xy = xdom | ydom
        dom = ax if xdom else (ay if ydom else az)
        u = dy if xdom else dx
        v = dz if xy else dy
        dsel = dx if xdom else (dy if ydom else dz)
        face = (0 if xdom else (2 if ydom else 4)) + (1 if dsel > 0 else 0)
        kk = 0
        if dom > 0 and dom < np.float32(3e38):  # not the origin itself, NaN or inf
            r = one / dom
            ub = min(np.int32((u * r + one) * hu), nbu - 1)
            vb = min(np.int32((v * r + one) * hv), nbv - 1)
            if ub & 1:
                vb = nbv - 1 - vb
            kk = (face * nbu + max(ub, 0)) * nbv + max(vb, 0)
        key[i] = kk
        start[kk + 1] += 1
    for b in range(n_buckets):
        start[b + 1] += start[b]
    for i in range(n):
        kk = key[i]
        j = start[kk]
        start[kk] = j + 1
        out[j, 0] = points[i, 0]
        out[j, 1] = points[i, 1]
        out[j, 2] = points[i, 2]
    return out


@njit(cache=True, nogil=True)
def discretize_points(points, res):
    """The unique voxel centres of a scan's finite, in-map endpoints (insertPointCloud's
    ``discretize``: one ray per endpoint voxel; a set, so the order does not matter).

    Returns (centres (M, 3) float32, n_nonfinite, n_out_of_bounds).
    """
    rf = 1.0 / res
    n = points.shape[0]
    codes = np.empty(n, np.uint64)
    m = 0
    n_nonfinite = 0
    n_oob = 0
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            n_nonfinite += 1
            continue
        kx = _key_checked(x, rf)
        ky = _key_checked(y, rf)
        kz = _key_checked(z, rf)
        if kx < 0 or ky < 0 or kz < 0:
            n_oob += 1
            continue
        codes[m] = morton(kx, ky, kz)
        m += 1
    u = np.unique(codes[:m])
    ks = codes_to_keys(u)
    centres = np.empty((u.shape[0], 3), np.float32)
    for i in range(u.shape[0]):
        for a in range(3):
            centres[i, a] = np.float32(_key_to_coord(ks[i, a], res))
    return centres, n_nonfinite, n_oob


@njit(cache=True)
def _mark_rays_dense(pts, ox, oy, oz, ok0, res, max_range, grid, glo, ghi, row, slab, counters,
                     slow, hits):
    """Mark the rays that lie in a dense cell grid (fast path); list the others in ``slow``.

    ``grid`` holds one byte per cell of the key box [glo, glo + 8 * dims) (x fastest, ``row``
    and ``slab`` cells per y and z step): 1 for a free cell, written by plain stores (a step
    moves the cell address by a constant), then 2 for a hit cell, written after all rays (the
    occupied state wins). The rays and the walk are those of :func:`_mark_rays_grid` (same
    exact computeRayKeys replay), except that the end cell test compares addresses at every
    step: they are unique inside the grid. ``hits`` is scratch for the hit cells' addresses.

    The rays go in blocks of :data:`_DENSE_BLOCK`: first every ray's set-up (end point, keys,
    the divisions of tMax and tDelta), then every ray's walk. The same operations on the same
    values, reordered: the set-ups of a block no longer wait behind the mispredicted exit of
    the previous walk (the corridor's marking 7-8 % faster).
    """
    rf = 1.0 / res
    n = pts.shape[0]
    n_hits = 0
    glx = glo[0]
    gly = glo[1]
    glz = glo[2]
    # every ray starts in the origin's cell: its borders are the same for all rays
    bxp, bxn = _axis_border(ok0[0], ox, res)
    byp, byn = _axis_border(ok0[1], oy, res)
    bzp, bzn = _axis_border(ok0[2], oz, res)
    o_addr = (ok0[0] - glx) + (ok0[1] - gly) * row + (ok0[2] - glz) * slab
    # per ray of a block: 0 nothing to mark, 1 the end cell only, 2 a walk (and the end cell)
    todo = np.empty(_DENSE_BLOCK, np.int64)
    end_addr = np.empty(_DENSE_BLOCK, np.int64)
    is_hit = np.empty(_DENSE_BLOCK, np.bool_)
    tm = np.empty((_DENSE_BLOCK, 6), np.float64)  # tMax x y z, tDelta x y z
    steps = np.empty((_DENSE_BLOCK, 3), np.int64)
    lengths = np.empty(_DENSE_BLOCK, np.float64)
    for b0 in range(0, n, _DENSE_BLOCK):
        b1 = min(b0 + _DENSE_BLOCK, n)
        for i in range(b0, b1):
            j = i - b0
            todo[j] = 0
            px = np.float32(pts[i, 0])
            py = np.float32(pts[i, 1])
            pz = np.float32(pts[i, 2])
            if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
                counters[1] += 1
                continue
            ddx, ddy, ddz, nrm, hit, ex, ey, ez = _ray_end(px, py, pz, ox, oy, oz, max_range)
            ex_k = _key_checked(ex, rf)
            ey_k = _key_checked(ey, rf)
            ez_k = _key_checked(ez, rf)
            if not (ex_k >= glx + 2 and ex_k <= ghi[0] - 2 and ey_k >= gly + 2
                    and ey_k <= ghi[1] - 2 and ez_k >= glz + 2 and ez_k <= ghi[2] - 2):
                slow[counters[4]] = i
                counters[4] += 1
                continue
            eaddr = (ex_k - glx) + (ey_k - gly) * row + (ez_k - glz) * slab
            end_addr[j] = eaddr
            is_hit[j] = hit
            if eaddr == o_addr:  # the end cell is the origin's: no free cell
                todo[j] = 1
                continue
            todo[j] = 2
            if hit:
                rdx = ddx
                rdy = ddy
                rdz = ddz
                length = np.float32(nrm)
            else:
                rdx = np.float32(ex - ox)
                rdy = np.float32(ey - oy)
                rdz = np.float32(ez - oz)
                nsq = np.float32(np.float32(rdx * rdx + rdy * rdy) + rdz * rdz)
                length = np.float32(math.sqrt(np.float64(nsq)))
            sx, tx, dtx = _axis_setup_pre(np.float32(rdx / length), bxp, bxn, res)
            sy, ty, dty = _axis_setup_pre(np.float32(rdy / length), byp, byn, res)
            sz, tz, dtz = _axis_setup_pre(np.float32(rdz / length), bzp, bzn, res)
            tm[j, 0] = tx
            tm[j, 1] = ty
            tm[j, 2] = tz
            tm[j, 3] = dtx
            tm[j, 4] = dty
            tm[j, 5] = dtz
            steps[j, 0] = sx
            steps[j, 1] = sy * row
            steps[j, 2] = sz * slab
            lengths[j] = np.float64(length)
        for j in range(b1 - b0):
            if todo[j] == 0:
                continue
            if todo[j] == 2:
                tx = tm[j, 0]
                ty = tm[j, 1]
                tz = tm[j, 2]
                dtx = tm[j, 3]
                dty = tm[j, 4]
                dtz = tm[j, 5]
                lend = lengths[j]
                lim = DBL_MAX  # the first step is taken whatever its tMax
                # unsigned addresses (steps wrap modulo 2^64): no negative-index fix needed
                addr = np.uint64(o_addr)
                ueaddr = np.uint64(end_addr[j])
                ix = np.uint64(steps[j, 0])
                iy = np.uint64(steps[j, 1])
                iz = np.uint64(steps[j, 2])
                while True:
                    if tx < ty:
                        if tx < tz:
                            if tx > lim:
                                break
                            grid[addr] = 1
                            addr += ix
                            tx += dtx
                        else:
                            if tz > lim:
                                break
                            grid[addr] = 1
                            addr += iz
                            tz += dtz
                    else:
                        if ty < tz:
                            if ty > lim:
                                break
                            grid[addr] = 1
                            addr += iy
                            ty += dty
                        else:
                            if tz > lim:
                                break
                            grid[addr] = 1
                            addr += iz
                            tz += dtz
                    lim = lend
                    if addr == ueaddr:
                        break
            if is_hit[j]:
                hits[n_hits] = end_addr[j]
                n_hits += 1
    for j in range(n_hits):
        grid[hits[j]] = 2


@njit(cache=True)
def _dense_to_bricks(grid, glo, dims, tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap):
    """Move the marks of a dense grid into bricks (and clear the grid for its next use).

    Returns (tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap), grown as needed.
    """
    row = 8 * dims[0]
    slab = row * 8 * dims[1]
    # 8 cells of a brick row are one aligned uint64 (glo and row are multiples of 8)
    g64 = grid.view(np.uint64)
    row64 = row >> 3
    slab64 = slab >> 3
    n_bricks = dims[0] * dims[1] * dims[2]
    used = np.zeros(n_bricks, np.bool_)
    n_used = 0
    for bz in range(dims[2]):
        for by in range(dims[1]):
            for bx in range(dims[0]):
                w0 = bx + 8 * by * row64 + 8 * bz * slab64
                anyb = np.uint64(0)
                for z in range(8):
                    for y in range(8):
                        anyb |= g64[w0 + y * row64 + z * slab64]
                if anyb != 0:
                    used[bx + dims[0] * (by + dims[1] * bz)] = True
                    n_used += 1
    need = nb + n_used
    if need > pool_cap:
        while need > pool_cap:
            pool_cap *= 2
        npool = np.zeros(pool_cap * 512, np.uint8)
        npool[: nb * 512] = pool[: nb * 512]
        pool = npool
        nbc = np.empty(pool_cap, np.uint64)
        nbc[:nb] = bcodes[:nb]
        bcodes = nbc
    if (need + 1) * 2 > cap:
        while (need + 1) * 2 > cap:
            cap *= 4
        mask = cap - 1
        tab_keys = np.full(cap, _EMPTY, np.uint64)
        tab_vals = np.empty(cap, np.int64)
        for j in range(nb):
            hh = _hash(bcodes[j], mask)
            while tab_keys[hh] != _EMPTY:
                hh = (hh + 1) & mask
            tab_keys[hh] = bcodes[j]
            tab_vals[hh] = j
    mask = cap - 1
    p64 = pool.view(np.uint64)
    for bz in range(dims[2]):
        for by in range(dims[1]):
            for bx in range(dims[0]):
                if not used[bx + dims[0] * (by + dims[1] * bz)]:
                    continue
                bc = morton((glo[0] >> 3) + bx, (glo[1] >> 3) + by, (glo[2] >> 3) + bz)
                idx, h = _brick_find(tab_keys, tab_vals, bc, mask)
                if idx < 0:
                    idx = nb
                    bcodes[nb] = bc
                    tab_keys[h] = bc
                    tab_vals[h] = idx
                    nb += 1
                w0 = bx + 8 * by * row64 + 8 * bz * slab64
                # brick cell lx + 8 ly + 64 lz: row (ly, lz) is uint64 number idx * 64 + ly + 8 lz
                for z in range(8):
                    for y in range(8):
                        w = w0 + y * row64 + z * slab64
                        p64[idx * 64 + y + 8 * z] |= g64[w]
                        g64[w] = 0
    return tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap


# Scans whose key box has at most this many cells are marked in a dense grid (one byte per
# cell, reused from scan to scan), larger ones in bricks found through a grid directory.
_DENSE_MAX_CELLS = 1 << 22


# The brick grid directory of the fast path holds at most this many bricks (16 MB of int32);
# a larger key box is cut around the origin and the rays leaving it take the hashed path.
_GRID_MAX_BRICKS = 1 << 22


@njit(cache=True)
def _grid_box(pts, ok0, rf, max_range):
    """(glo, ghi, dims) of the brick grid for the rays ``pts`` from the key ``ok0``.

    The box covers the end keys (cut to ``max_range`` around the origin when it is >= 0) with a
    margin of 3 cells, starts on a multiple of 8 and stays inside the key space.
    """
    lo = ok0.copy()
    hi = ok0.copy()
    for j in range(pts.shape[0]):
        for a in range(3):
            kk = _key_checked(pts[j, a], rf)
            if kk >= 0:
                if kk < lo[a]:
                    lo[a] = kk
                if kk > hi[a]:
                    hi[a] = kk
    reach = 1 << 20
    if max_range >= 0.0:
        reach = np.int64(min(max_range * rf, 1e6)) + 3
    dims = np.empty(3, np.int64)
    glo = np.empty(3, np.int64)
    ghi = np.empty(3, np.int64)
    for _attempt in range(2):
        total = 1
        for a in range(3):
            l0 = max(lo[a] - 3, ok0[a] - reach, 0)
            h0 = min(hi[a] + 3, ok0[a] + reach, 65535)
            glo[a] = (l0 >> 3) << 3
            dims[a] = ((h0 - glo[a]) >> 3) + 1
            ghi[a] = min(glo[a] + 8 * dims[a] - 1, 65535)
            total *= dims[a]
        if total <= _GRID_MAX_BRICKS:
            break
        reach = 4 * 128  # a 128^3-brick box around the origin
    return glo, ghi, dims


@njit(cache=True, nogil=True)
def scan_marks(pts, origin, res, max_range, grid, path=0):
    """Free/hit marks of the rays ``pts`` from ``origin`` in bricks (no discretisation).

    Returns (tab_keys, tab_vals, pool, bcodes, n_bricks, counters, grid): the brick hash
    table, the marks (``pool[512 * b + cell]``: bit 0 free, bit 1 hit), the brick Morton codes,
    counters [n_bricks, n_nonfinite, n_out_of_bounds, n_failed, n_slow] and the dense-grid
    buffer. Rays inside the key box around the origin are marked by :func:`_mark_rays_dense`
    (in ``grid``: a zeroed uint8 buffer whose length is a multiple of 8, replaced by a larger
    one when too small and left zeroed for the next scan) or, for a large box,
    :func:`_mark_rays_grid`; the others
    (far from the origin, at the edge of the key space, origin outside the map) by
    :func:`_mark_rays`. All walk exactly computeRayKeys' cells, so the marks do not depend on
    the path taken (``path`` 1 / 2 forces the brick grid / the hashed path, for tests).
    Releases the GIL.
    """
    rf = 1.0 / res
    n = pts.shape[0]
    ox = np.float32(origin[0])
    oy = np.float32(origin[1])
    oz = np.float32(origin[2])
    ok0 = np.empty(3, np.int64)
    ok0[0] = _key_checked(ox, rf)
    ok0[1] = _key_checked(oy, rf)
    ok0[2] = _key_checked(oz, rf)
    counters = np.zeros(5, np.int64)
    cap = 1 << 12
    tab_keys = np.full(cap, _EMPTY, np.uint64)
    tab_vals = np.empty(cap, np.int64)
    pool_cap = 1024
    pool = np.zeros(pool_cap * 512, np.uint8)
    bcodes = np.empty(pool_cap, np.uint64)
    slow_pts = pts
    if ok0[0] >= 0 and ok0[1] >= 0 and ok0[2] >= 0:
        glo, ghi, dims = _grid_box(pts, ok0, rf, max_range)
        inside = True
        for a in range(3):
            if ok0[a] < glo[a] + 2 or ok0[a] > ghi[a] - 2:
                inside = False
        n_cells = 512 * dims[0] * dims[1] * dims[2]
        if path == 2:
            inside = False
        if inside and n_cells <= _DENSE_MAX_CELLS and path == 0:
            if grid.shape[0] < n_cells:
                grid = np.zeros(n_cells + n_cells // 4, np.uint8)
            slow = np.empty(n, np.int64)
            row = 8 * dims[0]
            _mark_rays_dense(pts, ox, oy, oz, ok0, res, max_range, grid, glo, ghi, row,
                             row * 8 * dims[1], counters, slow, np.empty(n, np.int64))
            tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap = _dense_to_bricks(
                grid, glo, dims, tab_keys, tab_vals, pool, bcodes, 0, cap, pool_cap)
            counters[0] = nb
            n_slow = counters[4]
            slow_pts = np.empty((n_slow, 3), pts.dtype)
            for j in range(n_slow):
                for a in range(3):
                    slow_pts[j, a] = pts[slow[j], a]
        elif inside:
            gdir = np.full(dims[0] * dims[1] * dims[2], -1, np.int32)
            slow = np.empty(n, np.int64)
            i = 0
            while True:
                i = _mark_rays_grid(pts, ox, oy, oz, ok0, res, max_range, i, pool, bcodes,
                                    counters, gdir, glo, ghi, dims[0], dims[0] * dims[1], slow)
                if i >= n:
                    break
                tab_keys, tab_vals, pool, bcodes, cap, pool_cap = _grow_marks(
                    tab_keys, tab_vals, pool, bcodes, counters[0], cap, pool_cap, False)
            # the grid's bricks into the hash table (the slow path and unite_marks look there)
            tab_keys, tab_vals, pool, bcodes, cap, pool_cap = _grow_marks(
                tab_keys, tab_vals, pool, bcodes, counters[0], cap, pool_cap, True)
            n_slow = counters[4]
            slow_pts = np.empty((n_slow, 3), pts.dtype)
            for j in range(n_slow):
                for a in range(3):
                    slow_pts[j, a] = pts[slow[j], a]
    nbr = np.full(pool_cap * 6, -1, np.int64)
    n2 = slow_pts.shape[0]
    i = 0
    while n2 > 0:
        i = _mark_rays(slow_pts, ox, oy, oz, ok0, res, max_range, i, tab_keys, tab_vals, pool,
                       bcodes, nbr, counters)
        if i >= n2:
            break
        nb = counters[0]
        tab_keys, tab_vals, pool, bcodes, cap, pool_cap = _grow_marks(
            tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap, False)
        if nbr.shape[0] < pool_cap * 6:
            nnbr = np.full(pool_cap * 6, -1, np.int64)
            nnbr[: nb * 6] = nbr[: nb * 6]
            nbr = nnbr
    return tab_keys, tab_vals, pool, bcodes, counters[0], counters, grid


@njit(cache=True)
def _grow_marks(tab_keys, tab_vals, pool, bcodes, nb, cap, pool_cap, rehash):
    """Room for more bricks: a larger pool when full, a larger hash table when half full (or
    a rebuilt one when ``rehash``: the grid path fills ``bcodes`` only)."""
    if nb >= pool_cap:
        pool_cap *= 2
        npool = np.zeros(pool_cap * 512, np.uint8)
        npool[: nb * 512] = pool[: nb * 512]
        pool = npool
        nbc = np.empty(pool_cap, np.uint64)
        nbc[:nb] = bcodes[:nb]
        bcodes = nbc
    if (nb + 1) * 2 > cap or rehash:
        while (nb + 1) * 2 > cap:
            cap *= 4
        mask = cap - 1
        tab_keys = np.full(cap, _EMPTY, np.uint64)
        tab_vals = np.empty(cap, np.int64)
        for j in range(nb):
            hh = _hash(bcodes[j], mask)
            while tab_keys[hh] != _EMPTY:
                hh = (hh + 1) & mask
            tab_keys[hh] = bcodes[j]
            tab_vals[hh] = j
    return tab_keys, tab_vals, pool, bcodes, cap, pool_cap


@njit(cache=True, nogil=True)
def sorted_scan_marks(points, origin, res, max_range, part, n_parts, block, grid, path=0,
                      presorted=False):
    """:func:`scan_marks` of one share of a scan's rays, sorted by direction first.

    The share is every ``n_parts``-th block of ``block`` rays starting at block ``part`` (rays
    of neighbouring blocks are alike, so the shares cost the same). ``presorted``: the points
    are already in :func:`sort_rays` order (the share keeps that order, no second sort).
    Releases the GIL: the threads of ``OcTree.insert_point_cloud`` mark their shares at the
    same time.
    """
    n = points.shape[0]
    if n_parts == 1:
        sub = points  # the whole scan: no copy (sort_rays and scan_marks only read it)
        m = n
    else:
        m = 0
        for s in range(part * block, n, n_parts * block):
            m += min(block, n - s)
        sub = np.empty((m, 3), points.dtype)
        j = 0
        for s in range(part * block, n, n_parts * block):
            for t in range(s, min(s + block, n)):
                sub[j, 0] = points[t, 0]
                sub[j, 1] = points[t, 1]
                sub[j, 2] = points[t, 2]
                j += 1
    if m >= 4096 and not presorted:
        sub = sort_rays(sub, origin)
    return scan_marks(sub, origin, res, max_range, grid, path)


@njit(cache=True, nogil=True)
def unite_marks(tab_keys, tab_vals, pool, bcodes, nb, pool2, bcodes2, nb2):
    """Add the marks of another chunk of rays (pool2, bcodes2, nb2) to (tab_keys, ..., nb).

    A scan's key sets are a union over its rays (free or hit per cell, hit wins), so OR-ing
    the marks of chunks brick by brick gives the marks of the whole scan exactly. Returns the
    (possibly grown) (tab_keys, tab_vals, pool, bcodes, nb).
    """
    need = nb + nb2
    if need > bcodes.shape[0]:
        npool = np.zeros(need * 512, np.uint8)
        npool[: nb * 512] = pool[: nb * 512]
        pool = npool
        nbc = np.empty(need, np.uint64)
        nbc[:nb] = bcodes[:nb]
        bcodes = nbc
    cap = tab_keys.shape[0]
    if need * 2 > cap:
        while need * 2 > cap:
            cap *= 2
        mask = cap - 1
        tab_keys = np.full(cap, _EMPTY, np.uint64)
        tab_vals = np.empty(cap, np.int64)
        for j in range(nb):
            hh = _hash(bcodes[j], mask)
            while tab_keys[hh] != _EMPTY:
                hh = (hh + 1) & mask
            tab_keys[hh] = bcodes[j]
            tab_vals[hh] = j
    mask = cap - 1
    for j in range(nb2):
        bc = bcodes2[j]
        idx, h = _brick_find(tab_keys, tab_vals, bc, mask)
        src = j * 512
        if idx < 0:
            idx = nb
            bcodes[nb] = bc
            nb += 1
            tab_keys[h] = bc
            tab_vals[h] = idx
            dst = idx * 512
            for m in range(512):
                pool[dst + m] = pool2[src + m]
        else:
            dst = idx * 512
            for m in range(512):
                pool[dst + m] |= pool2[src + m]
    return tab_keys, tab_vals, pool, bcodes, nb


@njit(cache=True, nogil=True)
def emit_updates(pool, bcodes, nb, hit_log, miss_log):
    """Sorted Morton codes of the marked cells of ``nb`` bricks, their float32 log-odds update
    (``hit_log`` for a hit cell, ``miss_log`` for a free one) and the number of hit cells.
    Releases the GIL."""
    # emit in Morton order: bricks sorted by code, cells by local Morton index
    order = np.argsort(bcodes[:nb])
    local = np.empty(512, np.int64)
    for m in range(512):
        c = np.uint64(m)
        lx = _compact1by2(c)
        ly = _compact1by2(c >> np.uint64(1))
        lz = _compact1by2(c >> np.uint64(2))
        local[m] = np.int64(lx) + (np.int64(ly) << 3) + (np.int64(lz) << 6)
    total = 0
    for j in range(nb * 512):
        if pool[j] != 0:
            total += 1
    out = np.empty(total, np.uint64)
    upd = np.empty(total, np.float32)
    n_hit = 0
    t = 0
    for oi in range(nb):
        b = order[oi]
        base = b * 512
        hi = bcodes[b] << np.uint64(9)
        for m in range(512):
            s = pool[base + local[m]]
            if s != 0:
                out[t] = hi | np.uint64(m)
                h = (s & 2) != 0
                upd[t] = hit_log if h else miss_log
                n_hit += h
                t += 1
    return out, upd, n_hit


# --------------------------------------------------------------------------- tree updates


@intrinsic
def _ctlz64(typingctx, x):
    """Count of leading zero bits of a uint64 (LLVM's ctlz: one instruction, no branches)."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(i64, [i64, ir.IntType(1)])
        fn = builder.module.declare_intrinsic("llvm.ctlz", [i64], fnty)
        return builder.call(fn, [args[0], ir.Constant(ir.IntType(1), 0)])

    return types.int64(types.uint64), codegen


@njit(cache=True, inline="always")
def _msb(x):
    """Index of the highest set bit of a non-zero uint64."""
    return 63 - _ctlz64(np.uint64(x))


@njit(cache=True)
def new_block_bound(codes):
    """Upper bound of the child blocks a batch of sorted codes can create (distinct ancestors)."""
    n = codes.shape[0]
    if n == 0:
        return 0
    total = 16
    for i in range(1, n):
        x = codes[i] ^ codes[i - 1]
        if x == 0:
            continue
        total += _msb(x) // 3
    return total


@njit(cache=True, inline="always")
def _alloc(first, free_blocks, state):
    # state[0] = number of free blocks on the stack, state[1] = next never-used block
    if state[0] > 0:
        state[0] -= 1
        return free_blocks[state[0]]
    b = state[1]
    state[1] += 1
    return b


@njit(cache=True, inline="always")
def _finalize(n, val, first, cmask, free_blocks, state):
    """pruneNode, else updateOccupancyChildren (max of existing children)."""
    f = first[n]
    if f < 0:
        return
    m = cmask[n]
    if m == 0xFF:
        v0 = val[f]
        collapsible = True
        for k in range(8):
            if first[f + k] >= 0 or val[f + k] != v0:
                collapsible = False
                break
        if collapsible:
            val[n] = v0
            first[n] = -1
            cmask[n] = 0
            free_blocks[state[0]] = f >> 3
            state[0] += 1
            return
    mx = -FLT_MAX
    for k in range(8):
        if (m >> k) & 1:
            v = val[f + k]
            if v > mx:
                mx = v
    val[n] = mx


@njit(cache=True)
def apply_updates(val, first, cmask, free_blocks, state, codes, upd, cmin, cmax, root_new, lazy):
    """updateNode(key, upd[i], lazy) for sorted, unique codes; one pass, inner nodes once.

    Equivalent to liboctomap's per-key updateNode: the early exit on a clamped leaf, the
    expansion of pruned leaves (children copy the value), new nodes at 0.0, clamping, and on the
    way up pruneNode / max-of-children, done here when a node leaves the DFS path (its subtree is
    final for this batch by then). Returns (number of keys that changed something, index of the
    first key not applied for lack of child blocks or -1).

    A new subtree whose whole key cube gets the same update (8^L consecutive codes, aligned)
    ends as one leaf with the value clamp(0 + u): its 8^L equal new leaves are pruned level by
    level. Such a cube is written as that leaf directly (not in lazy mode, which never prunes).
    """
    n = codes.shape[0]
    stk = np.zeros(17, np.int64)
    dirty = np.zeros(17, np.bool_)
    stk_len = 1
    prev = np.uint64(0)
    n_applied = 0
    stopped = -1
    cap_blocks = free_blocks.shape[0]
    i = 0
    while i < n:
        code = codes[i]
        u = upd[i]
        if i > 0:
            x = code ^ prev
            if x == 0:
                shared = 16
            else:
                shared = 15 - _msb(x) // 3
            keep = min(shared, stk_len - 1)
            for d in range(stk_len - 1, keep, -1):
                if dirty[d]:
                    if not lazy:
                        _finalize(stk[d], val, first, cmask, free_blocks, state)
                    dirty[d] = False
            stk_len = keep + 1
        prev = code
        d = stk_len - 1
        nd = stk[d]
        # search phase
        while d < 16:
            if first[nd] < 0:
                break
            pos = np.int64((code >> np.uint64(3 * (15 - d))) & np.uint64(7))
            if (cmask[nd] >> pos) & 1:
                nd = first[nd] + pos
                d += 1
                stk[d] = nd
            else:
                break
        stk_len = d + 1
        is_leaf = first[nd] < 0 and not (d == 0 and root_new)
        if d == 16 or is_leaf:
            lv = val[nd]
            if (u >= 0 and lv >= cmax) or (u <= 0 and lv <= cmin):
                # the next keys in the same (pruned) leaf whose update also stops at its clamp
                # change nothing either: step over them without a search each
                i += 1
                if d < 16:
                    sh = np.uint64(3 * (16 - d))
                    top = code >> sh
                    while i < n and (codes[i] >> sh) == top:
                        u2 = upd[i]
                        if not ((u2 >= 0 and lv >= cmax) or (u2 <= 0 and lv <= cmin)):
                            break
                        i += 1
                continue
        if state[0] + (cap_blocks - state[1]) < 16 - d:
            # out of child blocks: stop before touching key i (the caller grows the arrays and
            # applies codes[i:] as a new batch; consecutive batches equal one sequence)
            stopped = i
            break
        created = d == 0 and root_new and first[0] < 0
        # depth of the node to update: 16, or the top of a full new cube with one update
        dt = 16
        if not lazy and d <= 14 and (first[nd] >= 0 or created):
            lev = 0
            n_same = 1  # codes[i:i + n_same] are code, code + 1, ... with the update u
            while lev < 15 - d:
                size = np.int64(1) << (3 * (lev + 1))
                if (code & np.uint64(size - 1)) != 0 or i + size > n:
                    break
                # sorted unique codes: the cube is complete iff its last code is in place
                if codes[i + size - 1] != code + np.uint64(size - 1):
                    break
                while n_same < size and upd[i + n_same] == u:
                    n_same += 1
                if n_same < size:
                    break
                lev += 1
            dt = 16 - lev
        while d < dt:
            pos = np.int64((code >> np.uint64(3 * (15 - d))) & np.uint64(7))
            f = first[nd]
            if f < 0:
                blk = _alloc(first, free_blocks, state)
                f = blk * 8
                first[nd] = f
                if not created:
                    pv = val[nd]
                    for k in range(8):
                        val[f + k] = pv
                        first[f + k] = -1
                        cmask[f + k] = 0
                    cmask[nd] = 0xFF
                else:
                    cmask[nd] = np.uint8(1 << pos)
                    val[f + pos] = 0.0
                    first[f + pos] = -1
                    cmask[f + pos] = 0
            else:
                cmask[nd] = cmask[nd] | np.uint8(1 << pos)
                val[f + pos] = 0.0
                first[f + pos] = -1
                cmask[f + pos] = 0
                created = True
            nd = f + pos
            d += 1
            stk[d] = nd
        stk_len = dt + 1
        lv = np.float32(val[nd] + u)
        if lv < cmin:
            lv = cmin
        elif lv > cmax:
            lv = cmax
        val[nd] = lv
        n_keys = np.int64(1) << (3 * (16 - dt))
        n_applied += n_keys
        root_new = False
        for dd in range(dt - 1, -1, -1):
            if dirty[dd]:
                break
            dirty[dd] = True
        i += n_keys
    for d in range(stk_len - 1, -1, -1):
        if dirty[d]:
            if not lazy:
                _finalize(stk[d], val, first, cmask, free_blocks, state)
            dirty[d] = False
    return n_applied, stopped


# --------------------------------------------------------------------------- traversal


@njit(cache=True)
def preorder(first, cmask, has_root):
    """Pre-order DFS (children 0..7) of the tree: node index, depth, node-centre key.

    This is liboctomap's tree/leaf iterator order and its .ot/.bt payload order.
    """
    total, _ = count_nodes(first, cmask, has_root)
    nodes = np.empty(total, np.int64)
    depths = np.empty(total, np.uint8)
    keys = np.empty((total, 3), np.uint16)
    if total == 0:
        return nodes, depths, keys
    _fill_preorder(first, cmask, nodes, depths, keys)
    return nodes, depths, keys


@njit(cache=True)
def _fill_preorder(first, cmask, nodes, depths, keys):
    st_n = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    st_k = np.empty((8 * 17 + 8, 3), np.int64)
    st_n[0] = 0
    st_d[0] = 0
    st_k[0, 0] = 32768
    st_k[0, 1] = 32768
    st_k[0, 2] = 32768
    sp = 1
    t = 0
    while sp > 0:
        sp -= 1
        n = st_n[sp]
        d = st_d[sp]
        kx = st_k[sp, 0]
        ky = st_k[sp, 1]
        kz = st_k[sp, 2]
        nodes[t] = n
        depths[t] = d
        keys[t, 0] = kx
        keys[t, 1] = ky
        keys[t, 2] = kz
        t += 1
        f = first[n]
        if f >= 0:
            m = cmask[n]
            off = 32768 >> (d + 1)
            lo = off + (0 if off else 1)
            for k in range(7, -1, -1):
                if (m >> k) & 1:
                    st_n[sp] = f + k
                    st_d[sp] = d + 1
                    st_k[sp, 0] = kx + off if k & 1 else kx - lo
                    st_k[sp, 1] = ky + off if k & 2 else ky - lo
                    st_k[sp, 2] = kz + off if k & 4 else kz - lo
                    sp += 1


@njit(cache=True)
def count_nodes(first, cmask, has_root):
    """(number of nodes, number of inner nodes) by DFS."""
    if not has_root:
        return 0, 0
    st = np.empty(8 * 17 + 8, np.int64)
    st[0] = 0
    sp = 1
    total = 0
    inner = 0
    while sp > 0:
        sp -= 1
        n = st[sp]
        total += 1
        f = first[n]
        if f >= 0:
            inner += 1
            m = cmask[n]
            for k in range(8):
                if (m >> k) & 1:
                    st[sp] = f + k
                    sp += 1
    return total, inner


# --------------------------------------------------------------------------- whole-tree passes


@njit(cache=True)
def prune_sweeps(val, first, cmask, free_blocks, state):
    """prune(): sweeps at depth 15 -> 1 (pruneNode on nodes at that depth), stop on a sweep
    that prunes nothing (liboctomap's early stop). Returns the number of pruned nodes."""
    total = 0
    st_n = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    for max_depth in range(15, 0, -1):
        num = 0
        st_n[0] = 0
        st_d[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            n = st_n[sp]
            d = st_d[sp]
            if d < max_depth:
                f = first[n]
                if f >= 0:
                    m = cmask[n]
                    for k in range(8):
                        if (m >> k) & 1:
                            st_n[sp] = f + k
                            st_d[sp] = d + 1
                            sp += 1
            else:
                f = first[n]
                if f >= 0 and cmask[n] == 0xFF:
                    v0 = val[f]
                    ok = True
                    for k in range(8):
                        if first[f + k] >= 0 or val[f + k] != v0:
                            ok = False
                            break
                    if ok:
                        val[n] = v0
                        first[n] = -1
                        cmask[n] = 0
                        free_blocks[state[0]] = f >> 3
                        state[0] += 1
                        num += 1
        total += num
        if num == 0:
            break
    return total


@njit(cache=True)
def expand_all(val, first, cmask, free_blocks, state, cap_blocks):
    """expand(): every leaf above depth 16 gets 8 children copying its value, recursively.

    Returns False (and stops) when the block capacity would be exceeded."""
    st_n = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    st_n[0] = 0
    st_d[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        n = st_n[sp]
        d = st_d[sp]
        if d >= 16:
            continue
        f = first[n]
        if f < 0:
            if state[0] == 0 and state[1] >= cap_blocks:
                return False
            b = _alloc(first, free_blocks, state)
            f = b * 8
            for k in range(8):
                val[f + k] = val[n]
                first[f + k] = -1
                cmask[f + k] = 0
            first[n] = f
            cmask[n] = 0xFF
        m = cmask[n]
        for k in range(8):
            if (m >> k) & 1:
                st_n[sp] = f + k
                st_d[sp] = d + 1
                sp += 1
    return True


@njit(cache=True)
def expand_block_need(first, cmask, has_root):
    """Blocks expand() would allocate (sum over leaves at depth d of (8^(16-d)-1)/7)."""
    if not has_root:
        return 0
    st_n = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    st_n[0] = 0
    st_d[0] = 0
    sp = 1
    need = 0
    while sp > 0:
        sp -= 1
        n = st_n[sp]
        d = st_d[sp]
        f = first[n]
        if f < 0:
            if d < 16:
                need += ((1 << (3 * (16 - d))) - 1) // 7
            continue
        m = cmask[n]
        for k in range(8):
            if (m >> k) & 1:
                st_n[sp] = f + k
                st_d[sp] = d + 1
                sp += 1
    return need


@njit(cache=True)
def update_inner(val, first, cmask, has_root):
    """updateInnerOccupancy(): every inner node = max of its existing children (post-order)."""
    if not has_root:
        return
    nodes, depths, keys = preorder(first, cmask, has_root)
    for t in range(nodes.shape[0] - 1, -1, -1):
        n = nodes[t]
        f = first[n]
        if f >= 0:
            mx = -FLT_MAX
            m = cmask[n]
            for k in range(8):
                if (m >> k) & 1:
                    if val[f + k] > mx:
                        mx = val[f + k]
            val[n] = mx


# --------------------------------------------------------------------------- queries


@njit(cache=True)
def search_codes(val, first, cmask, has_root, codes, max_depth):
    """search(key, depth): node index of the node containing each key (-1 = unknown), its depth."""
    n = codes.shape[0]
    out = np.full(n, -1, np.int64)
    dep = np.zeros(n, np.uint8)
    if not has_root:
        return out, dep
    for i in range(n):
        code = codes[i]
        nd = 0
        d = 0
        found = True
        while d < max_depth:
            f = first[nd]
            pos = np.int64((code >> np.uint64(3 * (15 - d))) & np.uint64(7))
            if f >= 0 and (cmask[nd] >> pos) & 1:
                nd = f + pos
                d += 1
            elif f < 0:
                break
            else:
                found = False
                break
        if found:
            out[i] = nd
            dep[i] = d
    return out, dep


@njit(cache=True, inline="always")
def _search_one(first, cmask, kx, ky, kz):
    code = morton(kx, ky, kz)
    nd = 0
    for d in range(16):
        f = first[nd]
        if f < 0:
            return nd
        pos = np.int64((code >> np.uint64(3 * (15 - d))) & np.uint64(7))
        if (cmask[nd] >> pos) & 1:
            nd = f + pos
        else:
            return -1
    return nd


@njit(cache=True, inline="always")
def _search_path(first, cmask, code, prev, pstk, plen):
    """search(key) resuming from the deepest node shared with the previous key's path.

    Returns (node or -1, new path length). Consecutive DDA cells share most of their path.
    """
    x = code ^ prev
    shared = 16 if x == 0 else 15 - _msb(x) // 3
    d = min(shared, plen - 1)
    nd = pstk[d]
    while d < 16:
        f = first[nd]
        if f < 0:
            return nd, d + 1
        pos = np.int64((code >> np.uint64(3 * (15 - d))) & np.uint64(7))
        if (cmask[nd] >> pos) & 1:
            nd = f + pos
            d += 1
            pstk[d] = nd
        else:
            return -1, d + 1
    return nd, 17


@njit(cache=True)
def cast_rays(val, first, cmask, has_root, origins, directions, res, occ_thres,
              ignore_unknown, max_range):
    """castRay for N rays: (hit bool, status int8, end (N,3) float32).

    status: 0 = ran (hit says whether an occupied cell was found), 1 = origin out of bounds,
    2 = zero direction (end left as NaN, like liboctomap leaving ``end`` untouched).
    """
    n = origins.shape[0]
    hit = np.zeros(n, np.bool_)
    status = np.zeros(n, np.int8)
    end = np.full((n, 3), np.nan, np.float32)
    rf = 1.0 / res
    cur = np.empty(3, np.int64)
    step = np.zeros(3, np.int64)
    tmax = np.empty(3, np.float64)
    tdelta = np.empty(3, np.float64)
    max_set = max_range > 0.0
    mr2 = max_range * max_range
    pstk = np.zeros(17, np.int64)
    for i in range(n):
        ox = np.float32(origins[i, 0])
        oy = np.float32(origins[i, 1])
        oz = np.float32(origins[i, 2])
        o = (ox, oy, oz)
        cur[0] = _key_checked(ox, rf)
        cur[1] = _key_checked(oy, rf)
        cur[2] = _key_checked(oz, rf)
        if cur[0] < 0 or cur[1] < 0 or cur[2] < 0:
            status[i] = 1
            continue
        nd = _search_one(first, cmask, cur[0], cur[1], cur[2]) if has_root else -1
        if nd >= 0:
            if val[nd] >= occ_thres:
                for a in range(3):
                    end[i, a] = np.float32(_key_to_coord(cur[a], res))
                hit[i] = True
                continue
        elif not ignore_unknown:
            for a in range(3):
                end[i, a] = np.float32(_key_to_coord(cur[a], res))
            continue
        dx = np.float32(directions[i, 0])
        dy = np.float32(directions[i, 1])
        dz = np.float32(directions[i, 2])
        ln = math.sqrt(np.float64(np.float32(np.float32(dx * dx + dy * dy) + dz * dz)))
        if ln > 0:
            fl = np.float32(ln)
            dx = np.float32(dx / fl)
            dy = np.float32(dy / fl)
            dz = np.float32(dz / fl)
        dd = (dx, dy, dz)
        for a in range(3):
            di = dd[a]
            step[a] = 1 if di > 0 else (-1 if di < 0 else 0)
            if step[a] != 0:
                border = _key_to_coord(cur[a], res) + np.float64(step[a] * res * 0.5)
                tmax[a] = (border - np.float64(o[a])) / np.float64(di)
                tdelta[a] = res / np.float64(abs(di))
            else:
                tmax[a] = DBL_MAX
                tdelta[a] = DBL_MAX
        if step[0] == 0 and step[1] == 0 and step[2] == 0:
            status[i] = 2
            continue
        prev = morton(cur[0], cur[1], cur[2])
        plen = 1
        while True:
            if tmax[0] < tmax[1]:
                dim = 0 if tmax[0] < tmax[2] else 2
            else:
                dim = 1 if tmax[1] < tmax[2] else 2
            if (step[dim] < 0 and cur[dim] == 0) or (step[dim] > 0 and cur[dim] == 65535):
                for a in range(3):
                    end[i, a] = np.float32(_key_to_coord(cur[a], res))
                break
            cur[dim] += step[dim]
            tmax[dim] += tdelta[dim]
            ex = np.float32(_key_to_coord(cur[0], res))
            ey = np.float32(_key_to_coord(cur[1], res))
            ez = np.float32(_key_to_coord(cur[2], res))
            end[i, 0] = ex
            end[i, 1] = ey
            end[i, 2] = ez
            if max_set:
                a0 = np.float32(ex - ox)
                a1 = np.float32(ey - oy)
                a2 = np.float32(ez - oz)
                dsq = 0.0
                dsq += np.float64(np.float32(a0 * a0))
                dsq += np.float64(np.float32(a1 * a1))
                dsq += np.float64(np.float32(a2 * a2))
                if dsq > mr2:
                    break
            nd = -1
            if has_root:
                code = morton(cur[0], cur[1], cur[2])
                nd, plen = _search_path(first, cmask, code, prev, pstk, plen)
                prev = code
            if nd >= 0:
                if val[nd] >= occ_thres:
                    hit[i] = True
                    break
            elif not ignore_unknown:
                break
    return hit, status, end


# --------------------------------------------------------------------------- file payloads


@njit(cache=True)
def bt_encode(val, first, cmask, nodes, occ_thres):
    """.bt payload: 2 bytes per inner node in pre-order (1 = free leaf, 2 = occupied, 3 = inner)."""
    n_inner = 0
    for t in range(nodes.shape[0]):
        if first[nodes[t]] >= 0:
            n_inner += 1
    if nodes.shape[0] == 1:
        return np.zeros(2, np.uint8)
    out = np.zeros(2 * n_inner, np.uint8)
    j = 0
    for t in range(nodes.shape[0]):
        n = nodes[t]
        f = first[n]
        if f < 0:
            continue
        m = cmask[n]
        b0 = 0
        b1 = 0
        for k in range(8):
            if (m >> k) & 1:
                c = f + k
                if first[c] >= 0:
                    code = 3
                elif val[c] >= occ_thres:
                    code = 2
                else:
                    code = 1
                if k < 4:
                    b0 |= code << (2 * k)
                else:
                    b1 |= code << (2 * (k - 4))
        out[j] = b0
        out[j + 1] = b1
        j += 2
    return out


@njit(cache=True)
def bt_decode(data, start, cmin, cmax):
    """Parse a .bt payload from ``data[start:]``.

    Returns (val, first, cmask, n_blocks, end_offset, error_offset); error_offset >= 0 means the
    payload is truncated or inconsistent at that byte.
    """
    avail = data.shape[0] - start
    max_inner = avail // 2
    cap_blocks = max_inner + 1
    val = np.empty(cap_blocks * 8, np.float32)
    first = np.full(cap_blocks * 8, -1, np.int32)
    cmask = np.zeros(cap_blocks * 8, np.uint8)
    val[0] = cmax
    nb = 1
    pos = start
    st = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    st[0] = 0
    st_d[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        n = st[sp]
        d = st_d[sp]
        if pos + 2 > data.shape[0]:
            return val, first, cmask, nb, pos, pos
        b0 = data[pos]
        b1 = data[pos + 1]
        pos += 2
        codes = np.empty(8, np.int64)
        anyc = False
        for k in range(8):
            byte = b0 if k < 4 else b1
            codes[k] = (byte >> (2 * (k & 3))) & 3
            if codes[k] != 0:
                anyc = True
        if not anyc:
            continue
        if d >= 16:
            return val, first, cmask, nb, pos, pos - 2
        if nb >= cap_blocks:
            return val, first, cmask, nb, pos, pos - 2
        f = nb * 8
        nb += 1
        first[n] = f
        m = 0
        for k in range(8):
            c = codes[k]
            if c != 0:
                m |= 1 << k
                first[f + k] = -1
                cmask[f + k] = 0
                if c == 1:
                    val[f + k] = cmin
                elif c == 2:
                    val[f + k] = cmax
                else:
                    val[f + k] = cmax
        cmask[n] = m
        for k in range(7, -1, -1):
            if codes[k] == 3:
                st[sp] = f + k
                st_d[sp] = d + 1
                sp += 1
    return val, first, cmask, nb, pos, -1


@njit(cache=True)
def ot_decode(data, start, node_bytes):
    """Parse an .ot payload (pre-order: value bytes, child mask byte).

    Returns (payload (M, node_bytes-1) uint8 per slot, first, cmask, n_blocks, end, error_offset).
    """
    avail = data.shape[0] - start
    max_nodes = avail // node_bytes
    vb = node_bytes - 1
    # every node is node_bytes long, so the inner nodes (non-zero child mask) can be counted
    # before parsing: one block of 8 per inner node plus the root's block bounds the
    # allocation (a bound of one block per node zeroed ~8x more memory than needed)
    inner = 0
    for i in range(max_nodes):
        if data[start + i * node_bytes + vb] != 0:
            inner += 1
    cap_blocks = inner + 2
    payload = np.zeros((cap_blocks * 8, vb), np.uint8)
    first = np.full(payload.shape[0], -1, np.int32)
    cmask = np.zeros(payload.shape[0], np.uint8)
    nb = 1
    pos = start
    st = np.empty(8 * 17 + 8, np.int64)
    st_d = np.empty(8 * 17 + 8, np.int64)
    st[0] = 0
    st_d[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        n = st[sp]
        d = st_d[sp]
        if pos + node_bytes > data.shape[0]:
            return payload, first, cmask, nb, pos, pos
        for b in range(vb):
            payload[n, b] = data[pos + b]
        m = data[pos + vb]
        pos += node_bytes
        if m == 0:
            continue
        if d >= 16:
            return payload, first, cmask, nb, pos, pos - 1
        if (nb + 1) * 8 > payload.shape[0]:
            return payload, first, cmask, nb, pos, pos - 1
        f = nb * 8
        nb += 1
        first[n] = f
        cmask[n] = m
        for k in range(7, -1, -1):
            if (m >> k) & 1:
                st[sp] = f + k
                st_d[sp] = d + 1
                sp += 1
    return payload, first, cmask, nb, pos, -1


@njit(cache=True)
def leaf_arrays(first, val, nodes, depths, keys, res, max_depth):
    """Leaves of a pre-order listing: (index into listing, centres (M,3), sizes, log-odds).

    ``max_depth`` < 16 treats nodes at that depth as leaves (iterator maxDepth); descendants of
    such nodes are skipped because they come right after them in pre-order.
    """
    n = nodes.shape[0]
    sel = np.empty(n, np.int64)
    m = 0
    skip_below = 255
    for t in range(n):
        d = depths[t]
        if d > skip_below:
            continue
        skip_below = 255
        if first[nodes[t]] < 0:
            sel[m] = t
            m += 1
        elif d == max_depth:
            sel[m] = t
            m += 1
            skip_below = d
    centers = np.empty((m, 3), np.float64)
    sizes = np.empty(m, np.float64)
    lo = np.empty(m, np.float32)
    for j in range(m):
        t = sel[j]
        d = np.int64(depths[t])
        scale = np.float64(1 << (16 - d))
        size = res * scale
        sizes[j] = size
        lo[j] = val[nodes[t]]
        for a in range(3):
            if d == 0:
                centers[j, a] = 0.0
            else:
                centers[j, a] = (math.floor((np.float64(keys[t, a]) - 32768.0) / scale) + 0.5) \
                    * size
    return sel[:m], centers, sizes, lo
