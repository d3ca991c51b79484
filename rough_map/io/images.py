"""Image files: a frame's picture (e.g. one image of a stereo pair) as 8-bit grayscale.

OpenCV decodes the file (any format it reads: PNG, JPEG, TIFF, PGM ...); it is imported
only when an image is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rough_map._files import PathLike
from rough_map.errors import FileFormatError

__all__ = ["read_image"]


def read_image(path: PathLike) -> np.ndarray:
    """Read an image file as 8-bit grayscale, shape ``(height, width)``.

    Parameters
    ----------
    path : str or PathLike
        The image file.

    Returns
    -------
    ndarray of uint8, shape (height, width)
        Gray levels; colour images are converted by OpenCV (``IMREAD_GRAYSCALE``).

    Raises
    ------
    FileFormatError
        The file is missing or not an image OpenCV can decode.
    """
    import cv2  # heavy: only when an image is read

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise FileFormatError(path, "not an image OpenCV can decode")
    return np.asarray(image)
