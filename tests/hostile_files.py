"""Small valid files of every format octofactor reads, and hostile variants of them.

Used by test_fuzz_readers.py (seeds that hypothesis mutates) and test_hostile_cli.py (one
file per case of issue 16). Everything is written with plain numpy/struct or the project's
own writers, so a seed is a valid file by construction.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

IDENTITY_INFO = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


def g2o_text(vertex_extra: str = "", edge: str | None = None) -> str:
    """A 3-node chain as a 3-D g2o file; ``edge`` replaces the second edge line."""
    lines = [
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
        "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1",
        "VERTEX_SE3:QUAT 2 2 0.1 0 0 0 0 1" + vertex_extra,
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {IDENTITY_INFO}",
        edge if edge is not None else f"EDGE_SE3:QUAT 1 2 1 0.1 0 0 0 0 1 {IDENTITY_INFO}",
    ]
    return "\n".join(lines) + "\n"


def tum_text() -> str:
    return ("# timestamp tx ty tz qx qy qz qw\n"
            "1.0 0 0 0 0 0 0 1\n1.1 0.1 0 0 0 0 0 1\n1.2 0.2 0.01 0 0 0 0.0499792 0.9987503\n")


def transform_text() -> str:
    return "1 0 0 0.1\n0 1 0 0.2\n0 0 1 0.3\n0 0 0 1\n"


def camera_text() -> str:
    return "# fx fy cx cy width height depth_scale\n40 40 15.5 11.5 32 24 5000\n"


def scan_graph_bytes(self_loop: bool = False, nan_point: bool = False) -> bytes:
    """An OctoMap .graph with two nodes of three points and one edge (0 -> 1); with
    ``nan_point`` the second node's last point is NaN."""
    pose = struct.pack("<iddd", 3, 0.0, 0.0, 0.0) + struct.pack("<idddd", 4, 1.0, 0.0, 0.0, 0.0)
    parts = [struct.pack("<I", 2)]
    for node_id in (0, 1):
        parts.append(struct.pack("<I", 3))
        for k in range(3):
            x = float("nan") if nan_point and node_id == 1 and k == 2 else 1.0 + k
            parts.append(struct.pack("<iddd", 3, x, 0.5 * k, 0.2))
        parts.append(pose)
        parts.append(struct.pack("<I", node_id))
    parts.append(struct.pack("<I", 1))
    parts.append(struct.pack("<II", 0, 0 if self_loop else 1))
    parts.append(pose)
    parts.append(struct.pack("<d", 1.0))
    return b"".join(parts)


def _tree_points() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.uniform(-1.0, 1.0, size=(40, 3))


def octree_bytes(kind: str) -> bytes:
    """A small map as .bt, .ot or a SemanticOcTree .ot ('bt', 'ot', 'sem')."""
    from mapping import OcTree
    from mapping.io import bt_bytes, ot_bytes
    from mapping.semantic import SemanticOcTree

    points = _tree_points()
    if kind == "sem":
        tree = SemanticOcTree(0.25, n_classes=3)
        tree.insert_point_cloud(points, np.zeros(3), labels=np.arange(len(points)) % 3)
        return ot_bytes(tree)
    tree = OcTree(0.25)
    tree.insert_point_cloud(points, np.zeros(3))
    return bt_bytes(tree) if kind == "bt" else ot_bytes(tree)


def ply_bytes(n: int = 30, labels: np.ndarray | None = None, ascii: bool = False,
              claimed: int | None = None, probs: bool = False) -> bytes:
    """A PLY of ``n`` vertices x y z (float32) and an int32 label (or prob_0, prob_1);
    ``claimed`` writes another vertex count into the header."""
    rng = np.random.default_rng(n)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    labels = (np.arange(n) % 2) if labels is None else np.asarray(labels)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if probs:
        fields += [("prob_0", "<f4"), ("prob_1", "<f4")]
    else:
        fields += [("label", "<i4")]
    rows = np.zeros(n, dtype=fields)
    rows["x"], rows["y"], rows["z"] = xyz.T
    if probs:
        rows["prob_0"] = 0.3
        rows["prob_1"] = 0.7
    else:
        rows["label"] = labels
    count = n if claimed is None else claimed
    props = "".join(f"property {'float' if t == '<f4' else 'int'} {name}\n" for name, t in fields)
    fmt = "ascii" if ascii else "binary_little_endian"
    header = f"ply\nformat {fmt} 1.0\nelement vertex {count}\n{props}end_header\n".encode()
    if ascii:
        body = "".join(" ".join(repr(v.item()) for v in row) + "\n" for row in rows).encode()
    else:
        body = rows.tobytes()
    return header + body


def png_bytes(width: int, height: int, depth16: bool = False) -> bytes:
    import cv2

    rng = np.random.default_rng(width * height)
    if depth16:
        image = rng.integers(4000, 9000, size=(height, width)).astype(np.uint16)
    else:
        image = rng.integers(0, 255, size=(height, width, 3)).astype(np.uint8)
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def png_claiming(width: int, height: int) -> bytes:
    """A tiny PNG whose IHDR claims width x height (the IDAT holds almost nothing)."""
    def chunk(tag: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + tag + body
                + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def write_sequence(folder: Path, n_frames: int = 4, broken: tuple[int, ...] = ()) -> Path:
    """A TUM-layout RGB-D folder of 32x24 frames; frames in ``broken`` have garbage PNGs."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "rgb").mkdir(exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    (folder / "camera.txt").write_text(camera_text())
    rgb_lines, depth_lines = [], []
    for k in range(n_frames):
        stamp = 1.0 + 0.1 * k
        name = f"{stamp:.6f}.png"
        rgb = b"not a png" if k in broken else png_bytes(32, 24)
        (folder / "rgb" / name).write_bytes(rgb)
        (folder / "depth" / name).write_bytes(png_bytes(32, 24, depth16=True))
        rgb_lines.append(f"{stamp:.6f} rgb/{name}")
        depth_lines.append(f"{stamp:.6f} depth/{name}")
    (folder / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")
    return folder


def header_with(data: bytes, key: bytes, value: bytes) -> bytes:
    """An OctoMap file with the header line ``key ...`` replaced by ``key value``."""
    start = data.index(b"\n" + key + b" ") + 1
    end = data.index(b"\n", start)
    return data[:start] + key + b" " + value + data[end:]


def ot_payload_start(data: bytes) -> int:
    return data.index(b"data\n") + 5


def semantic_section(data: bytes) -> int:
    """Byte offset of the 'SEMV' magic of a SemanticOcTree .ot."""
    return data.rindex(b"SEMV")
