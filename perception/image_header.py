"""Image sizes read from file headers, checked before anything is decoded.

A PNG or JPEG header can claim 60000 x 60000 pixels in a few bytes; OpenCV would then try to
allocate the image (or fail an assertion). :func:`check_image_header` reads the size the
header claims (PNG, JPEG, BMP, PNM) and refuses images that are too small for the detectors
or larger than :data:`MAX_IMAGE_PIXELS`. Other formats are left to OpenCV, whose own pixel
limit (``CV_IO_MAX_IMAGE_PIXELS``) still applies; its failure becomes an ImageError too.
"""
from __future__ import annotations

import os
import struct

from .errors import ImageError

#: most pixels an input image may have (8192 x 8192)
MAX_IMAGE_PIXELS = 1 << 26
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless...): not DHT/JPG/DAC
# library messages that mean the decoded pixels are not the file's (libjpeg, libpng)
_CORRUPT = ("Corrupt JPEG data", "Premature end of JPEG", "libpng error")
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def claimed_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) the header of an encoded image claims; None for unknown formats and
    headers too damaged to read (OpenCV then refuses them)."""
    if data[:8] == _PNG_MAGIC:
        if len(data) < 24 or data[12:16] != b"IHDR":
            return None
        return struct.unpack(">II", data[16:24])
    if data[:2] == b"\xff\xd8":
        pos = 2
        while pos + 4 <= len(data):
            if data[pos] != 0xFF:
                return None
            marker = data[pos + 1]
            if marker == 0xFF:  # fill byte
                pos += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                pos += 2
                continue
            (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
            if marker in _SOF:
                if pos + 9 > len(data):
                    return None
                height, width = struct.unpack(">HH", data[pos + 5:pos + 9])
                return width, height
            pos += 2 + length
        return None
    if data[:2] == b"BM" and len(data) >= 26:
        width, height = struct.unpack("<ii", data[18:26])
        return abs(width), abs(height)
    if len(data) >= 2 and data[:1] == b"P" and data[1:2] in b"123456":
        tokens = []
        for line in data[2:4096].splitlines():
            line = line.split(b"#", 1)[0]
            tokens += line.split()
            if len(tokens) >= 2:
                break
        try:
            return int(tokens[0]), int(tokens[1])
        except (IndexError, ValueError):
            return None
    return None


def check_image_header(path: str | os.PathLike, data: bytes, min_side: int = 1,
                       max_pixels: int = MAX_IMAGE_PIXELS) -> None:
    """Raise ImageError naming ``path`` when the claimed size is too small or too large."""
    size = claimed_size(data)
    if size is None:
        return
    width, height = size
    if width < min_side or height < min_side:
        raise ImageError(path, f"image header claims {width}x{height} pixels; at least "
                               f"{min_side}x{min_side} are needed")
    if width * height > max_pixels:
        raise ImageError(path, f"image header claims {width}x{height} pixels, more than the "
                               f"{max_pixels}-pixel limit")


def decode(path: str | os.PathLike, data: bytes, flags: int, min_side: int = 1):
    """``cv2.imdecode`` after :func:`check_image_header`; None when OpenCV cannot decode it."""
    import cv2
    import numpy as np

    from estimation.fileio import captured_native_output, first_native_message

    check_image_header(path, data, min_side)
    try:
        with captured_native_output() as noise:
            image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "OpenCV error"
        raise ImageError(path, f"cannot decode the image ({reason})") from None
    message = first_native_message(noise[0])
    if image is None and message:
        raise ImageError(path, f"cannot decode the image ({message})")
    # libjpeg decodes a damaged file to an image with grey blocks, and only says so
    if any(flag in noise[0] for flag in _CORRUPT):
        raise ImageError(path, f"corrupt image data ({message})")
    return image
