"""Resampling scenes into the normalized (epipolar) geometry with OpenCV.

The map of an output pixel is exact: normalized pixel -> normalized metres -> inverse of the
scene's 2x3 normalization affine -> parallel scene coordinates (x, y') -> inverse PTP (Eq 7) ->
perspective y -> (line, sample) of the original scene. ``cv2.remap`` then interpolates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.epipolar import invert_affine_2x3
from ..geometry.navigation import SceneFrame
from ..geometry.ptp import ptp_inverse

FloatArray = NDArray[np.float64]

#: Supported pixel types (numpy dtype -> ROS encoding of a single-channel image).
ENCODINGS = {
    np.dtype(np.uint8): "mono8",
    np.dtype(np.uint16): "mono16",
    np.dtype(np.float32): "32FC1",
}


@dataclass(frozen=True)
class SceneGeometry:
    """What the resampler needs to know of one original scene.

    Attributes:
        frame: image (line, sample) <-> scene metres (x, perspective y).
        to_normalized: 2x3 affine, parallel scene metres (x, y') -> normalized metres.
        psi: roll for the PTP correction, radians.
        principal_distance: c, metres.
    """

    frame: SceneFrame
    to_normalized: FloatArray
    psi: float
    principal_distance: float

    def normalized_to_image(self, xn: FloatArray, yn: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Normalized metres -> (line, sample) in the original scene (exact)."""
        inv = invert_affine_2x3(self.to_normalized)
        x = inv[0, 0] * xn + inv[0, 1] * yn + inv[0, 2]
        yp = inv[1, 0] * xn + inv[1, 1] * yn + inv[1, 2]
        y = ptp_inverse(yp, self.principal_distance, self.psi)
        ls = self.frame.to_image(x, y)
        return ls[..., 0], ls[..., 1]

    def image_to_normalized(self, line: FloatArray, sample: FloatArray) -> FloatArray:
        """(line, sample) -> normalized metres (..., 2) (exact; PTP applied)."""
        from ..geometry.ptp import ptp_forward

        xy = self.frame.to_scene(line, sample)
        xy[..., 1] = ptp_forward(xy[..., 1], self.principal_distance, self.psi)
        h = self.to_normalized
        return np.asarray(xy @ h[:, :2].T + h[:, 2], dtype=float)


@dataclass(frozen=True)
class OutputGrid:
    """Normalized image grid: ``col = (x_n - x_origin) / pixel``, same for rows with y.

    Attributes:
        pixel: normalized metres per output pixel.
        x_origin: normalized x (metres) at the centre of output column 0.
        y_origin: normalized y (metres) at the centre of output row 0.
        width: columns.
        height: rows.
    """

    pixel: float
    x_origin: float
    y_origin: float
    width: int
    height: int


def footprint(geom: SceneGeometry, lines: int, detectors: int, samples: int = 16) -> FloatArray:
    """Normalized metres of the scene border (4 * samples points, (n, 2))."""
    t = np.linspace(0.0, 1.0, samples)
    ll = np.concatenate(
        [t * (lines - 1), np.full_like(t, lines - 1.0), (1 - t) * (lines - 1), np.zeros_like(t)]
    )
    ss = np.concatenate(
        [
            np.zeros_like(t),
            t * (detectors - 1),
            np.full_like(t, detectors - 1.0),
            (1 - t) * (detectors - 1),
        ]
    )
    return geom.image_to_normalized(ll, ss)


def native_pixel(geom: SceneGeometry) -> float:
    """Smallest normalized length of one original pixel step (line or sample), metres."""
    h = geom.to_normalized
    return float(
        min(
            np.linalg.norm(h[:, 0]) * abs(geom.frame.x_per_line),
            np.linalg.norm(h[:, 1]) * geom.frame.pixel_size,
        )
    )


def resample(
    image: NDArray[np.generic],
    geom: SceneGeometry,
    grid: OutputGrid,
    *,
    nodata: float = 0.0,
    interpolation: int = cv2.INTER_LINEAR,
    block_rows: int = 256,
) -> NDArray[np.generic]:
    """Resample one original scene (lines, detectors) onto ``grid``; outside the scene: nodata.

    Maps are built and applied in blocks of ``block_rows`` output rows to bound memory. The
    output dtype is the input's (uint8, uint16 or float32).
    """
    if image.dtype not in ENCODINGS:
        raise ValueError(f"unsupported pixel type {image.dtype}; use uint8, uint16 or float32")
    out = np.empty((grid.height, grid.width), dtype=image.dtype)
    cols = grid.x_origin + grid.pixel * np.arange(grid.width, dtype=float)
    for r0 in range(0, grid.height, block_rows):
        r1 = min(grid.height, r0 + block_rows)
        rows = grid.y_origin + grid.pixel * np.arange(r0, r1, dtype=float)
        xn, yn = np.meshgrid(cols, rows)
        line, sample = geom.normalized_to_image(xn, yn)
        out[r0:r1] = cv2.remap(
            image,
            sample.astype(np.float32),
            line.astype(np.float32),
            interpolation,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(nodata),
        )
    return out
