"""PLY (and PCD) header checks run before Open3D reads a file.

Open3D (RPly) trusts the header: a vertex count larger than the file makes it allocate for
the count and print noise, a count smaller than the file silently drops the rest. So every
PLY reader first calls :func:`check_ply`, which parses the header itself and checks that the
element counts match the bytes (binary) or lines (ASCII) that follow, before Open3D is
called. Errors are :class:`~estimation.errors.FormatError` naming the file and the line or
byte offset.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from .errors import FormatError
from .fileio import check_input_file

#: numpy kind of each PLY scalar type, both the classic and the sized names (the byte order
#: is the file's)
PLY_NUMPY_TYPES = {
    "char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1",
    "short": "i2", "ushort": "u2", "int16": "i2", "uint16": "u2",
    "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: byte size of each PLY scalar type
PLY_TYPES = {name: int(kind[1]) for name, kind in PLY_NUMPY_TYPES.items()}
PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
#: longest header read (bytes)
MAX_HEADER_BYTES = 1 << 16
#: largest element count accepted (RPly counts are C longs; Open3D indexes with int64)
MAX_COUNT = (1 << 31) - 1


@dataclass(frozen=True)
class PlyElement:
    """One ``element`` of a PLY header: its name, count and ``(name, type)`` properties;
    list properties have the type ``list <count type> <item type>``."""

    name: str
    count: int
    properties: tuple[tuple[str, str], ...]

    @property
    def fixed_row_bytes(self) -> int | None:
        """Bytes of one binary row, None when the element has list properties."""
        if any(kind.startswith("list") for _, kind in self.properties):
            return None
        return sum(PLY_TYPES[kind] for _, kind in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """The parsed header of a PLY file whose counts agree with its content."""

    format: str
    elements: tuple[PlyElement, ...]
    data_start: int

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    @property
    def vertex_properties(self) -> tuple[str, ...]:
        vertex = self.element("vertex")
        return () if vertex is None else tuple(name for name, _ in vertex.properties)


def _parse_header(path, head: bytes) -> PlyHeader:
    if not head.startswith(b"ply\n") and not head.startswith(b"ply\r\n"):
        raise FormatError(path, "not a PLY file (no 'ply' magic line)", offset=0)
    end = head.find(b"end_header")
    if end < 0:
        raise FormatError(path, f"no 'end_header' in the first {MAX_HEADER_BYTES} bytes "
                          "(truncated or not a PLY file)", offset=min(len(head), 0))
    newline = head.find(b"\n", end)
    if newline < 0:
        raise FormatError(path, "truncated header (no newline after 'end_header')", offset=end)
    try:
        text = head[:end].decode("ascii")
    except UnicodeDecodeError as exc:
        raise FormatError(path, "header is not ASCII text", offset=exc.start) from None
    fmt = None
    elements: list[list] = []
    for line_no, line in enumerate(text.splitlines(), 1):
        tokens = line.split()
        if not tokens or tokens[0] in ("ply", "comment", "obj_info"):
            continue
        keyword = tokens[0]
        if keyword == "format":
            if len(tokens) != 3 or tokens[1] not in PLY_FORMATS:
                raise FormatError(path, f"bad format line {line.strip()[:60]!r}", line=line_no)
            fmt = tokens[1]
        elif keyword == "element":
            if len(tokens) != 3:
                raise FormatError(path, "element line needs a name and a count", line=line_no)
            try:
                count = int(tokens[2])
            except ValueError:
                raise FormatError(path, f"element count {tokens[2][:30]!r} is not an integer",
                                  line=line_no) from None
            if not 0 <= count <= MAX_COUNT:
                raise FormatError(path, f"element count {count} outside 0..{MAX_COUNT}",
                                  line=line_no)
            elements.append([tokens[1], count, []])
        elif keyword == "property":
            if not elements:
                raise FormatError(path, "property before any element", line=line_no)
            if len(tokens) == 3 and tokens[1] in PLY_TYPES:
                elements[-1][2].append((tokens[2], tokens[1]))
            elif (len(tokens) == 5 and tokens[1] == "list" and tokens[2] in PLY_TYPES
                  and tokens[3] in PLY_TYPES):
                elements[-1][2].append((tokens[4], f"list {tokens[2]} {tokens[3]}"))
            else:
                raise FormatError(path, f"bad property line {line.strip()[:60]!r}",
                                  line=line_no)
        else:
            raise FormatError(path, f"unknown header keyword {keyword[:30]!r}", line=line_no)
    if fmt is None:
        raise FormatError(path, "header has no format line")
    for name, _count, properties in elements:
        if name == "vertex":
            lists = [p for p, kind in properties if kind.startswith("list")]
            if lists:
                raise FormatError(path, f"vertex property {lists[0]!r} is a list (Open3D would "
                                  "skip it)")
            names = [p for p, _ in properties]
            if len(set(names)) != len(names):
                raise FormatError(path, "vertex properties repeat a name")
    return PlyHeader(fmt, tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
                     newline + 1)


def check_ply(path: str | os.PathLike) -> PlyHeader:
    """Return the header of the PLY file ``path`` after checking it against the content.

    Binary files: the element rows must fill the rest of the file exactly (elements with
    list properties, e.g. faces, must at least have room for an empty list per row).
    ASCII files: the non-blank lines after the header must number the sum of the counts.
    """
    size = check_input_file(path)
    with open(path, "rb") as handle:
        head = handle.read(MAX_HEADER_BYTES)
        header = _parse_header(path, head)
        payload = size - header.data_start
        if header.format == "ascii":
            handle.seek(header.data_start)
            lines = sum(1 for line in handle if line.strip())
            expected = sum(e.count for e in header.elements)
            if lines != expected:
                raise FormatError(path, f"header claims {expected} data lines "
                                  f"({_counts(header)}), the file holds {lines}",
                                  offset=header.data_start)
            return header
    exact = True
    need = 0
    for element in header.elements:
        row = element.fixed_row_bytes
        if row is None:
            exact = False
            # each list property holds at least its count
            row = sum(PLY_TYPES[kind.split()[1]] if kind.startswith("list") else PLY_TYPES[kind]
                      for _, kind in element.properties)
        need += element.count * row
    if need > payload or (exact and need != payload):
        relation = "but only" if need > payload else "but"
        raise FormatError(path, f"header claims {_counts(header)} ({need} bytes) {relation} "
                          f"{payload} bytes follow the header", offset=header.data_start)
    return header


def read_vertex_property(path: str | os.PathLike, header: PlyHeader, name: str):
    """Return the vertex property ``name`` of a checked PLY (:func:`check_ply`) as a numpy
    array of its own type.

    Open3D's reader skips the classic type names ``char``, ``short``, ``ushort`` and
    ``uint`` (it keeps ``uint16``): ScanNet's ``ushort label``, for one. So a column is
    read here, from the vertex rows' bytes (binary) or lines (ASCII). The elements before
    the vertices must have fixed-size rows in a binary file (their lists cannot be skipped
    without reading them).
    """
    import numpy as np

    index = next(i for i, e in enumerate(header.elements) if e.name == "vertex")
    vertex = header.elements[index]
    column = [p for p, _ in vertex.properties].index(name)
    if header.format == "ascii":
        lines_before = sum(e.count for e in header.elements[:index])
        with open(path, "rb") as handle:
            handle.seek(header.data_start)
            rows = (line for line in handle if line.strip())
            for _ in range(lines_before):
                next(rows)
            kind = PLY_NUMPY_TYPES[vertex.properties[column][1]]
            values = np.empty(vertex.count, dtype=kind)
            for row, line in enumerate(rows):
                if row == vertex.count:
                    break
                fields = line.split()
                if len(fields) != len(vertex.properties):
                    raise FormatError(path, f"vertex {row} has {len(fields)} values, the "
                                      f"header names {len(vertex.properties)}")
                try:
                    values[row] = float(fields[column]) if kind[0] == "f" else int(fields[column])
                except (ValueError, OverflowError):
                    raise FormatError(path, f"vertex {row}: {name} "
                                      f"{fields[column][:30].decode(errors='replace')!r} is "
                                      f"not a {vertex.properties[column][1]}") from None
        return values
    before = 0
    for element in header.elements[:index]:
        if element.fixed_row_bytes is None:
            raise FormatError(path, f"element {element.name!r} before the vertices has list "
                              f"properties: cannot locate the vertex property {name!r}")
        before += element.count * element.fixed_row_bytes
    order = "<" if header.format == "binary_little_endian" else ">"
    row = np.dtype([(f"p{i}", order + PLY_NUMPY_TYPES[kind])
                    for i, (_, kind) in enumerate(vertex.properties)])
    rows = np.memmap(path, dtype=row, mode="r", offset=header.data_start + before,
                     shape=(vertex.count,)) if vertex.count else np.zeros(0, row)
    return np.array(rows[f"p{column}"]).astype(rows.dtype[column].newbyteorder("="))


def _counts(header: PlyHeader) -> str:
    return ", ".join(f"{e.count} {e.name}" for e in header.elements) or "no elements"


def read_ply_quietly(path: str | os.PathLike, legacy: bool = False):
    """Read a checked PLY with Open3D (``o3d.t`` PointCloud, or legacy with ``legacy``)
    without Open3D's warnings on stdout."""
    import open3d as o3d

    from .fileio import captured_native_output, first_native_message, library_path

    name = library_path(path, "Open3D")
    with captured_native_output() as noise, \
            o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(name) if legacy else o3d.t.io.read_point_cloud(name)
    message = first_native_message(noise[0])
    if message:
        raise FormatError(path, f"Open3D could not read it ({message})")
    return cloud


