"""Rational polynomial (RPC) sensor models: formats, ground <-> image, virtual GCP (paper 2).

Modules: :mod:`.model` (the model), :mod:`.formats` (files: one module per format, one table),
:mod:`.virtual` (virtual GCP); ground frames in :mod:`parproj_ros.geometry.geodesy`, DEMs in
:mod:`parproj_ros.io.dem`.

An RPC (NITF RPC00B) maps ground (longitude, latitude in degrees on the WGS84 ellipsoid, height in
metres above the WGS84 ellipsoid) to image (line, sample) as ratios of cubic polynomials of the
normalized coordinates ``L = (lon - long_off) / long_scale``, ``P = (lat - lat_off) / lat_scale``,
``H = (h - height_off) / height_scale``::

    line   = line_scale * num_l(L, P, H) / den_l(L, P, H) + line_off
    sample = samp_scale * num_s(L, P, H) / den_s(L, P, H) + samp_off

with the 20 terms in RPC00B order (:data:`RPC00B_TERMS`).

Pixel convention of this project: continuous image coordinates, pixel centres at integers,
(0, 0) = centre of the first pixel (first line, first sample). Per format, as found in the file
and converted on reading (every model held by :class:`RPCModel` is in this convention):

* NITF RPC00B, ``_RPC.TXT``, ``.RPB``: (0, 0) = centre of the first pixel; no conversion.
* GeoTIFF RPCCoefficientTag (50844): GDAL copies its RPC metadata (RPC00B convention) into the
  tag unchanged; no conversion.
* OSSIM ``.geom`` keyword list: 0-based, pixel centres at integers; no conversion.
* DIMAP v2 (Pleiades 1A/1B, SPOT 6/7) ``RPC_*.XML``: (1, 1) = centre of the first pixel;
  ``line_off - 1``, ``samp_off - 1``.
* DIMAP v3 (Pleiades Neo): origin given by ``FIRST_COL`` of ``ImagetoGround_Validity_Domain``
  (0 for PNEO); ``- FIRST_COL``.

Evidence for DIMAP v2: the DIMAP XML and the OSSIM .geom of the same Pleiades scene (Mont
Ventoux, tests/data/ventoux) carry identical coefficients, but LINE_OFF / SAMP_OFF of the XML are
21110.5 / 19208.5 and those of the .geom 21109.5 / 19207.5; projections through the two differ by
exactly (1, 1) px (tests/rpc/test_rpc.py). GDAL's Pleiades reader makes the same correction (centre
of the upper-left pixel is (1, 1) in DIMAP v2, FIRST_COL of the validity domain since DIMAP v3),
and the RPC00B offsets refer to pixel centres (GDAL issue 3946).

Validity domain: an RPC declares where it was fitted (normalized |L|, |P|, |H|, |line|, |sample|
<= 1.1). That is advice, not a limit: the formula is evaluated wherever asked, as GDAL's RPC
transformer, rpcm and s2p do. Many distributed crops keep the parent scene's LINE_OFF / SAMP_OFF
with scales fitted to the crop, so that every pixel lies tens of scale units outside the declared
domain while the model is exact there. :meth:`RPCModel.project` and :meth:`RPCModel.localize`
therefore evaluate everywhere by default (``domain="advice"``); ``domain="limit"`` restores the
hard limit (used by :func:`virtual_gcp`, the paper-2 experiment). What is really wrong is refused
by the importer (parproj_ros/io/scene_import.py): non-finite coefficients, a localization that does
not converge, a denominator crossing zero over the image (:meth:`RPCModel.denominator_check`,
:meth:`RPCModel.image_denominator_check`, which also says where).

Ground frames: :func:`ecef_from_geodetic` / :func:`geodetic_from_ecef` (WGS84) and
:class:`LocalTangentPlane` (east, north, up, metres) give the local Cartesian object frame of the
parallel projection model (Z up). Heights are always ellipsoidal here; SRTM heights are above the
geoid (EGM96): :func:`srtm_height` adds a geoid undulation only if one is supplied (it is about
50 m in the western Alps and Provence, so ignoring it shifts every virtual point by that much in
height, which a parallel projection fit absorbs almost entirely).
"""

from __future__ import annotations

from ..geometry.geodesy import LocalTangentPlane, ecef_from_geodetic, geodetic_from_ecef
from .formats import (
    FORMATS,
    RPCFormat,
    RPCFormatSpec,
    detect_rpc_format,
    dimap_pixel_origin,
    read_dimap_rpc,
    read_geom,
    read_geotiff_rpc,
    read_keyword_list,
    read_rpb,
    read_rpc,
    read_rpc_file,
    read_rpc_txt,
    write_dimap_rpc,
    write_geom,
    write_geotiff_rpc,
    write_rpb,
    write_rpc,
    write_rpc_txt,
)
from .model import (
    DOMAIN_LIMIT,
    RPC00B_TERMS,
    RPC_TIFF_TAG,
    Domain,
    HeightFunction,
    Outside,
    RPCConvergenceError,
    RPCDomainError,
    RPCError,
    RPCFormatError,
    RPCModel,
)
from .virtual import VirtualGCP, estimate_scene, virtual_gcp

__all__ = [
    "DOMAIN_LIMIT",
    "FORMATS",
    "RPC00B_TERMS",
    "RPC_TIFF_TAG",
    "Domain",
    "HeightFunction",
    "LocalTangentPlane",
    "Outside",
    "RPCConvergenceError",
    "RPCDomainError",
    "RPCError",
    "RPCFormat",
    "RPCFormatError",
    "RPCFormatSpec",
    "RPCModel",
    "VirtualGCP",
    "detect_rpc_format",
    "dimap_pixel_origin",
    "ecef_from_geodetic",
    "estimate_scene",
    "geodetic_from_ecef",
    "read_dimap_rpc",
    "read_geom",
    "read_geotiff_rpc",
    "read_keyword_list",
    "read_rpb",
    "read_rpc",
    "read_rpc_file",
    "read_rpc_txt",
    "virtual_gcp",
    "write_dimap_rpc",
    "write_geom",
    "write_geotiff_rpc",
    "write_rpb",
    "write_rpc",
    "write_rpc_txt",
]
