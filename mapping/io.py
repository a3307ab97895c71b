"""OctoMap .bt / .ot files, byte-compatible with liboctomap 1.9.7 (OCTOMAP.md sections 1-2).

Readers take the whole file into memory and parse it with bounded arrays: every count in a
header is checked against the bytes that remain before anything is allocated, and every
problem is a :class:`estimation.errors.FormatError` carrying the byte offset.
"""
from __future__ import annotations

import math
import os

import numpy as np

from estimation.errors import FormatError
from estimation.fileio import atomic_write, read_input_bytes

from .octree import MAX_RESOLUTION, OcTree

BT_MAGIC = b"# Octomap OcTree binary file"
OT_MAGIC = b"# Octomap OcTree file"
_COMMENT = b"# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
MAX_HEADER = 1 << 20

#: .ot ids this module reads, with the bytes of one node's data (the child mask excluded)
OT_NODE_BYTES = {"OcTree": 4, "OcTreeStamped": 4, "ColorOcTree": 7}
#: .bt ids this module reads (a .bt holds occupancy only, whatever the tree type)
BT_IDS = ("OcTree", "OcTreeStamped", "ColorOcTree")
#: largest resolution read (m): voxel centres and sizes (float32 in liboctomap and in PLY
#: exports) stay finite up to res * 2**16 < 3.4e38
MAX_RES = MAX_RESOLUTION


def format_res(res: float) -> str:
    """Resolution as a C++ ostream prints it (6 significant digits, %g)."""
    return f"{res:g}"


def _header(magic: bytes, tree_id: str, size: int, res: float) -> bytes:
    return (magic + b"\n" + _COMMENT + f"id {tree_id}\nsize {size}\nres {format_res(res)}\ndata\n"
            .encode("ascii"))


def bt_bytes(tree: OcTree) -> bytes:
    """The .bt file of ``tree`` as it is (writeBinaryConst)."""
    from .octree import _k

    k = _k()

    nodes, _, _ = tree._structure()
    tree_id = getattr(tree, "_file_id", None) or tree.tree_type
    if tree_id == "SemanticOcTree":
        tree_id = "OcTree"  # .bt holds occupancy only: liboctomap reads it as an OcTree
    head = _header(BT_MAGIC, tree_id, int(nodes.shape[0]), tree.resolution)
    if nodes.shape[0] == 0:
        return head
    payload = k.bt_encode(tree._val, tree._first, tree._cmask, nodes, tree.occupancy_thres_log)
    return head + payload.tobytes()


def ot_bytes(tree: OcTree) -> bytes:
    """The .ot file of ``tree`` (every node: its data bytes, then the child-mask byte)."""
    nodes, _, _ = tree._structure()
    tree_id = getattr(tree, "_file_id", None) or tree.tree_type
    if tree_id == "ColorOcTree" and tree.color is None:
        tree_id = "OcTree"  # e.g. read from a ColorOcTree .bt, which carries no colours
    head = _header(OT_MAGIC, tree_id, int(nodes.shape[0]), tree.resolution)
    if tree.color is not None:
        rec = np.empty(nodes.shape[0], dtype=[("v", "<f4"), ("c", "u1", (3,)), ("m", "u1")])
        rec["c"] = tree.color[nodes]
    else:
        rec = np.empty(nodes.shape[0], dtype=[("v", "<f4"), ("m", "u1")])
    rec["v"] = tree._val[nodes]
    rec["m"] = np.where(tree._first[nodes] >= 0, tree._cmask[nodes], 0)
    extra = tree._ot_extra(nodes) if hasattr(tree, "_ot_extra") else None
    if extra is not None:
        return head + extra
    return head + rec.tobytes()


def write_bt(tree: OcTree, path: str | os.PathLike) -> None:
    data = bt_bytes(tree)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def write_ot(tree: OcTree, path: str | os.PathLike) -> None:
    data = ot_bytes(tree)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


class _Header:
    def __init__(self, kind: str, tree_id: str, size: int, res: float, data_start: int):
        self.kind, self.tree_id, self.size, self.res, self.data_start = (
            kind, tree_id, size, res, data_start)


