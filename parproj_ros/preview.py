"""Preview images a person looks at: the red-cyan anaglyph of a normalized pair."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def to_uint8(img: NDArray[np.generic], nodata: float = 0.0) -> NDArray[np.uint8]:
    """Stretch to 0..255 between the 1st and 99th percentiles of valid (non-nodata) pixels."""
    a = np.asarray(img, dtype=np.float32)
    valid = np.isfinite(a) & (a != nodata)
    if not valid.any():
        return np.zeros(a.shape, dtype=np.uint8)
    sub = a[valid][:: max(1, int(valid.sum() // 200_000))]
    lo, hi = np.percentile(sub, [1.0, 99.0])
    scale = 255.0 / max(float(hi - lo), 1e-12)
    out = np.clip(np.nan_to_num((a - lo) * scale), 0, 255).astype(np.uint8)
    out[~valid] = 0
    return out


def anaglyph(
    left: NDArray[np.generic], right: NDArray[np.generic], nodata: float = 0.0
) -> NDArray[np.uint8]:
    """Red = left, green and blue = right; (rows, cols, 3) uint8 (rgb8)."""
    lv, rv = to_uint8(left, nodata), to_uint8(right, nodata)
    return np.stack([lv, rv, rv], axis=-1)
