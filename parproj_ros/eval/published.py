"""The published transforms of a StereoPair: image pixels to normalized pixels.

What a user of the outputs computes from the messages alone (scene frame, PTP roll, 2x3
normalization affine, output grid): ``parproj evaluate`` maps truth points through it,
:mod:`parproj_ros.eval.same_input` raw pixels.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..geometry.ptp import ptp_forward

FloatArray = NDArray[np.float64]


def normalized_px(
    params: Any,
    to_norm: Any,
    x_origin: float,
    y_origin: float,
    pixel: float,
    line: FloatArray,
    sample: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Image (line, sample) -> normalized (col, row), through the published transforms.

    These are a ParallelProjection message's scene frame and roll, a 2x3 normalization affine
    (6 numbers) and the output grid.
    """
    x = (np.asarray(line, dtype=float) - params.line_mid) * params.x_per_line
    y = (np.asarray(sample, dtype=float) - params.principal_point) * params.pixel_size
    yp = ptp_forward(y, params.principal_distance, params.roll_psi)
    h = np.asarray(to_norm, dtype=float).reshape(2, 3)
    xn = h[0, 0] * x + h[0, 1] * yp + h[0, 2]
    yn = h[1, 0] * x + h[1, 1] * yp + h[1, 2]
    return (xn - x_origin) / pixel, (yn - y_origin) / pixel
