"""A DSM against a reference DSM, scored as the Marseille data's README scores s2p and CARS.

``python -m parproj_ros.eval.dsm_compare OURS REFERENCE [--images IMG ...] [--json]``

Method (../shared/data/marseille_triplet/README.md, "Agreement between the references"):

1. **One grid.** Both DSMs are sampled on the grid of the reference (or a grid given): the
   reference bilinearly, nodata kept out (:func:`~parproj_ros.imaging.fusion.sample_bilinear`:
   the valid neighbours' weights renormalized; empty when they weigh less than half). On a
   grid of the same lattice (the Marseille references share one: their corners differ by whole
   0.5 m cells) this is the identity.
2. **Our DSM** comes either as a georeferenced GeoTIFF (read like a reference), or as the
   ``dsm`` ElevationGrid of an output bag in its local tangent-plane frame
   (``enu_wgs84:lat=..,lon=..,h=..``, :mod:`parproj_ros.geometry.geodesy`; Z is the height
   above that plane, not above the ellipsoid). Then each grid cell's centre (E, N) is taken to
   (lon, lat), and the ellipsoidal height h of our surface on the ellipsoid normal through it
   is found by fixed-point iteration: (lon, lat, h) -> (x, y, z) in the frame; h += Z(x, y) - z
   with Z sampled bilinearly in our grid (the horizontal position moves by about d / R =
   1e-4 m per metre of h at 600 m from the origin; three rounds reach 1e-6 m). This is the
   exact conversion :mod:`parproj_ros.io.geotiff` writes, so no CRS in our file is needed.
3. **Footprint.** With the images given: the cells whose ground point (at the cell's median
   height over the DSMs compared, or the median of all their heights where none has one)
   projects inside every image through its RPC (crop origin applied as ``parproj import``
   does; inside = within the pixel area, -0.5 .. size - 0.5 in this project's pixel-centre
   convention). This reproduces the README's footprint of img_01 + img_02: 1,017,122 cells
   against its 1,017,090 with the six references. Without images: the cells where the
   reference has a height (a simpler footprint: completeness is then the share of the
   reference's cells where ours has a height too, which favours neither DSM's holes).
4. **Statistics** of d = ours - reference over the footprint cells valid in both: median
   (bias), NMAD = 1.4826 median |d - median d|, RMS, 95th percentile of |d|, metres; and the
   completeness of each (share of footprint cells with a height). Besides, the horizontal
   shift of ours against the reference (:func:`horizontal_shift`: d regressed on the
   reference's slopes), metres east and north.

Heights of a GeoTIFF are taken as WGS84 ellipsoidal heights (the references' tags and our
export say so); one whose tags name a geoid is refused unless its undulation is given.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..imaging.fusion import sample_bilinear
from ..imaging.heights import DsmGrid

if TYPE_CHECKING:
    from pyproj import CRS

__all__ = [
    "Comparison",
    "FrameDsm",
    "MapDsm",
    "compare",
    "difference_stats",
    "footprint",
    "frame_dsms_from_bag",
    "horizontal_shift",
    "import_bag_frame",
    "load_ours",
    "read_geotiff_dsm",
    "to_map_grid",
]

FloatArray = NDArray[np.float64]
Float32Array = NDArray[np.float32]
BoolArray = NDArray[np.bool_]

#: Fixed-point rounds for the ellipsoidal height of our surface at a map cell, and the step (m)
#: that ends them early.
MAX_ROUNDS = 8
HEIGHT_TOL_M = 1e-6
#: Largest horizontal shift :func:`horizontal_shift` reports, cells (its first-order fit holds
#: for a few cells; beyond, e.g. a DSM against a 90 m DEM, it reports none).
MAX_SHIFT_CELLS = 4.0
#: Rows of the map grid converted at once (bounds the working memory).
BLOCK_ROWS = 512


@dataclass(frozen=True)
class MapDsm:
    """A DSM on a north-up grid of a map CRS (a GeoTIFF).

    Attributes:
        heights: float32 (grid.height, grid.width), WGS84 ellipsoidal heights, metres; NaN
            where there is none.
        grid: the cells, in map metres (x0 = easting, y0 = northing of the first cell's centre).
        crs: the map CRS (pyproj).
        name: what to call it in reports.
    """

    heights: Float32Array
    grid: DsmGrid
    crs: CRS
    name: str


@dataclass(frozen=True)
class FrameDsm:
    """A DSM in a local tangent-plane object frame (an ElevationGrid of an output bag).

    Attributes:
        heights: float32 (grid.height, grid.width), Z metres in the frame, NaN holes.
        grid: the cells, in frame metres.
        frame_id: ``enu_wgs84:lat=..,lon=..,h=..``.
        name: what to call it (the pair id).
    """

    heights: Float32Array
    grid: DsmGrid
    frame_id: str
    name: str


def read_geotiff_dsm(
    path: str | Path, *, name: str | None = None, geoid_undulation_m: float | None = None
) -> MapDsm:
    """A DSM GeoTIFF (band 1) with its map grid; nodata as NaN.

    Args:
        path: the GeoTIFF.
        name: its name in reports (default: the file stem).
        geoid_undulation_m: added to every height of a file whose tags say its heights are
            above a geoid (EGM96 ...); required for such a file.

    Raises:
        ValueError: no CRS (a DSM of a frame without geodetic anchor: compare the output bag
            instead), a rotated or non-square grid, or geoid heights without an undulation.
    """
    import rasterio

    p = Path(path)
    with rasterio.open(p) as src:
        if src.crs is None:
            raise ValueError(
                f"{p}: no CRS: cannot place it on the reference (give the output bag, whose "
                "ElevationGrid carries its frame, instead)"
            )
        t = src.transform
        if t.b != 0 or t.d != 0 or t.e >= 0 or not math.isclose(t.a, -t.e, rel_tol=1e-9):
            raise ValueError(f"{p}: not a north-up grid of square cells ({tuple(t)[:6]})")
        z = src.read(1).astype(np.float32)
        nodata = src.nodata
        tags = {**src.tags(), **src.tags(1)}
        from pyproj import CRS as _CRS

        crs = _CRS.from_wkt(src.crs.to_wkt())
    if nodata is not None and not math.isnan(nodata):
        z[z == np.float32(nodata)] = np.nan
    datum = " ".join(str(v) for k, v in tags.items() if "DATUM" in k.upper() or k == "HEIGHT")
    if any(w in datum.lower() for w in ("geoid", "egm")):
        if geoid_undulation_m is None:
            raise ValueError(
                f"{p}: heights above a geoid ({datum}): give the geoid undulation to add"
            )
        z = z + np.float32(geoid_undulation_m)
    cell = float(t.a)
    grid = DsmGrid(t.c + 0.5 * cell, t.f - 0.5 * cell, cell, int(z.shape[1]), int(z.shape[0]))
    return MapDsm(z, grid, crs, name or p.stem)


def import_bag_frame(path: str | Path) -> str | None:
    """The object frame an imported bag's GCP are in (``enu_wgs84:...``), or None without GCP."""
    from ..ros.bag import BagReader

    reader = BagReader(Path(path))
    if contract.GCP not in reader.topics():
        return None
    for item in reader.messages(topics=[contract.GCP]):
        return str(item.msg.header.frame_id)
    return None


def frame_dsms_from_bag(
    path: str | Path, *, frame_id: str | None = None, topic: str = contract.DSM
) -> list[FrameDsm]:
    """Every ElevationGrid of an output bag's ``dsm`` topic (``parproj process --heights``).

    Args:
        path: the output bag folder.
        frame_id: the frame to take for a DSM labelled with a frame that is not a tangent
            plane (``parproj process`` labelled every output ``map`` before the frame
            travelled through it: give the import bag's, :func:`import_bag_frame`).
        topic: the topic read (``dsm_fused``: the pipeline's fused DSMs).

    Raises:
        BagError: the bag has no such topic.
    """
    from ..io.geotiff import frame_of
    from ..ros.bag import BagError, BagReader
    from ..ros.conversions import elevation_grid_from_msg

    reader = BagReader(Path(path))
    if topic not in reader.topics():
        raise BagError(f"no {topic} topic: process the bag with --heights", Path(path))
    out: list[FrameDsm] = []
    for item in reader.messages(topics=[topic]):
        m = item.msg
        heights, grid, _ = elevation_grid_from_msg(m)
        frame = str(m.header.frame_id)
        if frame_id is not None and frame_of(frame) is None:
            frame = frame_id
        out.append(
            FrameDsm(
                np.asarray(heights, dtype=np.float32),
                grid,
                frame,
                str(m.pair_id) or f"dsm_{len(out)}",
            )
        )
    return out


def _lonlat(crs: CRS, e: FloatArray, n: FloatArray) -> tuple[FloatArray, FloatArray]:
    from pyproj import CRS as _CRS
    from pyproj import Transformer

    tr = Transformer.from_crs(crs, _CRS.from_epsg(4326), always_xy=True)
    lon, lat = tr.transform(e, n)
    return np.asarray(lon, dtype=float), np.asarray(lat, dtype=float)


def _frame_heights(
    dsm: FrameDsm, lon: FloatArray, lat: FloatArray, start: FloatArray
) -> FloatArray:
    """Ellipsoidal height of the frame DSM's surface on the normals through (lon, lat)."""
    from ..io.geotiff import frame_of

    frame = frame_of(dsm.frame_id)
    if frame is None:
        raise ValueError(
            f"{dsm.name}: frame {dsm.frame_id!r} is not a tangent plane on WGS84: it cannot be "
            "placed on a map grid"
        )
    z = dsm.heights[np.isfinite(dsm.heights)]
    h_ref = frame.h0 + (float(np.median(z)) if z.size else 0.0)
    h = np.where(np.isfinite(start), start, h_ref)
    for _ in range(MAX_ROUNDS):
        x, y, zz = frame.to_local(lon, lat, h)
        zs = sample_bilinear(dsm.heights, dsm.grid, x, y)
        dh = zs - zz
        step = np.isfinite(dh)
        h = np.where(step, h + np.where(step, dh, 0.0), h)
        if not step.any() or float(np.max(np.abs(dh[step]))) < HEIGHT_TOL_M:
            break
    x, y, zz = frame.to_local(lon, lat, h)
    zs = sample_bilinear(dsm.heights, dsm.grid, x, y)
    return np.asarray(h + (zs - zz), dtype=float)


def to_map_grid(
    dsm: MapDsm | FrameDsm,
    grid: DsmGrid,
    crs: CRS,
    *,
    start: Float32Array | None = None,
) -> Float32Array:
    """A DSM's WGS84 ellipsoidal heights at the cell centres of a map grid (NaN: none).

    Args:
        dsm: a map DSM (resampled bilinearly, nodata kept out; any CRS) or a frame DSM (the
            surface's height on the ellipsoid normal through each cell centre, module doc).
        grid: the map grid (map metres).
        crs: its CRS.
        start: first guess of the heights (e.g. the reference's), metres; speeds the
            iteration of a frame DSM up.
    """
    from pyproj import CRS as _CRS
    from pyproj import Transformer

    out = np.full((grid.height, grid.width), np.nan, dtype=np.float32)
    same = isinstance(dsm, MapDsm) and _CRS(dsm.crs) == _CRS(crs)
    tr = None
    if isinstance(dsm, MapDsm) and not same:
        tr = Transformer.from_crs(crs, dsm.crs, always_xy=True)
    for r0 in range(0, grid.height, BLOCK_ROWS):
        r1 = min(grid.height, r0 + BLOCK_ROWS)
        e, n = grid.centres((r0, r1))
        if isinstance(dsm, MapDsm):
            if tr is not None:
                e, n = (np.asarray(v, dtype=float) for v in tr.transform(e, n))
            out[r0:r1] = sample_bilinear(dsm.heights, dsm.grid, e, n)
        else:
            lon, lat = _lonlat(crs, e, n)
            s = np.full(e.shape, np.nan) if start is None else start[r0:r1].astype(float)
            out[r0:r1] = _frame_heights(dsm, lon, lat, s)
    return out


def footprint(
    grid: DsmGrid,
    crs: CRS,
    heights: Sequence[Float32Array],
    images: Sequence[str | Path],
) -> BoolArray:
    """Map cells whose ground point projects inside every image (module doc, step 3).

    Args:
        grid: the map grid.
        crs: its CRS.
        heights: DSMs on that grid (ellipsoidal heights, NaN holes): a cell's ground point is
            at their median; where none has a height, at the median of all their heights.
        images: images with an RPC (tag 50844, sidecars: as ``parproj import`` finds them).
    """
    from ..io.scene_import import load_image

    stack = np.stack([np.asarray(h, dtype=np.float32) for h in heights])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN cells
        med = np.nanmedian(stack, axis=0)
    ok = np.isfinite(med)
    fill = float(np.median(med[ok])) if ok.any() else 0.0
    hh = np.where(ok, med, fill)
    inside = np.ones((grid.height, grid.width), dtype=bool)
    loaded = [load_image(p, f"image_{i}") for i, p in enumerate(images)]
    for r0 in range(0, grid.height, BLOCK_ROWS):
        r1 = min(grid.height, r0 + BLOCK_ROWS)
        e, n = grid.centres((r0, r1))
        lon, lat = _lonlat(crs, e, n)
        for img in loaded:
            line, sample = img.rpc.project(lon, lat, hh[r0:r1], outside="nan")
            with np.errstate(invalid="ignore"):
                inside[r0:r1] &= (
                    (line >= -0.5)
                    & (line <= img.lines - 0.5)
                    & (sample >= -0.5)
                    & (sample <= img.samples - 0.5)
                )
    return inside


def difference_stats(d: NDArray[np.floating[Any]]) -> dict[str, float | int]:
    """cells, median, NMAD (1.4826 median |d - median d|), RMS, p95 |d|, mean; metres.

    NaN values are left out; with no value the figures are NaN and cells 0.
    """
    v = np.asarray(d, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return {"cells": 0, "median": nan, "nmad": nan, "rms": nan, "p95_abs": nan, "mean": nan}
    m = float(np.median(v))
    return {
        "cells": int(v.size),
        "median": m,
        "nmad": 1.4826 * float(np.median(np.abs(v - m))),
        "rms": float(np.sqrt(np.mean(v * v))),
        "p95_abs": float(np.percentile(np.abs(v), 95)),
        "mean": float(np.mean(v)),
    }


def horizontal_shift(
    ours: NDArray[np.floating[Any]],
    reference: NDArray[np.floating[Any]],
    cell: float,
    mask: BoolArray,
    *,
    rounds: int = 3,
) -> dict[str, float | int]:
    """Horizontal shift of ``ours`` against ``reference`` on one north-up grid, metres.

    If ours(p) = reference(p - s) + dz, then d = ours - reference ~ dz - s . grad(reference)
    (first order in s). ``(dz, s_e, s_n)`` are fitted by least squares over the cells of
    ``mask`` valid in both, with slopes from central differences of the reference; cells
    farther than 3 NMAD from the fit's median residual are left out and the fit is repeated
    (``rounds`` times). Valid for shifts small against the terrain's curvature (a fraction of a
    cell to a few cells).

    Returns:
        ``shift_e_m``, ``shift_n_m`` (where ours lies relative to the reference, metres east
        and north), ``shift_dz_m`` (metres) and ``shift_cells`` (cells used); NaN and 0 when
        fewer than 100 cells with a slope are usable, or when the fit gives a shift beyond
        :data:`MAX_SHIFT_CELLS` (outside the range where the first-order model holds).
    """
    ref = np.asarray(reference, dtype=float)
    d = np.asarray(ours, dtype=float) - ref
    g_row, g_col = np.gradient(ref)
    de = g_col / cell  # dh / dE, per metre
    dn = -g_row / cell  # rows run south
    ok = mask & np.isfinite(d) & np.isfinite(de) & np.isfinite(dn)
    nan = float("nan")
    out: dict[str, float | int] = {
        "shift_e_m": nan,
        "shift_n_m": nan,
        "shift_dz_m": nan,
        "shift_cells": 0,
    }
    if ok.sum() < 100:
        return out
    dv, ev, nv = d[ok], de[ok], dn[ok]
    use = np.ones(dv.shape, dtype=bool)
    sol = np.zeros(3)
    for _ in range(max(rounds, 1)):
        a = np.stack([np.ones(int(use.sum())), -ev[use], -nv[use]], axis=1)
        sol, *_ = np.linalg.lstsq(a, dv[use], rcond=None)
        res = dv - (sol[0] - sol[1] * ev - sol[2] * nv)
        m = float(np.median(res))
        spread = 1.4826 * float(np.median(np.abs(res - m)))
        use = np.abs(res - m) <= 3.0 * max(spread, 1e-6)
        if use.sum() < 100:
            return out
    if math.hypot(float(sol[1]), float(sol[2])) > MAX_SHIFT_CELLS * cell:
        return out  # beyond the first-order range: not a measurement (e.g. against a coarse DEM)
    out.update(
        shift_e_m=float(sol[1]),
        shift_n_m=float(sol[2]),
        shift_dz_m=float(sol[0]),
        shift_cells=int(use.sum()),
    )
    return out


@dataclass(frozen=True)
class Comparison:
    """Ours - reference on one map grid over a footprint.

    Attributes:
        ours: our DSM's name.
        reference: the reference's name.
        stats: :func:`difference_stats` of ours - reference over the footprint cells valid in
            both (metres).
        footprint_cells: cells of the footprint.
        footprint: how it was made ("rpc: img_01.tif, img_02.tif" or "reference cells").
        completeness: share of footprint cells where ours has a height (0..1).
        reference_completeness: the same for the reference.
        grid: the map grid compared on.
        extra: anything else worth reporting.
    """

    ours: str
    reference: str
    stats: dict[str, float | int]
    footprint_cells: int
    footprint: str
    completeness: float
    reference_completeness: float
    grid: DsmGrid
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready figures."""
        return {
            "ours": self.ours,
            "reference": self.reference,
            **self.stats,
            "completeness": self.completeness,
            "reference_completeness": self.reference_completeness,
            "footprint_cells": self.footprint_cells,
            "footprint": self.footprint,
            **self.extra,
        }

    def line(self) -> str:
        """One line for a person."""
        s = self.stats
        sh = self.extra
        shift = (
            f"; shift E {sh['shift_e_m']:+.2f} m, N {sh['shift_n_m']:+.2f} m"
            if math.isfinite(float(sh.get("shift_e_m", float("nan"))))
            else ""
        )
        return (
            f"{self.ours} - {self.reference}: median {s['median']:+.2f} m, NMAD {s['nmad']:.2f} "
            f"m, RMS {s['rms']:.2f} m, p95 |d| {s['p95_abs']:.2f} m over {s['cells']} cells"
            f"{shift}; "
            f"completeness {100 * self.completeness:.1f} % (reference "
            f"{100 * self.reference_completeness:.1f} %) of {self.footprint_cells} footprint "
            f"cells ({self.footprint})"
        )


def compare(
    ours: MapDsm | FrameDsm,
    reference: MapDsm,
    *,
    images: Sequence[str | Path] = (),
    grid: tuple[DsmGrid, CRS] | None = None,
    footprint_layers: Sequence[MapDsm] = (),
    mask: BoolArray | None = None,
) -> Comparison:
    """Score ``ours`` against ``reference`` (module docstring).

    Args:
        ours: our DSM (a GeoTIFF read by :func:`read_geotiff_dsm`, or an ElevationGrid).
        reference: the reference.
        images: the images whose common RPC footprint is scored (none: the reference's cells).
        grid: (grid, CRS) to compare on (default: the reference's).
        footprint_layers: further DSMs whose heights take part in the footprint's median
            height (the README uses all six references).
        mask: a precomputed footprint on ``grid`` (then ``images`` only names it).
    """
    g, crs = grid if grid is not None else (reference.grid, reference.crs)
    ref = to_map_grid(reference, g, crs)
    mine = to_map_grid(ours, g, crs, start=ref)
    if mask is not None:
        fp = np.asarray(mask, dtype=bool)
        how = "given" + (f" (rpc: {', '.join(Path(p).name for p in images)})" if images else "")
    elif images:
        layers = [ref, mine] + [to_map_grid(f, g, crs) for f in footprint_layers]
        fp = footprint(g, crs, layers, images)
        how = "rpc: " + ", ".join(Path(p).name for p in images)
    else:
        fp = np.isfinite(ref)
        how = "reference cells"
    n = int(fp.sum())
    d = np.where(fp, mine.astype(float) - ref.astype(float), np.nan)
    stats = difference_stats(d)
    comp = float(np.isfinite(mine[fp]).mean()) if n else 0.0
    rcomp = float(np.isfinite(ref[fp]).mean()) if n else 0.0
    shift = horizontal_shift(mine, ref, g.cell, fp)
    return Comparison(ours.name, reference.name, stats, n, how, comp, rcomp, g, shift)


def load_ours(
    path: str | Path, pair: str | None = None, *, frame_id: str | None = None
) -> MapDsm | FrameDsm:
    """Our DSM: a GeoTIFF file, or the ``dsm`` of an output bag folder.

    ``pair``: its pair id, needed when the bag holds several; ``frame_id``: see
    :func:`frame_dsms_from_bag`.

    Raises:
        ValueError: a bag with several DSMs and no (or an unknown) ``pair``.
    """
    p = Path(path)
    if p.is_file() and p.suffix.lower() in (".tif", ".tiff"):
        return read_geotiff_dsm(p)
    dsms = frame_dsms_from_bag(p, frame_id=frame_id)
    if pair is not None:
        dsms = [d for d in dsms if d.name == pair]
        if not dsms:
            raise ValueError(f"{p}: no DSM of pair {pair!r}")
    if len(dsms) != 1:
        names = ", ".join(d.name for d in frame_dsms_from_bag(p))
        raise ValueError(f"{p}: {len(dsms)} DSMs ({names}): choose one with --pair")
    return dsms[0]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m parproj_ros.eval.dsm_compare``: print the comparison (exit 1 if empty)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("ours", help="our DSM: a GeoTIFF with CRS, or an output bag folder")
    ap.add_argument("reference", help="reference DSM GeoTIFF (ellipsoidal heights)")
    ap.add_argument("--images", nargs="*", default=[], help="images whose footprint is scored")
    ap.add_argument("--pair", help="pair id of the DSM in a bag with several")
    ap.add_argument(
        "--import-bag",
        help="the bag `parproj import` wrote: its frame for a DSM labelled 'map'",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    try:
        frame = import_bag_frame(args.import_bag) if args.import_bag else None
        ours = load_ours(args.ours, args.pair, frame_id=frame)
        res = compare(ours, read_geotiff_dsm(args.reference), images=args.images)
    except (OSError, ValueError) as err:
        print(f"dsm_compare: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res.as_dict(), indent=1))
    else:
        print(res.line())
    if res.stats["cells"] == 0:
        print("dsm_compare: no cell valid in both DSMs within the footprint", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
