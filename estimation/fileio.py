"""File helpers shared by every reader and writer.

Writers go through :func:`atomic_write` / :func:`atomic_path`: the data goes to a temporary
file beside the destination, named ``.<name>.octofactor-<pid>.tmp<suffix>``, which is renamed
over the destination only when everything was written. An exception, Ctrl-C or SIGTERM (the
CLI turns it into an exception) removes the temporary file; one left by a killed process
(SIGKILL, power loss) is removed by the next run that writes the same path once its process
is gone. The destination must be a regular file or not exist: a symlink, a directory or a
special file (device, FIFO, socket) at the output path is refused with an
:class:`~estimation.errors.OctofactorError`, so ``-o /dev/null`` never replaces /dev/null and
a symlink is never silently turned into a regular file.

Readers check their input with :func:`check_input_file` (a regular file of bounded size: no
``/dev/zero``, FIFO or directory) and read binary files with :func:`read_input_bytes` (or
map them with :func:`map_input_file`).
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import FormatError, OctofactorError

#: largest input file octofactor reads (bytes); a bigger one is refused before it is read
MAX_INPUT_BYTES = 4 << 30
_TMP_TAG = ".octofactor-"


def check_input_file(path: str | os.PathLike, max_bytes: int = MAX_INPUT_BYTES) -> int:
    """Return the size of ``path`` after checking it is a regular file of at most ``max_bytes``.

    Raises FileNotFoundError/PermissionError (the CLI names the file) or a FormatError for a
    directory, a device, a FIFO or a socket (reading ``/dev/zero`` would never end) and for
    files larger than ``max_bytes``.
    """
    info = os.stat(path)
    if stat.S_ISDIR(info.st_mode):
        raise FormatError(path, "is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise FormatError(path, "not a regular file (device, FIFO or socket): octofactor "
                          "reads regular files only")
    if info.st_size > max_bytes:
        raise FormatError(path, f"file is {info.st_size} bytes, more than the "
                          f"{max_bytes}-byte limit")
    return int(info.st_size)


def map_input_file(path: str | os.PathLike, max_bytes: int = MAX_INPUT_BYTES):
    """The content of the regular file ``path`` (see :func:`check_input_file`) mapped
    read-only into memory: pages are read when first touched, so a reader that hands parts of
    a large binary file to several threads reads them in parallel, and nothing is copied.

    The map has the file's size when it was opened (a file that lies about its counts is
    caught by the reader's bounds checks as with :func:`read_input_bytes`). A file truncated
    by another process *while* it is mapped makes the next access to the lost pages fail
    with SIGBUS; use :func:`read_input_bytes` where that matters more than speed.
    """
    import mmap

    size = check_input_file(path, max_bytes)
    if size == 0:  # mmap cannot map an empty file
        return b""
    with open(path, "rb") as handle:
        try:
            return mmap.mmap(handle.fileno(), size, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # a file system that cannot map files: read it
            pass
    return read_input_bytes(path, max_bytes)


def library_path(path: str | os.PathLike, library: str) -> str:
    """``path`` as the UTF-8 string that GTSAM's and Open3D's bindings need; a file name with
    bytes that are not UTF-8 is an OctofactorError naming it (they cannot open it)."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        shown = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        raise OctofactorError(f"{shown}: the file name is not UTF-8, which {library} needs "
                              "(rename the file)") from None
    return text


def read_input_bytes(path: str | os.PathLike, max_bytes: int = MAX_INPUT_BYTES) -> bytes:
    """Return the content of the regular file ``path`` (see :func:`check_input_file`)."""
    size = check_input_file(path, max_bytes)
    with open(path, "rb") as handle:
        data = handle.read(size + 1)
    if len(data) > size:  # grew while we read it: still bounded
        raise FormatError(path, "file changed while it was read")
    return data


def _tmp_prefix(path: Path) -> str:
    return f".{path.name}{_TMP_TAG}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove temporary files of ``path`` left by octofactor processes that no longer run.

    Returns the removed paths. A temporary file whose process is alive (a concurrent
    writer) is kept.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    prefix = _tmp_prefix(path)
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.tmp")
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        match = pattern.match(name)
        if match is None:
            continue
        pid = int(match.group(1))
        if pid != os.getpid() and _pid_alive(pid):
            continue
        candidate = directory / name
        with contextlib.suppress(OSError):
            if stat.S_ISREG(os.lstat(candidate).st_mode):
                os.unlink(candidate)
                removed.append(candidate)
    return removed


def check_output_path(path: str | os.PathLike) -> Path:
    """Refuse an output path that is a symlink, a directory or a special file.

    Returns ``path`` as a Path. A missing file is fine (its folder must exist: the open
    fails with FileNotFoundError naming it otherwise).
    """
    path = Path(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return path
    except OSError as exc:
        raise OctofactorError(f"{path}: cannot write: {exc.strerror}") from None
    if stat.S_ISLNK(info.st_mode):
        raise OctofactorError(f"{path}: is a symbolic link; octofactor does not replace or "
                              "write through links (give the link's target instead)")
    if stat.S_ISDIR(info.st_mode):
        raise OctofactorError(f"{path}: is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise OctofactorError(f"{path}: is a device, FIFO or socket; octofactor writes regular "
                              "files only (it would replace it)")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to; rename it over ``path`` on success.

    For writers that take a file name (Open3D picks the format from ``suffix``). The
    temporary file is removed on any exception, including KeyboardInterrupt and the
    SystemExit the CLI raises on SIGTERM; errors name ``path``, not the temporary file.
    """
    path = check_output_path(path)
    directory = path.parent if str(path.parent) else Path(".")
    remove_stale_temporaries(path)
    tmp = directory / f"{_tmp_prefix(path)}{os.getpid()}.tmp{suffix}"
    try:
        try:
            yield tmp
            # mkstemp-like files are 0600; give the file the permissions open() would
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
            check_output_path(path)  # it may have become a link meanwhile
            os.replace(tmp, path)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    except OSError as exc:
        raise _named_output_error(path, exc) from None


def _named_output_error(path: Path, exc: OSError) -> OctofactorError:
    if exc.errno == errno.ENAMETOOLONG:
        reason = "file name too long"
    else:
        reason = exc.strerror or str(exc)
    return OctofactorError(f"{path}: cannot write: {reason}")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success.

    An exception (or an interrupted process) leaves any existing file at ``path``
    untouched and removes the temporary file (see the module docstring).
    """
    with atomic_path(path) as tmp:
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # a leftover of this very pid (a reused pid)
            os.unlink(tmp)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())


@contextlib.contextmanager
def captured_native_output() -> Iterator[list[str]]:
    """Capture what C/C++ libraries print on file descriptors 1 and 2 (libpng, libjpeg,
    libtiff, OpenCV's and Open3D's loggers) while the block runs.

    Yields a list that holds the captured text after the block, so that the caller can put
    the library's reason into its one-line error instead of letting it reach the terminal.
    """
    import sys
    import tempfile

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    captured: list[str] = []
    with tempfile.TemporaryFile() as noise_file:
        noise = noise_file.fileno()
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(noise, 1)
            os.dup2(noise, 2)
            yield captured
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            os.lseek(noise, 0, os.SEEK_SET)
            captured.append(os.read(noise, 1 << 16).decode("utf-8", "replace"))


def first_native_message(text: str) -> str:
    """The first line of captured library output, without OpenCV's log prefix."""
    import re

    for line in text.splitlines():
        line = re.sub(r"^\[\s*\w+:\d+@[\d.]+\]\s*(global\s+\S+\s+)?", "", line).strip()
        if line:
            return line[:160]
    return ""


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
