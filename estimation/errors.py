"""The octofactor exception hierarchy.

Every error a user can cause (bad files, bad arguments, degenerate input) is an
:class:`OctofactorError`. The CLI turns it into one line on stderr and exit code 2.
``perception`` and ``mapping`` subclass it for their own errors.
"""
from __future__ import annotations

import os


class OctofactorError(Exception):
    """Base class of every error octofactor raises on purpose."""


class FormatError(OctofactorError):
    """A file is truncated, corrupt or lies about its content.

    The message names the file and, where known, the byte offset or line.
    """

    def __init__(self, path: str | os.PathLike | None, message: str, *,
                 offset: int | None = None, line: int | None = None):
        where = str(path) if path is not None else "<stream>"
        if line is not None:
            where += f":{line}"
        if offset is not None:
            where += f" (byte {offset})"
        super().__init__(f"{where}: {message}")
        self.path = None if path is None else str(path)
        self.offset = offset
        self.line = line
        self.reason = message


class FormatWarning(UserWarning):
    """A file was read, but part of it was not (e.g. g2o elements octofactor does not use):
    the CLI prints it as one ``octofactor: warning:`` line."""


class EstimationError(OctofactorError):
    """An estimator was given input it cannot work with."""