#: PCD header keys in the order the format requires them (DATA last)
_PCD_KEYS = ("FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "POINTS", "DATA")


def check_pcd(path: str | os.PathLike) -> int:
    """Return the point count of the PCD file ``path`` after checking it against the content.

    The header's ``POINTS`` must equal ``WIDTH x HEIGHT`` and lie in 0..2^31-1; ``DATA ascii``
    must be followed by that many non-blank lines, ``DATA binary`` by exactly that many rows of
    the declared field sizes, ``DATA binary_compressed`` by a compressed block that fits the
    file and expands to exactly that many rows. Open3D would allocate for the count first.
    """
    import struct

    size = check_input_file(path)
    with open(path, "rb") as handle:
        head = handle.read(MAX_HEADER_BYTES)
        fields: dict[str, list[str]] = {}
        pos = 0
        line_no = 0
        while "DATA" not in fields:
            end = head.find(b"\n", pos)
            if end < 0:
                raise FormatError(path, f"no DATA line in the first {MAX_HEADER_BYTES} bytes "
                                  "(truncated or not a PCD file)")
            line_no += 1
            try:
                tokens = head[pos:end].decode("ascii").split()
            except UnicodeDecodeError:
                raise FormatError(path, "header is not ASCII text", line=line_no) from None
            pos = end + 1
            if tokens and not tokens[0].startswith("#"):
                fields[tokens[0].upper()] = tokens[1:]
        missing = [key for key in _PCD_KEYS if key not in fields]
        if missing:
            raise FormatError(path, f"PCD header lacks {', '.join(missing)}")
        try:
            sizes = [int(v) for v in fields["SIZE"]]
            counts = [int(v) for v in fields["COUNT"]]
            width, height, points = (int(fields[k][0]) for k in ("WIDTH", "HEIGHT", "POINTS"))
        except (ValueError, IndexError):
            raise FormatError(path, "PCD header numbers (SIZE, COUNT, WIDTH, HEIGHT, POINTS) "
                              "are not integers") from None
        n_fields = len(fields["FIELDS"])
        if not (len(sizes) == len(counts) == len(fields["TYPE"]) == n_fields) or \
                any(s not in (1, 2, 4, 8) for s in sizes) or \
                any(not 1 <= c <= 1024 for c in counts):
            raise FormatError(path, "PCD header FIELDS, SIZE, TYPE and COUNT do not match")
        if not 0 <= points <= MAX_COUNT or width < 0 or height < 0 or width * height != points:
            raise FormatError(path, f"PCD header claims {points} points (WIDTH {width} x HEIGHT "
                              f"{height}); counts must agree and lie in 0..{MAX_COUNT}")
        row = sum(s * c for s, c in zip(sizes, counts))
        kind = fields["DATA"][0].lower() if fields["DATA"] else ""
        payload = size - pos
        if kind == "ascii":
            handle.seek(pos)
            lines = sum(1 for line in handle if line.strip())
            if lines != points:
                raise FormatError(path, f"header claims {points} points, the file holds {lines} "
                                  "data lines", offset=pos)
        elif kind == "binary":
            if payload != points * row:
                raise FormatError(path, f"header claims {points} points ({points * row} bytes), "
                                  f"{payload} bytes follow the header", offset=pos)
        elif kind == "binary_compressed":
            handle.seek(pos)
            sizes_raw = handle.read(8)
            if len(sizes_raw) < 8:
                raise FormatError(path, "truncated compressed PCD block", offset=pos)
            compressed, uncompressed = struct.unpack("<II", sizes_raw)
            if compressed > payload - 8 or uncompressed != points * row:
                raise FormatError(path, f"compressed block of {compressed} bytes expanding to "
                                  f"{uncompressed} does not hold {points} points of {row} bytes "
                                  f"in the {payload - 8} bytes that follow", offset=pos)
        else:
            raise FormatError(path, f"unknown PCD DATA kind {kind!r}")
    return points
