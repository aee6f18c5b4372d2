"""DSM accuracy and the pictures a person looks at: hillshade, disparity, height error map.

The DSM of a pair (an ElevationGrid message) against the true surface: a simulated bag's
terrain (the scenario that made it, rebuilt from its seed: :func:`scenario_terrain`), or a DEM
for a real pair (coarse: the SRTM tile's 1" or 3" posts smooth every feature smaller than about
90 m, so its differences are an upper bound of the DSM's own error, not a measure of it).

Figures (:func:`dsm_accuracy`): error e = DSM - truth over the measured cells (filled cells
aside), its RMS, bias and NMAD = 1.4826 median |e - median e| (robust to blunders), and the
completeness: cells with a height over the cells of the DSM's footprint (the convex hull of its
cells with a height: the outside of the imaged area is not a hole), with and without the
filled cells.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..imaging.heights import DsmGrid, dsm_errors

FloatArray = NDArray[np.float64]
#: A true surface: object (X, Y) metres -> Z metres (NaN where unknown).
Surface = Callable[[FloatArray, FloatArray], FloatArray]


def disparities_by_stamp(reader: Any) -> dict[int, NDArray[np.float32]]:
    """The ``disparity`` maps of an output bag by stamp (ns), invalid pixels NaN.

    ``reader``: a :class:`~parproj_ros.ros.bag.BagReader`. A DisparityImage marks an invalid
    pixel with a value below its ``min_disparity``.
    """
    from ..ros.conversions import image_to_array, stamp_to_ns

    out: dict[int, NDArray[np.float32]] = {}
    if contract.DISPARITY not in reader.topics():
        return out
    for item in reader.messages(topics=[contract.DISPARITY]):
        d = image_to_array(item.msg.image).astype(np.float32)
        d[d < item.msg.min_disparity] = np.nan
        out[stamp_to_ns(item.msg.header.stamp)] = d
    return out


def footprint(heights: NDArray[np.floating[Any]]) -> NDArray[np.bool_]:
    """Cells inside the convex hull of the cells with a height (the imaged area)."""
    valid = np.isfinite(heights)
    out = np.zeros(heights.shape, dtype=np.uint8)
    if valid.sum() < 3:
        return np.asarray(valid, dtype=bool)
    rows, cols = np.nonzero(valid)
    hull = cv2.convexHull(np.stack([cols, rows], axis=1).astype(np.int32))
    cv2.fillConvexPoly(out, hull, 1)
    return np.asarray(out.astype(bool) | valid, dtype=bool)


def dsm_accuracy(
    heights: NDArray[np.floating[Any]],
    grid: DsmGrid,
    truth: Surface,
    filled: NDArray[np.bool_] | None = None,
) -> dict[str, float]:
    """Height errors and completeness of a DSM against a true surface (module docstring).

    Args:
        heights: (rows, cols) metres, NaN for holes.
        grid: where the cells are.
        truth: the true Z at object (X, Y).
        filled: True for cells filled from a neighbour (left out of the error figures);
            inferred as none when not given.

    Returns:
        ``rms``, ``nmad``, ``mean`` (bias), metres, ``n`` (cells compared), ``completeness``
        (measured and filled cells / footprint cells), ``completeness_measured`` (measured
        cells only), ``cells`` (footprint cells).
    """
    h = np.asarray(heights, dtype=float)
    x, y = grid.centres()
    z = np.asarray(truth(x, y), dtype=float)
    fill = np.zeros(h.shape, dtype=bool) if filled is None else np.asarray(filled, dtype=bool)
    inside = footprint(h)
    measured = np.where(fill, np.nan, h)
    err = dsm_errors(measured, z, inside)
    cells = int(inside.sum())
    has = np.isfinite(h) & inside
    err["completeness"] = float(has.sum() / cells) if cells else 0.0
    err["completeness_measured"] = float((has & ~fill).sum() / cells) if cells else 0.0
    err["cells"] = float(cells)
    return err


def scenario_terrain(name: str) -> Surface | None:
    """The true surface of a simulated bag made by scenario ``name`` (None if unknown)."""
    from ..sim.scenarios import SCENARIOS
    from ..sim.terrain import procedural_terrain

    make = SCENARIOS.get(name)
    if make is None:
        return None
    scn = make()
    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    return terrain.height


def enu_dem_surface(frame_id: str, dem: Callable[[FloatArray, FloatArray], FloatArray]) -> Surface:
    """A DEM of ellipsoidal heights as a surface in a tangent-plane frame (``enu_wgs84:...``).

    The plane's Z of a ground point is not its ellipsoidal height (the Earth curves away from
    the plane): each (X, Y) is iterated to the point on the DEM that the plane's vertical
    through it meets (three fixed-point steps: centimetres over a scene).
    """
    from ..io.scene_import import frame_from_id

    ltp = frame_from_id(frame_id)

    def surface(x: FloatArray, y: FloatArray) -> FloatArray:
        z = np.zeros(np.shape(x))
        for _ in range(3):
            lon, lat, _h = ltp.to_geodetic(x, y, z)
            h = dem(np.asarray(lon), np.asarray(lat))
            _x, _y, zz = ltp.to_local(lon, lat, h)  # (_x, _y) within cm of (x, y)
            z = np.asarray(zz, dtype=float)
        return z

    return surface


def hillshade(
    heights: NDArray[np.floating[Any]],
    cell: float,
    *,
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> NDArray[np.uint8]:
    """Shaded relief of a north-up DSM (sun from ``azimuth_deg``, clockwise from north), 0-255.

    Holes are 0 (black). Along an axis of a single cell the slope is taken as 0 (a DSM of one
    row or column has no gradient across it).
    """
    z = np.asarray(heights, dtype=float)
    valid = np.isfinite(z)
    zf = np.where(valid, z, np.nanmean(z) if valid.any() else 0.0)
    # rows go south: dZ/dnorth = -dzdy
    dzdy = np.gradient(zf, cell, axis=0) if zf.shape[0] > 1 else np.zeros_like(zf)
    dzdx = np.gradient(zf, cell, axis=1) if zf.shape[1] > 1 else np.zeros_like(zf)
    slope = np.arctan(np.hypot(dzdx, dzdy))
    aspect = np.arctan2(-dzdx, dzdy)
    az = math.radians(360.0 - azimuth_deg + 90.0)
    alt = math.radians(altitude_deg)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    out = np.clip(255 * shade, 0, 255).astype(np.uint8)
    out[~valid] = 0
    return np.asarray(out, dtype=np.uint8)


def save_height_plots(
    folder: Path,
    name: str,
    heights: NDArray[np.floating[Any]],
    grid: DsmGrid,
    *,
    disparity: NDArray[np.floating[Any]] | None = None,
    truth: Surface | None = None,
    ortho: NDArray[Any] | None = None,
) -> list[Path]:
    """PNGs of a pair's heights: hillshade, disparity, height error map, ortho-image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    ext = (
        grid.x0 - grid.cell / 2,
        grid.x0 + (grid.width - 0.5) * grid.cell,
        grid.y0 - (grid.height - 0.5) * grid.cell,
        grid.y0 + grid.cell / 2,
    )

    def save(fig: Any, stem: str) -> None:
        path = folder / f"{name}_{stem}.png"
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        written.append(path)

    fig, ax = plt.subplots(figsize=(7, 6))
    ax.imshow(hillshade(heights, grid.cell), cmap="gray", extent=ext)
    im = ax.imshow(heights, cmap="terrain", alpha=0.35, extent=ext)
    fig.colorbar(im, ax=ax, label="height Z, m")
    ax.set(title=f"DSM {name} (hillshade)", xlabel="X, m", ylabel="Y, m")
    save(fig, "dsm_hillshade")
    if disparity is not None:
        fig, ax = plt.subplots(figsize=(7, 6))
        im = ax.imshow(disparity, cmap="viridis")
        fig.colorbar(im, ax=ax, label="disparity col_left - col_right, px")
        ax.set(title=f"disparity {name} (left normalized grid)", xlabel="col", ylabel="row")
        save(fig, "disparity")
    if truth is not None:
        x, y = grid.centres()
        err = np.asarray(heights, dtype=float) - truth(x, y)
        lim = float(np.nanpercentile(np.abs(err), 99)) if np.isfinite(err).any() else 1.0
        fig, ax = plt.subplots(figsize=(7, 6))
        im = ax.imshow(err, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=ext)
        fig.colorbar(im, ax=ax, label="DSM - truth, m")
        ax.set(title=f"height error {name}", xlabel="X, m", ylabel="Y, m")
        save(fig, "height_error")
    if ortho is not None:
        fig, ax = plt.subplots(figsize=(7, 6))
        ax.imshow(ortho, cmap="gray", extent=ext)
        ax.set(title=f"ortho-image {name}", xlabel="X, m", ylabel="Y, m")
        save(fig, "ortho")
    return written
