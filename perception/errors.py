"""The perception package's errors (subclasses of :class:`estimation.errors.OctofactorError`)."""
from __future__ import annotations

import os

from estimation.errors import OctofactorError


class PerceptionError(OctofactorError):
    """Base class of every error the perception package raises on purpose."""


class ImageError(PerceptionError):
    """An image file is missing, unreadable or corrupt; the message names the file."""

    def __init__(self, path: str | os.PathLike, message: str):
        super().__init__(f"{path}: {message}")
        self.path = str(path)
        self.reason = message
