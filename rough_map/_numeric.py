"""Small numeric helpers shared by the layers, for arrays met once per frame or per cell."""

from __future__ import annotations

import numpy as np

__all__ = ["median"]


def median(values: np.ndarray) -> float:
    """The median of a non-empty 1-D array: ``np.median``'s value (the mean of the two
    middle values of an even count), without its overhead, which is several times the work
    on the few thousand values of a frame."""
    n = values.size
    k = n // 2
    if n % 2:
        return float(np.partition(values, k)[k])
    part = np.partition(values, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2)
