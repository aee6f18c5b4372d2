"""Rasters and RPC models of the import tests (no ROS): the Ventoux crops, a synthetic scene."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from rasterio.rpc import RPC

from parproj_ros import rpc
from parproj_ros.rpc import RPCModel

from .paths import DATA

NAMES = ("left", "right")
#: Crop origins (line, sample) of the Ventoux crops in their full scenes (data README).
ORIGINS = ((5000.0, 5000.0), (5162.0, 4915.0))
FLAT_H = 500.0  # m, the synthetic ground


def to_rasterio(m: RPCModel) -> RPC:
    """Our model as rasterio's RPC (same RPC00B pixel convention)."""
    return RPC(
        height_off=m.height_off,
        height_scale=m.height_scale,
        lat_off=m.lat_off,
        lat_scale=m.lat_scale,
        line_den_coeff=list(m.line_den_coeff),
        line_num_coeff=list(m.line_num_coeff),
        line_off=m.line_off,
        line_scale=m.line_scale,
        long_off=m.long_off,
        long_scale=m.long_scale,
        samp_den_coeff=list(m.samp_den_coeff),
        samp_num_coeff=list(m.samp_num_coeff),
        samp_off=m.samp_off,
        samp_scale=m.samp_scale,
        err_bias=m.err_bias,
        err_rand=m.err_rand,
    )


def crop_rpcs() -> list[RPCModel]:
    """The RPC of each crop in its own grid (full-scene .geom shifted by the crop origin)."""
    fulls = [rpc.read_rpc(DATA / f"{n}_image.geom") for n in NAMES]
    return [f.shifted(-o[0], -o[1]) for f, o in zip(fulls, ORIGINS, strict=True)]


def pixels(name: str) -> np.ndarray:
    with rasterio.open(DATA / f"{name}_image.tif") as src:
        return np.asarray(src.read(1))


def write(path: Path, img: np.ndarray, model: RPCModel | None, **opts: Any) -> None:
    """A raster (driver from the extension) with the RPC as GDAL writes it."""
    driver = {".tif": "GTiff", ".jp2": "JP2OpenJPEG", ".png": "PNG"}[path.suffix]
    extra: dict[str, Any] = {} if model is None else {"rpcs": to_rasterio(model)}
    with rasterio.open(
        path,
        "w",
        driver=driver,
        width=img.shape[1],
        height=img.shape[0],
        count=1,
        dtype=str(img.dtype),
        **extra,
        **opts,
    ) as dst:
        dst.write(img, 1)


def affine_rpc(look: float) -> RPCModel:
    """A nearly affine RPC of a full 4000 x 4000 px scene; ``look``: line shift per unit H."""
    line_num = np.zeros(20)
    samp_num = np.zeros(20)
    den = np.zeros(20)
    den[0] = 1.0
    line_num[[2, 3, 4]] = (-1.0, look, 2e-4)  # P, H, LP (a little curvature)
    samp_num[[1, 2, 3, 7]] = (1.0, 0.02, 0.01, -1e-4)  # L, P, H, LL
    return RPCModel(
        line_off=2000.0,
        samp_off=2000.0,
        lat_off=44.2,
        long_off=5.2,
        height_off=FLAT_H,
        line_scale=2000.0,
        samp_scale=2000.0,
        lat_scale=0.018,
        long_scale=0.025,
        height_scale=500.0,
        line_num_coeff=line_num,
        line_den_coeff=den,
        samp_num_coeff=samp_num,
        samp_den_coeff=den,
    )


def render_crop(full: RPCModel, crop: tuple[int, int, int, int]) -> np.ndarray:
    """uint16 image of a textured flat ground (h = FLAT_H) seen by a crop of ``full``."""
    l0, s0, nl, ns = crop
    gl, gs = np.meshgrid(np.arange(nl) + l0, np.arange(ns) + s0, indexing="ij")
    lon, lat = full.localize(gl, gs, np.full(gl.shape, FLAT_H))
    # ground texture: smooth noise on a 1 m lattice of a 3 km square (same in both views)
    rng = np.random.default_rng(7)
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (3000, 3000)).astype(np.float32), (0, 0), 2.0)
    x = ((lon - 5.2) * 111_320 * np.cos(np.radians(44.2)) + 1500).astype(np.float32)
    y = ((lat - 44.2) * 110_540 + 1500).astype(np.float32)
    img = cv2.remap(tex, x, y, cv2.INTER_LINEAR)
    img = (img - img.min()) / (img.max() - img.min())
    return (200 + 3000 * img).astype(np.uint16)


#: The SRTM 3" crop of tests/data/ventoux (heights above EGM96): its file, the latitude of row 0
#: and longitude of column 0 (node centres) and the spacing, degrees (the file's header).
SRTM_CROP = DATA / "srtm_N44E005_crop.txt"
SRTM_LAT0, SRTM_LON0, SRTM_STEP = 45 - 927 / 1200, 5 + 206 / 1200, 1 / 1200


