"""Exports of an octree: occupied voxels to PLY (Open3D tensor writer), a height-slice PNG."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from estimation.errors import OctofactorError
from estimation.fileio import atomic_path, atomic_write, library_path

#: colours for class labels (tab20-like, uint8); label -1 (none) is grey
PALETTE = np.array([
    [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207],
    [174, 199, 232], [255, 187, 120], [152, 223, 138], [255, 152, 150], [197, 176, 213],
    [196, 156, 148], [247, 182, 210], [199, 199, 199], [219, 219, 141], [158, 218, 229],
], dtype=np.uint8)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """(N,3) uint8 colours of int labels (grey for negative labels)."""
    labels = np.asarray(labels, dtype=np.int64)
    out = PALETTE[np.mod(labels, len(PALETTE))]
    out[labels < 0] = (160, 160, 160)
    return out


def occupancy_colors(z: np.ndarray) -> np.ndarray:
    """(N,3) uint8 height colours (viridis) like octovis' height colouring."""
    from matplotlib import colormaps

    z = np.asarray(z, dtype=np.float64)
    span = z.max() - z.min() if z.size else 1.0
    t = (z - (z.min() if z.size else 0.0)) / (span if span > 0 else 1.0)
    return (colormaps["viridis"](t)[:, :3] * 255).astype(np.uint8)


def write_ply(tree, path: str | os.PathLike, binary: bool = True) -> int:
    """Write the occupied leaves as a point cloud PLY; returns the number of voxels.

    Vertex properties: x, y, z (float32 centres), red/green/blue (uint8: class colour for a
    SemanticOcTree, height colour otherwise), ``label`` (int32 arg-max class, -1 if none; only
    for a SemanticOcTree), ``log_odds`` (float32) and ``size`` (float32 edge length). Open3D's
    tensor writer accepts only these dtypes (int64/uint32 are rejected).
    """
    occ = tree.occupied_voxels()
    for name, values in (("voxel centres", occ.centers.astype(np.float32)),
                         ("voxel sizes", occ.sizes.astype(np.float32)),
                         ("log-odds", occ.log_odds)):
        if not np.all(np.isfinite(values)):
            raise OctofactorError(f"{path}: cannot export: {name} are NaN or inf in float32 "
                                  "(resolution or log-odds out of range)")
    if len(occ) == 0:
        # Open3D refuses to write an empty cloud: write the same header with 0 vertices
        props = ["float x", "float y", "float z", "uchar red", "uchar green", "uchar blue"]
        if hasattr(tree, "voxel_labels"):
            props.append("int label")
        props += ["float log_odds", "float size"]
        fmt = "binary_little_endian" if binary else "ascii"
        header = (f"ply\nformat {fmt} 1.0\nelement vertex 0\n"
                  + "".join(f"property {p}\n" for p in props) + "end_header\n")
        with atomic_write(path, "wb") as fh:
            fh.write(header.encode("ascii"))
        return 0
    import open3d as o3d

    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3d.core.Tensor(occ.centers.astype(np.float32))
    labels = None
    if hasattr(tree, "voxel_labels"):
        labels = tree.voxel_labels(occ).astype(np.int32)
        colors = label_colors(labels)
    else:
        colors = occupancy_colors(occ.centers[:, 2])
    pcd.point.colors = o3d.core.Tensor(colors.astype(np.uint8))
    if labels is not None:
        pcd.point.label = o3d.core.Tensor(labels.reshape(-1, 1))
    pcd.point.log_odds = o3d.core.Tensor(occ.log_odds.astype(np.float32).reshape(-1, 1))
    pcd.point.size = o3d.core.Tensor(occ.sizes.astype(np.float32).reshape(-1, 1))
    # Open3D writes by file name and picks the format from the suffix: a hidden temporary
    # .ply beside the destination (estimation.fileio), renamed over it on success
    library_path(path, "Open3D")  # the temporary file's name contains it
    with atomic_path(path, suffix=".ply") as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), pcd, write_ascii=not binary):
            raise OctofactorError(f"{path}: Open3D could not write the PLY file")
    return len(occ)


def _slice_figsize(centers_xy: np.ndarray, half: np.ndarray, width: float = 10.0,
                   min_height: float = 2.0, max_height: float = 10.0) -> tuple[float, float]:
    """Figure size (inches) whose axes have the slice's aspect ratio: a 30 m x 2 m corridor is
    a wide, low figure rather than a thin strip on a 4:3 canvas. Very tall slices get a
    narrower figure instead."""
    if len(centers_xy) == 0:
        return width, 0.75 * width
    extent = (centers_xy + half[:, None]).max(axis=0) - (centers_xy - half[:, None]).min(axis=0)
    aspect = float(extent[1] / max(extent[0], 1e-9))
    height = width * aspect + 1.0  # + title and tick labels
    if height > max_height:
        return max(3.0, (max_height - 1.0) / aspect + 1.2), max_height
    return width + 1.2, max(min_height, height)


def save_height_slice(tree, path: str | os.PathLike, height: float | None = None,
                      dpi: int = 120) -> float:
    """Save a PNG of the map cut at ``height`` (m): occupied black, free light, unknown grey.

    Returns the height used (default: the middle of the occupied voxels' z range).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lv = tree.leaves()
    occ = lv.log_odds >= tree.occupancy_thres_log
    if height is None:
        z = lv.centers[occ, 2] if occ.any() else lv.centers[:, 2]
        height = float(np.median(z)) if z.size else 0.0
    half = lv.sizes / 2
    cut = (lv.centers[:, 2] - half <= height) & (lv.centers[:, 2] + half > height)
    fig, ax = plt.subplots(figsize=_slice_figsize(lv.centers[cut, :2], half[cut]))
    ax.set_facecolor((0.6, 0.6, 0.6))
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    for mask, colour, label in ((cut & ~occ, (0.95, 0.95, 0.95), "free"),
                                (cut & occ, (0.05, 0.05, 0.05), "occupied")):
        rects = [Rectangle((c[0] - h, c[1] - h), 2 * h, 2 * h)
                 for c, h in zip(lv.centers[mask], half[mask], strict=True)]
        if rects:
            ax.add_collection(PatchCollection(rects, facecolor=colour, edgecolor="none",
                                              label=label))
    if cut.any():
        lo = (lv.centers[cut, :2] - half[cut, None]).min(axis=0)
        hi = (lv.centers[cut, :2] + half[cut, None]).max(axis=0)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"octree slice at z = {height:.2f} m (res {tree.resolution:g} m)\n"
                 "black occupied, white free, grey unknown", fontsize=9)
    path = Path(path)
    with atomic_write(path, "wb") as fh:
        # tight: the axes keep the map's aspect, the canvas follows them (no blank bands)
        fig.savefig(fh, format="png", dpi=dpi, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)
    return height
