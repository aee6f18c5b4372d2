"""Rasters and RPC models of the import tests (no ROS): the Ventoux crops, a synthetic scene."""

from __future__ import annotations

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