def srtm_crop_geotiff(path: Path, *, shift_lon_deg: float = 0.0) -> Path:
    """The SRTM crop as a GeoTIFF (EPSG:4326, int16 as the tile, nodata -32768).

    Its nodes are cell centres (GDAL's convention for an ``.hgt``): the same surface as
    ``grid_height`` of the crop. ``shift_lon_deg``: the same heights that many degrees east (a
    DEM of another place).
    """
    from rasterio.transform import from_origin

    data = np.loadtxt(SRTM_CROP).astype(np.int16)
    west = SRTM_LON0 + shift_lon_deg - SRTM_STEP / 2
    north = SRTM_LAT0 + SRTM_STEP / 2
    profile = {
        "driver": "GTiff",
        "width": data.shape[1],
        "height": data.shape[0],
        "count": 1,
        "dtype": "int16",
        "crs": "EPSG:4326",
        "transform": from_origin(west, north, SRTM_STEP, SRTM_STEP),
        "nodata": -32768,
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    return path


def srtm_crop_z(frame_id: str, x: Any, y: Any, undulation: float = 50.0) -> Any:
    """The SRTM crop's heights + ``undulation`` as object Z of the plane ``frame_id`` at (X, Y).

    Through the crop's own reader (``grid_height``, not the GeoTIFF) and the plane's curvature
    (``core.dem_terrain.surface_z``); NaN outside the crop.
    """
    from parproj_ros.core.dem_terrain import surface_z
    from parproj_ros.core.frames import frame_from_id
    from parproj_ros.io.dem import grid_height

    ref = grid_height(
        np.loadtxt(SRTM_CROP),
        lat_max=SRTM_LAT0,
        lon_min=SRTM_LON0,
        step_deg=SRTM_STEP,
        geoid_undulation=undulation,
    )
    return surface_z(frame_from_id(frame_id), ref, x, y, 0.0)  # type: ignore[arg-type]


def pair_ground_slack(side_m: float = 250.0) -> float:
    """How far a DEM span sampled on the pair-ground grid may miss a span over the same ground.

    The grid's node spacing (``side_m``, a Ventoux crop: 500 px of 0.5 m, over
    ``FOOTPRINT_GRID - 1`` steps, diagonal) times the crop's steepest slope (metres).
    """
    import math

    from parproj_ros.core.dem_terrain import FOOTPRINT_GRID

    h = np.loadtxt(SRTM_CROP)
    dy = SRTM_STEP * math.pi / 180 * 6.371e6
    dx = dy * math.cos(math.radians(SRTM_LAT0))
    slope = float(np.hypot(*np.gradient(h, dy, dx)).max())
    return slope * side_m / (FOOTPRINT_GRID - 1) * math.sqrt(2.0)


def terrain_geotiff(path: Path, surface: Any, frame_id: str, half_m: float, step_m: float) -> Path:
    """A simulated terrain as a DEM: a GeoTIFF (EPSG:4326, float32, ellipsoidal heights).

    ``surface(x, y)``: the terrain's Z in the tangent plane ``frame_id`` over the square
    ``|x|, |y| <= half_m`` (metres). Each node at (lon, lat) holds the ellipsoidal height whose
    point lies on the surface (6 fixed-point steps: the plane's curvature, micrometres here);
    nodes about ``step_m`` apart. Sampled bilinearly, it gives the surface within the
    interpolation's error (its slope times a node spacing, at most).
    """
    from rasterio.transform import from_origin

    from parproj_ros.core.frames import tangent_plane

    plane = tangent_plane(frame_id)
    assert plane is not None, frame_id
    xs = np.array([-half_m, half_m, -half_m, half_m])
    ys = np.array([-half_m, -half_m, half_m, half_m])
    lon, lat, _ = plane.to_geodetic(xs, ys, np.zeros(4))
    dlat = step_m / 111_320.0
    dlon = dlat / math.cos(math.radians(float(np.mean(lat))))
    west, east = float(lon.min()) + dlon, float(lon.max()) - dlon
    south, north = float(lat.min()) + dlat, float(lat.max()) - dlat
    cols, rows = int((east - west) / dlon) + 1, int((north - south) / dlat) + 1
    glon, glat = np.meshgrid(west + dlon * np.arange(cols), north - dlat * np.arange(rows))
    h = np.full(glon.shape, plane.h0)
    for _ in range(6):
        x, y, z = plane.to_local(glon, glat, h)
        h = h + (surface(x, y) - z)
    profile = {
        "driver": "GTiff",
        "width": cols,
        "height": rows,
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:4326",
        "transform": from_origin(west - dlon / 2, north + dlat / 2, dlon, dlat),
        "nodata": float("nan"),
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(h.astype(np.float32), 1)
    return path
