"""File helpers shared by every writer: atomic replace and bounded binary reads."""
from __future__ import annotations

import contextlib
import os
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import FormatError


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success.

    An exception (or an interrupted process) leaves any existing file at ``path``
    untouched and removes the temporary file.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    # mkstemp creates 0600; give the file the permissions open() would (0666 & ~umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


class BinaryReader:
    """Little-endian reads from an in-memory buffer that fail with a :class:`FormatError`.

    Every read checks the remaining length first, so a header that lies about a count
    is caught before anything is allocated for it (use :meth:`require` with the byte
    size a count implies).
    """

    def __init__(self, data: bytes | memoryview, path: str | os.PathLike | None, offset: int = 0):
        self.data = memoryview(data)
        self.path = path
        self.pos = offset

    @property
    def remaining(self) -> int:
        return len(self.data) - self.pos

    def error(self, message: str, offset: int | None = None) -> FormatError:
        return FormatError(self.path, message, offset=self.pos if offset is None else offset)

    def require(self, nbytes: int, what: str) -> None:
        if nbytes < 0 or nbytes > self.remaining:
            raise self.error(
                f"truncated or corrupt: {what} needs {nbytes} bytes, {self.remaining} remain")

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        self.require(size, what)
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def take(self, nbytes: int, what: str) -> memoryview:
        self.require(nbytes, what)
        chunk = self.data[self.pos:self.pos + nbytes]
        self.pos += nbytes
        return chunk