def parse_header(data: bytes, path) -> _Header:
    """Parse the text header (readHeader): kind ('bt'/'ot'), id, size, res, payload offset."""
    nl = data.find(b"\n", 0, MAX_HEADER)
    first = data[: nl if nl >= 0 else min(len(data), 80)]
    if first.startswith(BT_MAGIC):
        kind = "bt"
    elif first.startswith(OT_MAGIC):
        kind = "ot"
    else:
        raise FormatError(path, "not an OctoMap file (first line is neither "
                          "'# Octomap OcTree binary file' nor '# Octomap OcTree file')", offset=0)
    if nl < 0:
        raise FormatError(path, "truncated header", offset=len(data))
    pos = nl + 1
    tree_id = None
    size = None
    res = None
    limit = min(len(data), MAX_HEADER)

    def token(p: int) -> tuple[bytes, int, int]:
        while p < limit and data[p:p + 1].isspace():
            p += 1
        s = p
        while p < limit and not data[p:p + 1].isspace():
            p += 1
        return data[s:p], s, p

    while True:
        tok, start, pos = token(pos)
        if not tok:
            raise FormatError(path, "header has no 'data' line", offset=start)
        if tok.startswith(b"#"):
            e = data.find(b"\n", pos, limit)
            if e < 0:
                raise FormatError(path, "truncated header", offset=pos)
            pos = e + 1
        elif tok == b"id":
            val, s, pos = token(pos)
            tree_id = val.decode("ascii", "replace")
        elif tok == b"size":
            val, s, pos = token(pos)
            try:
                size = int(val)
            except ValueError:
                raise FormatError(path, f"bad size {val!r}", offset=s) from None
            if size < 0:
                raise FormatError(path, f"negative size {size}", offset=s)
        elif tok == b"res":
            val, s, pos = token(pos)
            try:
                res = float(val)
            except ValueError:
                raise FormatError(path, f"bad res {val!r}", offset=s) from None
            if not (res > 0 and math.isfinite(res)):
                raise FormatError(path, f"resolution must be positive, got {res}", offset=s)
            if res > MAX_RES:
                raise FormatError(path, f"resolution {res:g} m is beyond {MAX_RES:g} m (voxel "
                                  "coordinates would overflow float32)", offset=s)
        elif tok == b"data":
            e = data.find(b"\n", pos, limit)
            if e < 0:
                raise FormatError(path, "truncated header after 'data'", offset=pos)
            pos = e + 1
            break
        else:
            e = data.find(b"\n", pos, limit)
            pos = limit if e < 0 else e + 1
    if not tree_id:
        raise FormatError(path, "header has no id", offset=pos)
    if tree_id == "1":
        tree_id = "OcTree"
    if res is None:
        raise FormatError(path, "header has no res", offset=pos)
    if size is None:
        raise FormatError(path, "header has no size", offset=pos)
    return _Header(kind, tree_id, size, res, pos)


def read_tree(path: str | os.PathLike, data: bytes | None = None) -> OcTree:
    """Read a .bt or .ot file into an :class:`OcTree` (SemanticOcTree for its own id)."""
    if data is None:
        data = read_input_bytes(path)
    hdr = parse_header(data, path)
    if hdr.kind == "bt":
        return _read_bt(data, hdr, path)
    return _read_ot(data, hdr, path)


def _make_tree(cls, res: float, n_slots: int, first, cmask, val, nb: int):
    tree = cls.__new__(cls)
    OcTree.__init__(tree, res)
    tree._val = np.ascontiguousarray(val[: nb * 8])
    tree._first = np.ascontiguousarray(first[: nb * 8])
    tree._cmask = np.ascontiguousarray(cmask[: nb * 8])
    tree._free = np.zeros(nb, np.int64)
    tree._state = np.array([0, nb], np.int64)
    tree._has_root = True
    tree._cache = None
    return tree


