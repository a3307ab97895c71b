"""4x4 transform text files (one matrix row per line, whitespace separated)."""
from __future__ import annotations

import os

import numpy as np

from ..errors import FormatError
from ..fileio import atomic_write, check_input_file


def read_transform(path: str | os.PathLike) -> np.ndarray:
    """Return the rigid 4x4 matrix stored as text in ``path`` (FormatError when it is not one)."""
    check_input_file(path, max_bytes=1 << 16)
    try:
        with open(path, encoding="utf-8") as handle:
            text = handle.read()
    except UnicodeDecodeError as exc:
        raise FormatError(path, "not UTF-8 text (a 4x4 matrix file)", offset=exc.start) from None
    rows = [ln.split() for ln in text.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise FormatError(path, "expected 4 lines of 4 numbers (a 4x4 matrix)")
    try:
        T = np.array([[float(v) for v in r] for r in rows])
    except ValueError as exc:
        raise FormatError(path, f"not a number: {exc}") from None
    if not np.all(np.isfinite(T)):
        raise FormatError(path, "matrix has NaN or inf entries")
    if np.max(np.abs(T[:3, :3])) > 1.0 + 1e-5:
        raise FormatError(path, "top-left 3x3 block is not a rotation matrix (an entry beyond 1)")
    if np.max(np.abs(T[:3, 3])) > 1e9:
        raise FormatError(path, "translation beyond 1e9 m")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise FormatError(path, "last row must be 0 0 0 1", line=4)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise FormatError(path, "top-left 3x3 block is not a rotation matrix")
    return T


def write_transform(path: str | os.PathLike, T: np.ndarray) -> None:
    """Write a 4x4 matrix as text with full precision, atomically."""
    with atomic_write(path, "w") as handle:
        for row in np.asarray(T, dtype=float).reshape(4, 4):
            handle.write(" ".join(f"{v:.17g}" for v in row) + "\n")
