"""Image loading and line segments (OpenCV) for the vanishing-point detectors.

Everything here returns plain arrays: ``(M, 4)`` float64 segments ``x1, y1, x2, y2`` in
0-based pixel coordinates of the full-resolution image.
"""
from __future__ import annotations

import os

import numpy as np

from perception.errors import ImageError, PerceptionError

#: smallest image side the line and VP detectors accept (pixels)
MIN_IMAGE_SIDE = 8
#: largest image file read (bytes)
MAX_IMAGE_FILE_BYTES = 256 << 20


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Return the image file at ``path`` as an (H, W) uint8 grayscale array.

    Raises
    ------
    ImageError
        When the file is missing, unreadable, empty or not a decodable image (the message
        names the file).
    """
    import cv2

    from estimation.errors import FormatError
    from estimation.fileio import read_input_bytes

    from .image_header import decode

    try:
        data = read_input_bytes(path, max_bytes=MAX_IMAGE_FILE_BYTES)
    except FormatError as exc:
        raise ImageError(path, exc.reason) from None
    except FileNotFoundError:
        raise ImageError(path, "no such file") from None
    except IsADirectoryError:
        raise ImageError(path, "is a directory, not an image") from None
    except OSError as exc:
        raise ImageError(path, f"cannot read ({exc.strerror})") from None
    if len(data) == 0:
        raise ImageError(path, "empty file")
    image = decode(path, data, cv2.IMREAD_GRAYSCALE, min_side=MIN_IMAGE_SIDE)
    if image is None or image.size == 0:
        raise ImageError(path, "not a decodable image (corrupt or unsupported format)")
    return image


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Return an (H, W) uint8 grayscale view/copy of a gray, BGR or BGRA image array.

    Float images with values in [0, 1] are scaled to [0, 255]; other dtypes are clipped.

    Raises
    ------
    PerceptionError
        When the array is not an image shape.
    """
    import cv2

    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if image.shape[2] != 3:
            raise PerceptionError(f"expected 1, 3 or 4 channels, got image shape {image.shape}")
    elif image.ndim != 2:
        raise PerceptionError(f"expected an (H, W) or (H, W, C) image, got shape {image.shape}")
    if image.dtype != np.uint8:
        values = image.astype(np.float64)
        if np.issubdtype(image.dtype, np.floating) and np.nanmax(values, initial=0.0) <= 1.0:
            values = values * 255.0
        image = np.clip(np.nan_to_num(values), 0, 255).astype(np.uint8)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if min(image.shape) < MIN_IMAGE_SIDE:
        raise PerceptionError(f"image is {image.shape[1]}x{image.shape[0]} pixels; the detectors "
                              f"need at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}")
    return np.ascontiguousarray(image)


def lsd_segments(gray: np.ndarray, scale: float = 0.5, min_length: float = 0.0,
                 max_segments: int | None = None) -> np.ndarray:
    """Return the LSD line segments of a grayscale image as (M, 4) float64 ``x1, y1, x2, y2``.

    Uses ``cv2.createLineSegmentDetector`` with standard refinement; ``scale`` is LSD's own
    Gaussian down-scaling (0.5 halves the run time of the default 0.8 on 640x480 images with
    little loss on long segments). Segments shorter than ``min_length`` pixels are dropped;
    ``max_segments`` keeps the longest ones (bounds the hypothesis-scoring cost).
    """
    import cv2

    detector = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, scale)
    found = detector.detect(gray)[0]
    if found is None or len(found) == 0:
        return np.zeros((0, 4))
    segments = found.reshape(-1, 4).astype(np.float64)
    # OpenCV's LSD maps coordinates from its down-scaled image back by x / scale, which
    # moves pixel centres: the exact map is (x + 0.5) / scale - 0.5 in the integer-centre
    # convention used everywhere else (measured: -0.5 px at scale 0.5 without this).
    segments += 0.5 / scale - 0.5
    lengths = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    keep = lengths >= min_length
    segments, lengths = segments[keep], lengths[keep]
    if max_segments is not None and len(segments) > max_segments:
        # stable sort keeps the result deterministic when lengths tie
        order = np.argsort(-lengths, kind="stable")[:max_segments]
        segments = segments[np.sort(order)]
    return segments


def hough_segments(gray: np.ndarray, canny_low: float, canny_high: float, rho: float,
                   theta: float, threshold: int, min_line_length: float,
                   max_line_gap: float) -> np.ndarray:
    """Return Canny + probabilistic Hough (``cv2.HoughLinesP``) segments as (M, 4) float64."""
    import cv2

    edges = cv2.Canny(gray, canny_low, canny_high)
    found = cv2.HoughLinesP(edges, rho, theta, threshold, minLineLength=min_line_length,
                            maxLineGap=max_line_gap)
    if found is None or len(found) == 0:
        return np.zeros((0, 4))
    return found.reshape(-1, 4).astype(np.float64)