def _read_bt(data: bytes, hdr: _Header, path) -> OcTree:
    from .octree import _k

    k = _k()

    if hdr.tree_id not in BT_IDS:
        raise FormatError(path, f"unknown or unsupported tree id {hdr.tree_id!r} in a .bt file "
                          f"(known: {', '.join(BT_IDS)})", offset=0)
    proto = OcTree(hdr.res)
    if hdr.size == 0:
        _check_empty_payload(data, hdr, path)
        tree = OcTree(hdr.res)
    else:
        if hdr.size > 8 * (len(data) - hdr.data_start) + 1:
            raise FormatError(path, f"header claims {hdr.size} nodes but only "
                              f"{len(data) - hdr.data_start} payload bytes follow",
                              offset=hdr.data_start)
        buf = np.frombuffer(data, np.uint8)
        val, first, cmask, nb, end, err = k.bt_decode(buf, hdr.data_start, proto.clamp_min_log,
                                                     proto.clamp_max_log)
        if err >= 0:
            raise FormatError(path, "truncated or corrupt .bt payload", offset=int(err))
        tree = _make_tree(OcTree, hdr.res, nb * 8, first, cmask, val, nb)
        # inner nodes = max of their children; the root keeps clamp_max (readBinaryNode)
        k.update_inner(tree._val, tree._first, tree._cmask, True)
        tree._val[0] = proto.clamp_max_log
        if tree.size() != hdr.size:
            raise FormatError(path, f"tree size mismatch: header says {hdr.size} nodes, the "
                              f"payload holds {tree.size()}", offset=int(end))
        if int(end) != len(data):
            raise FormatError(path, f"{len(data) - int(end)} unexpected bytes after the tree",
                              offset=int(end))
    if hdr.tree_id != "OcTree":
        tree._file_id = hdr.tree_id
    return tree


def _check_empty_payload(data: bytes, hdr: _Header, path) -> None:
    """A header with ``size 0`` must end the file: a payload behind it would be dropped."""
    if len(data) > hdr.data_start:
        raise FormatError(path, f"header says size 0 (an empty tree) but "
                          f"{len(data) - hdr.data_start} payload bytes follow",
                          offset=hdr.data_start)


def check_finite_log_odds(data: bytes, path, data_start: int, node_bytes: int,
                          n_nodes: int) -> None:
    """FormatError at the first .ot node (file order) whose float32 log-odds are NaN or inf."""
    records = np.frombuffer(data, np.uint8, count=n_nodes * node_bytes, offset=data_start)
    values = np.ascontiguousarray(records.reshape(n_nodes, node_bytes)[:, :4]).view("<f4")
    values = values.reshape(-1)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        index = int(bad[0])
        raise FormatError(path, f"node #{index} has log-odds {float(values[index])} (NaN or "
                          "inf)", offset=data_start + index * node_bytes)


def _read_ot(data: bytes, hdr: _Header, path) -> OcTree:
    from .octree import _k

    k = _k()

    if hdr.tree_id == "SemanticOcTree":
        from .semantic import SemanticOcTree

        return SemanticOcTree._read_ot(data, hdr, path)
    if hdr.tree_id not in OT_NODE_BYTES:
        raise FormatError(path, f"unknown or unsupported tree id {hdr.tree_id!r} (known: "
                          f"{', '.join(OT_NODE_BYTES)}, SemanticOcTree)", offset=0)
    nbytes = OT_NODE_BYTES[hdr.tree_id] + 1
    if hdr.size == 0:
        _check_empty_payload(data, hdr, path)
        tree = OcTree(hdr.res)
    else:
        if hdr.size * nbytes > len(data) - hdr.data_start:
            raise FormatError(path, f"truncated: header claims {hdr.size} nodes "
                              f"({hdr.size * nbytes} bytes), {len(data) - hdr.data_start} "
                              "bytes follow", offset=hdr.data_start)
        buf = np.frombuffer(data, np.uint8)[: hdr.data_start + hdr.size * nbytes]
        payload, first, cmask, nb, end, err = k.ot_decode(buf, hdr.data_start, nbytes)
        if err >= 0:
            raise FormatError(path, "truncated or corrupt .ot payload (the node tree does not "
                              "end where the header's size says)", offset=int(err))
        # each parsed node is one tree node: the count needs no traversal
        n_parsed = (int(end) - hdr.data_start) // nbytes
        if n_parsed != hdr.size:
            raise FormatError(path, f"tree size mismatch: header says {hdr.size} nodes, the "
                              f"payload holds {n_parsed}", offset=int(end))
        if int(end) != len(data):
            raise FormatError(path, f"{len(data) - int(end)} unexpected bytes after the tree",
                              offset=int(end))
        val = np.ascontiguousarray(payload[:, :4]).view("<f4").reshape(-1).astype(np.float32)
        check_finite_log_odds(data, path, hdr.data_start, nbytes, n_parsed)
        tree = _make_tree(OcTree, hdr.res, nb * 8, first, cmask, val, nb)
        if hdr.tree_id == "ColorOcTree":
            tree.color = np.ascontiguousarray(payload[: nb * 8, 4:7])
    if hdr.tree_id != "OcTree":
        tree._file_id = hdr.tree_id
        if hdr.tree_id == "ColorOcTree":
            tree.tree_type = "ColorOcTree"
    return tree
