"""Image files: a frame's picture (e.g. one image of a stereo pair) as 8-bit grayscale or BGR.

OpenCV decodes the file (any format it reads: PNG, JPEG, TIFF, PGM ...); it is imported
only when an image is read. Before decoding, the width and height in the header of a PNG,
JPEG, BMP, PNM or TIFF file are checked against ``LIMITS.image_pixels`` and, but for TIFF,
against what the file's size can hold, so a small forged file (a decompression bomb) is
refused instead of allocating gigabytes.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from rough_map._bounded import clip
from rough_map._files import PathLike
from rough_map.errors import FileFormatError
from rough_map.limits import LIMITS

__all__ = ["image_size", "read_image"]


_SLACK = 1 << 20
"""Pixels always allowed whatever the file size (tiny flat images compress very well)."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_PNM = re.compile(rb"P[1-6](?:\s+|#[^\n]*\n)+(\d{1,12})(?:\s+|#[^\n]*\n)+(\d{1,12})\s")


def read_image(path: PathLike, *, color: bool = False) -> np.ndarray:
    """Read an image file as 8-bit grayscale, shape ``(height, width)``, or BGR.

    Parameters
    ----------
    path : str or PathLike
        The image file.
    color : bool
        Return 8-bit BGR, shape ``(height, width, 3)``, instead of grayscale.

    Returns
    -------
    ndarray of uint8, shape (height, width) or (height, width, 3)
        Gray levels; colour images are converted by OpenCV (``IMREAD_GRAYSCALE``).

    Raises
    ------
    FileFormatError
        The file is missing, its header declares more than ``LIMITS.image_pixels`` pixels or
        more than its size can hold, or it is not an image OpenCV can decode.
    """
    import cv2  # heavy: only when an image is read

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    data = path.read_bytes()
    size = image_size(data)
    if size is not None:
        width, height, kind = size
        limit = (
            LIMITS.image_pixels
            if kind == "TIFF"
            else min(LIMITS.image_pixels, LIMITS.deflate_ratio * len(data) + _SLACK)
        )
        if width * height > limit:
            raise FileFormatError(
                path,
                f"{kind} header declares {width} x {height} pixels; a file of {len(data)} B "
                f"is read up to {limit} pixels",
                field="size",
            )
    if data.startswith(_PNG_SIGNATURE) and (problem := _png_chunk_problem(data)):
        raise FileFormatError(path, problem, field="chunks")
    flag = cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    except cv2.error as err:  # e.g. over OpenCV's own pixel limit
        raise FileFormatError(path, f"not an image OpenCV can decode: {clip(err)}") from err
    if image is None:
        raise FileFormatError(path, "not an image OpenCV can decode")
    return np.asarray(image)


def image_size(data: bytes) -> tuple[int, int, str] | None:
    """Width and height (px) declared by the header of a PNG, JPEG, BMP, PNM or TIFF image,
    and the format's name; None for another format or a header too short to tell."""
    if data.startswith(_PNG_SIGNATURE) and data[12:16] == b"IHDR" and len(data) >= 24:
        width, height = struct.unpack_from(">II", data, 16)
        return width, height, "PNG"
    if data.startswith(b"\xff\xd8"):
        return _jpeg_size(data)
    if data.startswith(b"BM") and len(data) >= 26:
        width, height = struct.unpack_from("<ii", data, 18)
        return abs(width), abs(height), "BMP"
    if (match := _PNM.match(data[:4096])) is not None:
        return int(match[1]), int(match[2]), "PNM"
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return _tiff_size(data)
    return None


def _png_chunk_problem(data: bytes) -> str | None:
    """Why the chunks of a PNG cannot be right (one runs past the end of the file: the
    decoder would allocate its declared length), or None."""
    pos = len(_PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        if pos + 12 + length > len(data):
            return (
                f"PNG chunk at byte {pos} declares {length} B, past the end of the "
                f"{len(data)} B file (truncated or corrupt)"
            )
        if data[pos + 4 : pos + 8] == b"IEND":
            break
        pos += 12 + length
    return None


def _jpeg_size(data: bytes) -> tuple[int, int, str] | None:
    """Size from the first start-of-frame marker of a JPEG."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in _JPEG_SOF and i + 9 <= len(data):
            height, width = struct.unpack_from(">HH", data, i + 5)
            return width, height, "JPEG"
        if marker == 0xDA or length < 2:  # image data before any frame: let OpenCV judge
            return None
        i += 2 + length
    return None


def _tiff_size(data: bytes) -> tuple[int, int, str] | None:
    """ImageWidth and ImageLength of the first IFD of a TIFF."""
    order = "<" if data[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack_from(order + "I", data, 4)
        (count,) = struct.unpack_from(order + "H", data, ifd)
        found: dict[int, int] = {}
        for k in range(min(count, 4096)):
            tag, kind = struct.unpack_from(order + "HH", data, ifd + 2 + 12 * k)
            if tag in (256, 257):
                fmt = order + ("H" if kind == 3 else "I")
                found[tag] = struct.unpack_from(fmt, data, ifd + 2 + 12 * k + 8)[0]
    except struct.error:
        return None
    if 256 in found and 257 in found:
        return found[256], found[257], "TIFF"
    return None
