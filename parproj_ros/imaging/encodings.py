"""Pixel encodings: sensor_msgs/Image encoding names <-> numpy pixel types (one table).

Single-channel scan lines and normalized images; the anaglyph (``rgb8``) is built apart.
"""

from __future__ import annotations

import numpy as np

#: Every single-channel encoding read: name -> numpy pixel type.
ENCODING_DTYPES: dict[str, np.dtype] = {
    "mono8": np.dtype(np.uint8),
    "8UC1": np.dtype(np.uint8),
    "mono16": np.dtype(np.uint16),
    "16UC1": np.dtype(np.uint16),
    "32FC1": np.dtype(np.float32),
}

#: The encoding written for each supported pixel type (the pixel types the pipeline handles).
DTYPE_ENCODINGS: dict[np.dtype, str] = {
    np.dtype(np.uint8): "mono8",
    np.dtype(np.uint16): "mono16",
    np.dtype(np.float32): "32FC1",
}

__all__ = ["DTYPE_ENCODINGS", "ENCODING_DTYPES"]
