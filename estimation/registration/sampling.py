"""Normal-space sampling (Rusinkiewicz and Levoy 2001) of the annealing stages' subset: rows
spread evenly over the directions of the surface normals, read off the GICP covariances.

Used by :meth:`.gicp.Registration._coarse_rows` (``NORMAL_SPACE_SAMPLING``); why and what it
changed: docs/registration_notes.md, "Normal-space sampling of the coarse subset".
"""
from __future__ import annotations

import numpy as np

# the hemisphere of normal directions (n and -n are one) in NORMAL_BINS[0] bands of equal
# n_z, each in NORMAL_BINS[1] sectors of equal azimuth: 32 bins of equal area (a cube map's
# 27 bins, without the pole, kept 3 of the 5 starts these bins rescue on the ICL-NUIM office:
# docs/registration_notes.md, "Normal-space sampling of the coarse subset")
NORMAL_BINS = (4, 8)


def covariance_normals(covariances: np.ndarray) -> np.ndarray:
    """Return the (M, 3) unit normals of GICP covariances ``I - (1 - epsilon) n n^T`` (the
    column of ``I - C`` with the largest diagonal, normalised: the kernels' rule), with
    ``n_z >= 0``; zero rows where ``C`` is isotropic (no surface)."""
    outer = np.eye(3) - covariances
    column = np.argmax(np.einsum("kii->ki", outer), axis=1)
    normals = outer[np.arange(len(outer)), :, column]
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 1e-9)
    normals[normals[:, 2] < 0] *= -1
    return normals


def normal_bins(normals: np.ndarray) -> np.ndarray:
    """Return each unit normal's (``n_z >= 0``) bin of :data:`NORMAL_BINS`; one more bin for
    a zero normal."""
    bands, sectors = NORMAL_BINS
    band = np.minimum((normals[:, 2] * bands).astype(int), bands - 1)
    azimuth = (np.arctan2(normals[:, 1], normals[:, 0]) + np.pi) / (2 * np.pi)
    sector = np.minimum((azimuth * sectors).astype(int), sectors - 1)
    return np.where(np.any(normals != 0, axis=1), band * sectors + sector, bands * sectors)


def normal_space_rows(normals: np.ndarray, n: int) -> np.ndarray:
    """Return the sorted indices of about ``n`` (at most ``n``) rows of ``normals`` (M, 3),
    spread evenly over the normals' directions (normal-space sampling): each bin of
    :func:`normal_bins` gives the same number of rows, evenly strided within the bin, and a
    bin with fewer gives all of its own (rows without a normal make one bin of their own)."""
    bins = normal_bins(normals)
    counts = np.bincount(bins, minlength=np.prod(NORMAL_BINS) + 1)
    # the quota: the largest q with sum(min(counts, q)) <= n (the smaller bins whole)
    sizes = np.sort(counts[counts > 0])
    quota, taken = sizes[-1], 0
    for i, size in enumerate(sizes):
        share = (n - taken) // (len(sizes) - i)
        if size > share:
            quota = share
            break
        taken += size
    order = np.argsort(bins, kind="stable")
    chosen = [members[np.linspace(0, len(members) - 1, min(len(members), quota)).astype(int)]
              for members in np.split(order, np.cumsum(counts)[:-1]) if len(members)]
    return np.sort(np.concatenate(chosen))
