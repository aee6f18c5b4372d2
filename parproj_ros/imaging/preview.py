"""Preview images a person looks at: the red-cyan anaglyph of a normalized pair."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .matching import to_uint8

__all__ = ["anaglyph", "to_uint8"]


def anaglyph(
    left: NDArray[np.generic], right: NDArray[np.generic], nodata: float = 0.0
) -> NDArray[np.uint8]:
    """Red = left, green and blue = right; (rows, cols, 3) uint8 (rgb8)."""
    lv, rv = to_uint8(left, nodata), to_uint8(right, nodata)
    return np.stack([lv, rv, rv], axis=-1)
