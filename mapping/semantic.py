"""SemanticOcTree: OctoMap occupancy plus per-voxel class evidence (its own .ot id).

Occupancy is exactly :class:`mapping.OcTree` (same updates, pruning, files' occupancy part).
Class evidence is kept per finest voxel (depth 16 key) that received an occupied endpoint:
``E[v, c] = sum over scans of log p_scan(c | v)`` where ``p_scan`` is the mean of the class
probabilities of that scan's points falling in ``v`` (independent categorical observations,
multiplied = log-evidence added), renormalised so that ``max_c E[v, c] = 0`` and floored at
``evidence_floor`` (a clamp, like occupancy clamping, so a voxel can still change its class).
The class posterior is ``softmax(E[v])``. See docs/octree.md for the file format.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from estimation.errors import FormatError

from .octree import InsertStats, OcTree, OctreeError, as_point3, as_points3

SEMANTIC_ID = "SemanticOcTree"
_TRAILER_MAGIC = b"SEMV"


@dataclass(frozen=True)
class SemanticVoxels:
    """Occupied voxels with their class posterior; unpacks as ``centres, probs``.

    Attributes
    ----------
    centers : (M,3) float64 voxel centres
    probs : (M,C) float32 class posterior (uniform where no class evidence was seen)
    labels : (M,) int32 arg-max class, -1 where no class evidence was seen
    log_odds : (M,) float32 occupancy log-odds
    sizes : (M,) float64 voxel edge length
    depths : (M,) uint8
    keys : (M,3) uint16
    """

    centers: np.ndarray
    probs: np.ndarray
    labels: np.ndarray
    log_odds: np.ndarray
    sizes: np.ndarray
    depths: np.ndarray
    keys: np.ndarray

    def __iter__(self):
        return iter((self.centers, self.probs))

    def __len__(self) -> int:
        return int(self.centers.shape[0])


class SemanticOcTree(OcTree):
    """Occupancy octree with per-voxel class evidence.

    Parameters
    ----------
    resolution : leaf size (m)
    n_classes : number of classes C
    label_confidence : probability given to the label when ``labels`` (not ``probs``) are given
    evidence_floor : lower clamp of the normalised log-evidence (default log(1e-4))
    **kwargs : occupancy parameters of :class:`OcTree`
    """

    tree_type = SEMANTIC_ID

    def __init__(self, resolution: float, n_classes: int, label_confidence: float = 0.8,
                 evidence_floor: float = float(np.log(1e-4)), **kwargs):
        if int(n_classes) < 1:
            raise OctreeError(f"n_classes must be >= 1, got {n_classes}")
        super().__init__(resolution, **kwargs)
        self.n_classes = int(n_classes)
        self.label_confidence = float(label_confidence)
        self.evidence_floor = np.float32(evidence_floor)
        self._sem_codes = np.zeros(0, np.uint64)
        self._sem_ev = np.zeros((0, self.n_classes), np.float32)

    def insert_point_cloud(self, points, origin, probs=None, labels=None,
                           max_range: float = -1.0, discretize: bool = False,
                           lazy_eval: bool = False) -> InsertStats:
        """Insert a scan (occupancy exactly as OcTree) and fuse its class evidence.

        ``probs`` (N,C) class probabilities or ``labels`` (N,) ints (-1 = unlabelled) per point.
        Only endpoints that become occupied hits (finite, in the map, within ``max_range``)
        contribute class evidence.
        """
        pts = as_points3(points, "points")
        stats = super().insert_point_cloud(pts, origin, max_range=max_range,
                                           discretize=discretize, lazy_eval=lazy_eval)
        p = self._point_probs(pts.shape[0], probs, labels)
        if p is None:
            return stats
        o = as_point3(origin, "origin")
        with np.errstate(invalid="ignore", over="ignore"):
            d = (pts - o).astype(np.float32)
            sq = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float32) + d[:, 2] * d[:, 2]
            norm = np.sqrt(sq.astype(np.float32).astype(np.float64))
        keys, valid = self.coord_to_key_checked(pts)
        ok = valid & np.isfinite(pts).all(axis=1) & np.isfinite(p).all(axis=1)
        if max_range >= 0:
            ok &= norm <= max_range
        if not ok.any():
            return stats
        from .octree import _k

        k = _k()

        codes = k.keys_to_codes(np.ascontiguousarray(keys[ok]))
        uniq, inv = np.unique(codes, return_inverse=True)
        sums = np.zeros((uniq.shape[0], self.n_classes), np.float64)
        np.add.at(sums, inv, p[ok].astype(np.float64))
        counts = np.bincount(inv, minlength=uniq.shape[0]).astype(np.float64)
        mean = sums / counts[:, None]
        obs = np.log(np.maximum(mean, 1e-12)).astype(np.float32)
        self._merge_evidence(uniq, obs)
        return stats

    def _point_probs(self, n: int, probs, labels) -> np.ndarray | None:
        if probs is not None:
            p = np.asarray(probs, dtype=np.float32)
            if p.shape != (n, self.n_classes):
                raise OctreeError(f"probs must be ({n}, {self.n_classes}), got {p.shape}")
            s = p.sum(axis=1, keepdims=True)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(s > 0, p / s, np.nan).astype(np.float32)
        if labels is not None:
            lab = np.asarray(labels).reshape(-1)
            if lab.shape[0] != n:
                raise OctreeError(f"labels must have {n} entries, got {lab.shape[0]}")
            lab = lab.astype(np.int64)
            if (lab >= self.n_classes).any():
                raise OctreeError(f"labels must be < n_classes={self.n_classes}")
            c = self.n_classes
            rest = (1.0 - self.label_confidence) / max(c - 1, 1)
            p = np.full((n, c), rest, np.float32)
            good = lab >= 0
            p[good, lab[good]] = self.label_confidence if c > 1 else 1.0
            p[~good] = np.nan
            return p
        return None

    def _merge_evidence(self, codes: np.ndarray, obs: np.ndarray) -> None:
        pos = np.searchsorted(self._sem_codes, codes)
        pos_c = np.minimum(pos, max(self._sem_codes.shape[0] - 1, 0))
        found = (self._sem_codes.shape[0] > 0) & (self._sem_codes[pos_c] == codes) if \
            self._sem_codes.shape[0] else np.zeros(codes.shape[0], bool)
        ev = self._sem_ev
        if found.any():
            idx = pos_c[found]
            ev[idx] = self._normalise(ev[idx] + obs[found])
        if (~found).any():
            new_codes = np.concatenate([self._sem_codes, codes[~found]])
            new_ev = np.concatenate([ev, self._normalise(obs[~found])])
            order = np.argsort(new_codes, kind="stable")
            self._sem_codes = new_codes[order]
            self._sem_ev = new_ev[order]

    def _normalise(self, e: np.ndarray) -> np.ndarray:
        e = e - e.max(axis=1, keepdims=True)
        return np.maximum(e, self.evidence_floor).astype(np.float32)

    # ------------------------------------------------------------------ queries
    def class_probs_of_leaves(self, keys: np.ndarray, depths: np.ndarray) -> tuple[
            np.ndarray, np.ndarray]:
        """(probs (M,C), has_evidence (M,)) for leaves given by node keys and depths.

        A pruned leaf averages the posteriors of the voxels with evidence inside it.
        """
        from .octree import _k

        k = _k()

        m = keys.shape[0]
        c = self.n_classes
        probs = np.full((m, c), 1.0 / c, np.float32)
        has = np.zeros(m, bool)
        if m == 0 or self._sem_codes.shape[0] == 0:
            return probs, has
        diff = (16 - depths.astype(np.int64))
        codes = k.keys_to_codes(np.ascontiguousarray(keys.astype(np.uint16)))
        shift = (3 * diff).astype(np.uint64)
        lo = (codes >> shift) << shift
        hi = lo + (np.uint64(1) << shift)
        a = np.searchsorted(self._sem_codes, lo)
        b = np.searchsorted(self._sem_codes, hi)
        post = np.exp(self._sem_ev.astype(np.float64))
        post /= post.sum(axis=1, keepdims=True)
        csum = np.vstack([np.zeros((1, c)), np.cumsum(post, axis=0)])
        cnt = b - a
        has = cnt > 0
        probs[has] = ((csum[b[has]] - csum[a[has]]) / cnt[has, None]).astype(np.float32)
        return probs, has

    def occupied_voxels(self) -> SemanticVoxels:
        """Occupied leaves with class posteriors; ``centres, probs = tree.occupied_voxels()``."""
        lv = super().occupied_voxels()
        probs, has = self.class_probs_of_leaves(lv.keys, lv.depths)
        labels = np.where(has, probs.argmax(axis=1), -1).astype(np.int32)
        return SemanticVoxels(lv.centers, probs, labels, lv.log_odds, lv.sizes, lv.depths,
                              lv.keys)

    def voxel_labels(self, voxels: SemanticVoxels) -> np.ndarray:
        return voxels.labels

    # ------------------------------------------------------------------ files
    def _ot_extra(self, nodes: np.ndarray) -> bytes:
        rec = np.empty(nodes.shape[0], dtype=[("v", "<f4"), ("m", "u1")])
        rec["v"] = self._val[nodes]
        rec["m"] = np.where(self._first[nodes] >= 0, self._cmask[nodes], 0)
        from .octree import _k

        k = _k()

        keys = k.codes_to_keys(self._sem_codes).astype("<u2")
        trailer = (_TRAILER_MAGIC + struct.pack("<IQ", self.n_classes, self._sem_codes.shape[0])
                   + keys.tobytes() + self._sem_ev.astype("<f4").tobytes())
        return rec.tobytes() + trailer

    def write_bt(self, path, const: bool = False) -> None:
        """.bt holds occupancy only (written with id OcTree so liboctomap reads it)."""
        from . import io

        if not const:
            self.to_max_likelihood()
            self.prune()
        io.write_bt(self, path)

    @classmethod
    def _read_ot(cls, data: bytes, hdr, path) -> SemanticOcTree:
        from .octree import _k

        k = _k()
        from . import io

        if hdr.size == 0:
            raise FormatError(path, "SemanticOcTree file without nodes", offset=hdr.data_start)
        if hdr.size * 5 > len(data) - hdr.data_start:
            raise FormatError(path, f"truncated: header claims {hdr.size} nodes",
                              offset=hdr.data_start)
        buf = np.frombuffer(data, np.uint8)[: hdr.data_start + hdr.size * 5]
        payload, first, cmask, nb, end, err = k.ot_decode(buf, hdr.data_start, 5)
        if err >= 0:
            raise FormatError(path, "truncated or corrupt .ot payload", offset=int(err))
        io.check_finite_log_odds(data, path, hdr.data_start, 5,
                                 (int(end) - hdr.data_start) // 5)
        pos = int(end)
        if data[pos:pos + 4] != _TRAILER_MAGIC or len(data) < pos + 16:
            raise FormatError(path, "missing semantic section 'SEMV'", offset=pos)
        n_classes, n_vox = struct.unpack_from("<IQ", data, pos + 4)
        pos += 16
        if n_classes < 1 or n_classes > 65535:
            raise FormatError(path, f"bad class count {n_classes}", offset=pos - 12)
        need = n_vox * (6 + 4 * n_classes)
        if need > len(data) - pos:
            raise FormatError(path, f"truncated: {n_vox} semantic voxels need {need} bytes, "
                              f"{len(data) - pos} remain", offset=pos)
        keys = np.frombuffer(data, "<u2", count=3 * n_vox, offset=pos).reshape(-1, 3)
        pos += 6 * n_vox
        ev = np.frombuffer(data, "<f4", count=n_vox * n_classes, offset=pos).reshape(
            n_vox, n_classes)
        bad = np.flatnonzero(~np.isfinite(ev.reshape(-1)))
        if bad.size:
            raise FormatError(path, f"class evidence of semantic voxel #{int(bad[0]) // n_classes}"
                              f" is NaN or inf", offset=pos + 4 * int(bad[0]))
        if pos + 4 * n_vox * n_classes != len(data):
            raise FormatError(path, f"{len(data) - pos - 4 * n_vox * n_classes} unexpected bytes "
                              f"after {n_vox} semantic voxels of {n_classes} classes (a wrong "
                              "voxel or class count?)", offset=pos + 4 * n_vox * n_classes)
        val = np.ascontiguousarray(payload[:, :4]).view("<f4").reshape(-1).astype(np.float32)
        tree = io._make_tree(cls, hdr.res, nb * 8, first, cmask, val, nb)
        tree.n_classes = int(n_classes)
        tree.label_confidence = 0.8
        tree.evidence_floor = np.float32(np.log(1e-4))
        codes = k.keys_to_codes(np.ascontiguousarray(keys.astype(np.uint16)))
        if codes.shape[0] and (np.diff(codes.astype(np.int64)) <= 0).any():
            raise FormatError(path, "semantic voxels are not sorted", offset=pos)
        tree._sem_codes = codes
        tree._sem_ev = ev.astype(np.float32)
        if tree.size() != hdr.size:
            raise FormatError(path, f"tree size mismatch: header says {hdr.size} nodes, the "
                              f"payload holds {tree.size()}", offset=int(end))
        return tree
