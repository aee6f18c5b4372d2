"""Digital elevation models: SRTM .hgt tiles, and lat/lon grids as height functions."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..rpc.model import HeightFunction

FloatArray = NDArray[np.float64]


def grid_height(
    heights: ArrayLike,
    *,
    lat_max: float,
    lon_min: float,
    step_deg: float,
    geoid_undulation: float = 0.0,
) -> HeightFunction:
    """A height function from a regular latitude/longitude grid (bilinear; NaN outside).

    Grid node (row i, column j) is at latitude ``lat_max - i * step_deg`` and longitude
    ``lon_min + j * step_deg`` (row 0 north; nodes are point samples, as in SRTM tiles, whose
    edge rows and columns lie on whole degrees).

    Args:
        heights: (rows, columns) heights, metres, at least 2 x 2.
        lat_max: latitude of row 0, degrees.
        lon_min: longitude of column 0, degrees.
        step_deg: node spacing in latitude and longitude, degrees.
        geoid_undulation: N added to every height, metres (geoid -> WGS84 ellipsoid).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape; NaN outside the grid.

    """
    data = np.array(heights, dtype=np.float64)
    if data.ndim != 2 or min(data.shape) < 2 or not np.all(np.isfinite(data)):
        raise ValueError(f"heights must be a finite 2-D grid of at least 2 x 2, got {data.shape}")
    if not step_deg > 0:
        raise ValueError(f"step_deg must be > 0, got {step_deg}")
    nr, nc = data.shape
    undulation = float(geoid_undulation)

    def height(lon: FloatArray, lat: FloatArray) -> FloatArray:
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        r = (lat_max - la) / step_deg
        c = (lo - lon_min) / step_deg
        with np.errstate(invalid="ignore"):
            inside = (r >= 0) & (r <= nr - 1) & (c >= 0) & (c <= nc - 1)
        rc = np.clip(np.nan_to_num(r), 0, nr - 1)
        cc = np.clip(np.nan_to_num(c), 0, nc - 1)
        i = np.minimum(rc.astype(np.intp), nr - 2)
        j = np.minimum(cc.astype(np.intp), nc - 2)
        tr, tc = rc - i, cc - j
        top = data[i, j] + tc * (data[i, j + 1] - data[i, j])
        bottom = data[i + 1, j] + tc * (data[i + 1, j + 1] - data[i + 1, j])
        h = top + tr * (bottom - top) + undulation
        return np.asarray(np.where(inside, h, np.nan), dtype=np.float64)

    return height


def srtm_height(
    path: str | Path,
    *,
    geoid_undulation: float = 0.0,
    tile_origin: tuple[float, float] | None = None,
) -> HeightFunction:
    """An SRTM ``.hgt`` tile as a height function (bilinear; NaN outside the tile).

    SRTM heights are above the EGM96 geoid. The RPC needs ellipsoidal heights: h = H + N. N (the
    geoid undulation, metres) is ignored unless supplied, as a constant: at Mont Ventoux it is
    about 50 m, and it varies by a few metres over a scene, which matters little for virtual GCP
    (they are spread over a height range anyway) but must be given for absolute heights.

    Args:
        path: 1201^2 (3") or 3601^2 (1") tile (voids filled by their nearest neighbour, see
            :func:`read_hgt`).
        geoid_undulation: N added to every height, metres.
        tile_origin: (lat, lon) of the SW corner, degrees (default: from the name N44E005).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape.

    """
    p = Path(path)
    lat_sw, lon_sw = tile_origin if tile_origin is not None else tile_origin_of(p)
    data = read_hgt(p)
    return grid_height(
        data,
        lat_max=lat_sw + 1.0,
        lon_min=lon_sw,
        step_deg=1.0 / (data.shape[0] - 1),
        geoid_undulation=geoid_undulation,
    )


def read_hgt(path: str | Path) -> FloatArray:
    """Read an SRTM ``.hgt`` tile with voids filled by their nearest valid neighbour.

    Args:
        path: a 1201 x 1201 (3 arc-second) or 3601 x 3601 (1 arc-second) tile of big-endian
            int16 heights above the geoid in metres, rows from north to south; -32768 = void.

    Returns:
        Heights, metres, float64 (n, n), row 0 the northern edge.

    Raises:
        ValueError: the file size is not that of either tile, or every sample is void.

    """
    from scipy.ndimage import distance_transform_edt

    raw = np.fromfile(Path(path), dtype=">i2")
    for n in (1201, 3601):
        if raw.size == n * n:
            break
    else:
        raise ValueError(f"{path}: {raw.size * 2} bytes is neither a 1201^2 nor 3601^2 SRTM tile")
    data = raw.reshape(n, n).astype(np.float64)
    void = raw.reshape(n, n) == -32768
    if void.all():
        raise ValueError(f"{path}: every sample is void")
    if void.any():
        idx = distance_transform_edt(void, return_distances=False, return_indices=True)
        data = data[idx[0], idx[1]]
    return data


def tile_origin_of(path: Path) -> tuple[int, int]:
    """(lat, lon) of an SRTM tile's south-west corner, degrees, from its name (N44E005.hgt)."""
    m = re.fullmatch(r"([NS])(\d{1,2})([EW])(\d{1,3})", path.stem.upper())
    if m is None:
        raise ValueError(
            f"{path.name}: cannot read the tile's SW corner from the name (expected e.g. "
            "N44E005.hgt); pass tile_origin=(lat, lon)"
        )
    lat = int(m.group(2)) * (1 if m.group(1) == "N" else -1)
    lon = int(m.group(4)) * (1 if m.group(3) == "E" else -1)
    return lat, lon
