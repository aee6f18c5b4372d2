"""y-parallax of a real pair (Mont Ventoux, Pleiades) against reference epipolar grids.

:func:`evaluate_against_grids` takes the output bag of ``parproj process`` (a StereoPair), the
two ORIGINAL crops and reference epipolar resampling grids (OTB, shareloc), matches features
between the original crops, and maps every match into epipolar rows

(a) through the published transforms of the StereoPair (scene frame, PTP roll, 2x3
    normalization affine, output grid: :func:`parproj_ros.eval.published.normalized_px`), and
(b) through the inverse of each reference grid (:class:`EpipolarGrid`),

then reports the y-parallax ``row_left - row_right`` of the same matches for every method: mean
|y|, RMS, 95th percentile of |y| (pixels of each method's epipolar image: ours are normalized
output pixels, the grids' are epipolar pixels; both are about one original pixel here).

Matches (independent of everything being evaluated): SIFT on both crops (8-bit stretch), Lowe's
ratio test (0.75), then each match refined by normalized cross-correlation: a 21 x 21 px template
around the left keypoint searched within +-3 px of the right keypoint, peak >= 0.85, sub-pixel
by a parabola through the peak and its neighbours along each axis (as
:func:`parproj_ros.eval.evaluate.match_y_parallax`). No RANSAC. Robust outlier cut
(:func:`robust_cut`): the displacement ``right - left`` of true matches varies along one
direction with the terrain height (the x-parallax) but, across it, is an affine function of the
image position (exact for parallel projection, and to well below a pixel over a 500 px crop of a
pushbroom scene). The direction of largest spread of the displacements gives the parallax
direction; the component across it is fitted by an affine function of the left position with
iterative 3-sigma rejection (sigma from the median absolute deviation, floor 0.5 px, 10
rounds). Matches off by more than the threshold are dropped for every method alike.

Reference grids (as found in ``shared/data/ventoux/reference_grids``; :func:`read_grid`): GeoTIFF
with two float bands per node, (rows, cols, 2); band 1 = column displacement, band 2 = row
displacement, in pixels of the original (full) scene; the ModelTransformationTag (34264) gives the
node spacing (30 px) and the corner of the first node's cell (-15, -15): node (i, j) is at
epipolar (row, col) = (-15 + 15 + 30 i, -15 + 15 + 30 j) = (30 i, 30 j) (GDAL's pixel-is-area
convention: cell corner = node - step / 2). The original position of node (i, j) is
``(30 i + drow, 30 j + dcol)`` (OTB's displacement-field convention), in full-scene pixels;
a crop pixel (line, sample) is at ``(line + line0, sample + sample0)`` with the crop offset of
the crop's ModelTransformationTag. Between nodes the grid is bilinear; its inverse (original
position -> epipolar pixel) is found by Newton iterations on the bilinear interpolation.
How this reading was verified: the grids' node spacing in the original image is 30 px per 30
epipolar px (:func:`grid_scale`: 1.000 left, 0.989 right), which fixes the band order and the
displacement (not position) reading (swapped bands or positions give 1.59 or worse); and the
grids map RPC-exact correspondences (truth/points of an imported bag,
:func:`rpc_points_y_parallax`) to the same epipolar row: OTB to 1e-4 px, shareloc to 0.005 px
(its right grid differs from OTB's by up to 0.005 px). The epipolar origin cancels in
``row_left - row_right``, and a common half-pixel shift of both original positions changes it by
only 0.01 px per pixel (the two grids are rotated alike to 0.6 deg): immaterial here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..imaging.matching import match_normalized
from ..io.scene_import import MODEL_TRANSFORMATION_TAG, crop_offset, read_image
from ..ros.bag import BagReader
from .evaluate import error_stats
from .published import normalized_px

FloatArray = NDArray[np.float64]

#: Reference grid files looked for in a folder: method name -> (left, right) file names.
REFERENCE_GRIDS = {
    "otb": ("otb_left_grid.tif", "otb_right_grid.tif"),
    "shareloc": ("shareloc_gt_left_grid.tif", "shareloc_gt_right_grid.tif"),
}


# ---------------------------------------------------------------------------------------------
# Reference grids


@dataclass(frozen=True)
class EpipolarGrid:
    """A resampling grid: epipolar pixel (row, col) -> original full-scene pixel (row, col).

    Attributes:
        row0: epipolar row of node row 0, pixels.
        col0: epipolar column of node column 0, pixels.
        step_row: epipolar rows between node rows, pixels.
        step_col: epipolar columns between node columns, pixels.
        rows: (ny, nx) original row of each node, pixels.
        cols: (ny, nx) original column of each node, pixels.

    """

    row0: float
    col0: float
    step_row: float
    step_col: float
    rows: FloatArray
    cols: FloatArray

    def _cell(
        self, er: FloatArray, ec: FloatArray
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], FloatArray, FloatArray]:
        """Cell indices (clamped: linear extrapolation outside) and fractions."""
        ny, nx = self.rows.shape
        u = (er - self.row0) / self.step_row
        v = (ec - self.col0) / self.step_col
        i = np.clip(np.floor(np.nan_to_num(u)).astype(np.intp), 0, ny - 2)
        j = np.clip(np.floor(np.nan_to_num(v)).astype(np.intp), 0, nx - 2)
        return i, j, u - i, v - j

    def forward(self, er: FloatArray, ec: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Epipolar (row, col) -> original (row, col), bilinear, pixels."""
        er, ec = np.broadcast_arrays(np.asarray(er, float), np.asarray(ec, float))
        i, j, fu, fv = self._cell(er, ec)
        out = []
        for g in (self.rows, self.cols):
            top = g[i, j] + fv * (g[i, j + 1] - g[i, j])
            bottom = g[i + 1, j] + fv * (g[i + 1, j + 1] - g[i + 1, j])
            out.append(top + fu * (bottom - top))
        return out[0], out[1]

    def _jacobian(self, er: FloatArray, ec: FloatArray) -> FloatArray:
        """d(row, col) / d(er, ec), shape (..., 2, 2)."""
        i, j, fu, fv = self._cell(er, ec)
        jac = np.empty((*er.shape, 2, 2))
        for k, g in enumerate((self.rows, self.cols)):
            g00, g01, g10, g11 = g[i, j], g[i, j + 1], g[i + 1, j], g[i + 1, j + 1]
            jac[..., k, 0] = ((g10 - g00) + fv * (g11 - g10 - g01 + g00)) / self.step_row
            jac[..., k, 1] = ((g01 - g00) + fu * (g11 - g10 - g01 + g00)) / self.step_col
        return jac

    def inverse(
        self, row: FloatArray, col: FloatArray, *, tol: float = 1e-8, max_iter: int = 50
    ) -> tuple[FloatArray, FloatArray]:
        """Original (row, col) -> epipolar (row, col): Newton on the bilinear grid.

        Starts from the least-squares affine inverse of the nodes; NaN where it does not
        converge to ``tol`` pixels (in the original image).
        """
        row, col = np.broadcast_arrays(np.asarray(row, float), np.asarray(col, float))
        ny, nx = self.rows.shape
        ei, ej = np.meshgrid(
            self.row0 + self.step_row * np.arange(ny),
            self.col0 + self.step_col * np.arange(nx),
            indexing="ij",
        )
        design = np.column_stack([self.rows.ravel(), self.cols.ravel(), np.ones(ny * nx)])
        coef, *_ = np.linalg.lstsq(design, np.column_stack([ei.ravel(), ej.ravel()]), rcond=None)
        start = np.stack([row, col, np.ones_like(row)], axis=-1) @ coef
        er, ec = start[..., 0].copy(), start[..., 1].copy()
        err = np.full(row.shape, np.inf)
        for _ in range(max_iter):
            fr, fc = self.forward(er, ec)
            rr, rc = fr - row, fc - col
            err = np.hypot(rr, rc)
            if not np.any(err > tol):
                break
            jac = self._jacobian(er, ec)
            det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
            er = er - (jac[..., 1, 1] * rr - jac[..., 0, 1] * rc) / det
            ec = ec - (jac[..., 0, 0] * rc - jac[..., 1, 0] * rr) / det
        fr, fc = self.forward(er, ec)
        bad = ~(np.hypot(fr - row, fc - col) <= max(tol, 1e-6))
        return np.where(bad, np.nan, er), np.where(bad, np.nan, ec)


def read_grid(path: str | Path, *, kind: str = "displacement") -> EpipolarGrid:
    """Read a reference epipolar grid GeoTIFF (module docstring).

    Args:
        path: the grid: two bands (column, row) per node, ModelTransformationTag with the node
            spacing and the corner of the first node's cell.
        kind: ``"displacement"`` (OTB, shareloc: original = epipolar node + value) or
            ``"position"`` (the values are original positions).

    Raises:
        ValueError: not a two-band grid, no or a rotated ModelTransformationTag, unknown kind.

    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        page = tif.pages.first
        data = np.asarray(page.asarray(), dtype=np.float64)
        tag = page.tags.get(MODEL_TRANSFORMATION_TAG)
        if tag is None:
            raise ValueError(f"{path}: no ModelTransformationTag ({MODEL_TRANSFORMATION_TAG})")
        m = np.asarray(tag.value, dtype=np.float64).reshape(4, 4)
        if data.ndim == 3 and page.planarconfig != 1:
            data = np.moveaxis(data, 0, -1)
    if data.ndim != 3 or data.shape[2] != 2:
        raise ValueError(f"{path}: expected a (rows, cols, 2) grid, got {data.shape}")
    if m[0, 1] != 0.0 or m[1, 0] != 0.0 or m[0, 0] <= 0 or m[1, 1] <= 0:
        raise ValueError(f"{path}: rotated or flipped grid geotransform {m[:2].ravel()}")
    step_col, step_row = float(m[0, 0]), float(m[1, 1])
    col0, row0 = float(m[0, 3]) + 0.5 * step_col, float(m[1, 3]) + 0.5 * step_row
    ny, nx = data.shape[:2]
    if kind == "displacement":
        ei, ej = np.meshgrid(
            row0 + step_row * np.arange(ny), col0 + step_col * np.arange(nx), indexing="ij"
        )
        rows, cols = data[..., 1] + ei, data[..., 0] + ej
    elif kind == "position":
        rows, cols = data[..., 1], data[..., 0]
    else:
        raise ValueError(f"kind must be 'displacement' or 'position', not {kind!r}")
    return EpipolarGrid(row0, col0, step_row, step_col, rows, cols)


# ---------------------------------------------------------------------------------------------
# Matches between the original images


@dataclass(frozen=True)
class Matches:
    """Conjugate points of two images, (line, sample) pixels of each (n, 2).

    Attributes:
        left: positions in the left image (integer: template centres).
        right: sub-pixel positions in the right image.
        ncc: correlation peak of each match.
        candidates: matches after the ratio test and NCC refinement.
        refined: the same count (kept for the report), before the outlier cut.
        cut_threshold_px: the final rejection threshold across the parallax direction, pixels.

    """

    left: FloatArray
    right: FloatArray
    ncc: FloatArray
    candidates: int
    refined: int
    cut_threshold_px: float

    def __len__(self) -> int:
        return len(self.left)


def robust_cut(
    left: FloatArray,
    right: FloatArray,
    *,
    k_sigma: float = 3.0,
    floor_px: float = 0.5,
    rounds: int = 10,
) -> tuple[NDArray[np.bool_], float]:
    """Inliers of matches by the affine model across the parallax direction (module docstring).

    Args:
        left: (n, 2) left (line, sample), pixels.
        right: (n, 2) right (line, sample), pixels.
        k_sigma: rejection threshold in robust standard deviations (1.4826 MAD).
        floor_px: smallest threshold, pixels.
        rounds: fit-and-reject rounds at most.

    Returns:
        (inlier mask, last threshold in pixels).

    """
    d = right - left
    n = len(d)
    keep = np.ones(n, dtype=bool)
    if n < 6:
        return keep, float("inf")
    thr = float("inf")
    for _ in range(rounds):
        c = d[keep] - np.median(d[keep], axis=0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        across = d @ vt[1]  # component across the direction of largest spread
        design = np.column_stack([left, np.ones(n)])
        coef, *_ = np.linalg.lstsq(design[keep], across[keep], rcond=None)
        res = across - design @ coef
        sigma = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep]))))
        thr = max(floor_px, k_sigma * sigma)
        new = np.abs(res) <= thr
        if np.array_equal(new, keep) or new.sum() < 6:
            break
        keep = new
    return keep, thr


def match_images(
    left: NDArray[np.generic],
    right: NDArray[np.generic],
    *,
    nodata: float = 0.0,
    half: int = 10,
    search: int = 3,
    min_corr: float = 0.85,
    nfeatures: int = 6000,
) -> Matches:
    """SIFT + ratio test + NCC sub-pixel refinement + robust cut (module docstring).

    The matching itself is :func:`parproj_ros.imaging.matching.match_normalized` over the
    whole image (one window) with no row filter, since the original crops are not epipolar.
    """
    m = match_normalized(
        left,
        right,
        nodata=nodata,
        window=max(left.shape + right.shape),
        grid=1,
        max_per_window=nfeatures // 4,
        half=half,
        search=search,
        min_corr=min_corr,
        max_y_px=None,
    )
    empty = np.zeros((0, 2))
    if len(m) == 0:
        return Matches(empty, empty, np.zeros(0), 0, 0, float("nan"))
    a = np.column_stack([m.yl, m.xl])  # (line, sample)
    b = np.column_stack([m.yr, m.xr])
    keep, thr = robust_cut(a, b)
    return Matches(a[keep], b[keep], m.score[keep], len(m), len(a), thr)


# ---------------------------------------------------------------------------------------------
# Evaluation


def read_stereo_pair(out_bag: str | Path, index: int = 0) -> Any:
    """The ``index``-th StereoPair message of an output bag.

    Raises:
        ValueError: the bag has no such StereoPair.

    """
    reader = BagReader(Path(out_bag))
    pairs = [item.msg for item in reader.messages(topics=[contract.STEREO_PAIR])]
    if len(pairs) <= index:
        raise ValueError(f"{out_bag}: {len(pairs)} stereo_pair messages, #{index} asked for")
    return pairs[index]


def ours_rows(sp: Any, left_ls: FloatArray, right_ls: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Normalized (output-pixel) rows of left and right image points via the published transforms.

    ``left_ls`` / ``right_ls`` are (n, 2) (line, sample) in the scenes of the StereoPair's
    left / right parameters (for an imported pair: crop pixels).
    """
    pix = sp.normalized_pixel_size
    _, rl = normalized_px(
        sp.left_params,
        sp.left_to_normalized,
        sp.left_x_origin,
        sp.y_origin,
        pix,
        left_ls[:, 0],
        left_ls[:, 1],
    )
    _, rr = normalized_px(
        sp.right_params,
        sp.right_to_normalized,
        sp.right_x_origin,
        sp.y_origin,
        pix,
        right_ls[:, 0],
        right_ls[:, 1],
    )
    return rl, rr


def grid_rows(
    grids: tuple[EpipolarGrid, EpipolarGrid],
    left_ls: FloatArray,
    right_ls: FloatArray,
    offsets: tuple[tuple[float, float], tuple[float, float]],
) -> tuple[FloatArray, FloatArray]:
    """Epipolar rows of crop points through inverse reference grids (crop offsets added)."""
    out = []
    for grid, ls, off in zip(grids, (left_ls, right_ls), offsets, strict=True):
        er, _ = grid.inverse(ls[:, 0] + off[0], ls[:, 1] + off[1])
        out.append(er)
    return out[0], out[1]


def grid_scale(grid: EpipolarGrid) -> float:
    """Original pixels per epipolar pixel along the grid's rows and columns, mean.

    1.0: the epipolar image keeps the original resolution.
    """
    dc = np.hypot(np.diff(grid.rows, axis=1), np.diff(grid.cols, axis=1)) / grid.step_col
    dr = np.hypot(np.diff(grid.rows, axis=0), np.diff(grid.cols, axis=0)) / grid.step_row
    return float(np.concatenate([dc.ravel(), dr.ravel()]).mean())


def _row_direction(rows_of: Any, centre: FloatArray) -> FloatArray:
    """d(epipolar row) / d(line, sample) at ``centre`` (central differences, 1 px)."""
    pts = centre + np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    r = rows_of(pts)
    return np.array([r[0] - r[1], r[2] - r[3]]) / 2.0


def load_grids(folder: str | Path) -> dict[str, tuple[EpipolarGrid, EpipolarGrid]]:
    """The reference grids of :data:`REFERENCE_GRIDS` present in ``folder``."""
    f = Path(folder)
    return {
        name: (read_grid(f / ln), read_grid(f / rn))
        for name, (ln, rn) in REFERENCE_GRIDS.items()
        if (f / ln).is_file() and (f / rn).is_file()
    }


def rpc_points_y_parallax(
    truth_bag: str | Path,
    sp: Any,
    grids: dict[str, tuple[EpipolarGrid, EpipolarGrid]],
    offsets: tuple[tuple[float, float], tuple[float, float]],
) -> dict[str, dict[str, float]]:
    """y-parallax of the RPC-exact truth points of an imported bag, for every method, pixels."""
    from ..ros.inputs import truth_from_bag

    lid, rid = sp.left_params.scene_id, sp.right_params.scene_id
    pts = [
        p for p in truth_from_bag(BagReader(Path(truth_bag))) if {lid, rid} <= set(p.observations)
    ]
    if not pts:
        return {}
    ll = np.array([p.observations[lid] for p in pts])
    rr = np.array([p.observations[rid] for p in pts])
    a, b = ours_rows(sp, ll, rr)
    out = {"ours": error_stats(a - b, finite_only=True)}
    for name, g in grids.items():
        a, b = grid_rows(g, ll, rr, offsets)
        out[name] = error_stats(a - b, finite_only=True)
    return out


def evaluate_against_grids(
    out_bag: str | Path,
    left_tif: str | Path,
    right_tif: str | Path,
    grids_dir: str | Path,
    *,
    truth_bag: str | Path | None = None,
    pair_index: int = 0,
    offsets: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """y-parallax of independent matches: ours (published transforms) vs reference grids.

    Args:
        out_bag: output bag of ``parproj process`` (its StereoPair number ``pair_index``).
        left_tif: the original left crop (the StereoPair's left scene).
        right_tif: the original right crop.
        grids_dir: folder with the reference grids (:data:`REFERENCE_GRIDS`).
        truth_bag: the imported input bag: its truth/points (RPC-exact) are evaluated too.
        pair_index: which StereoPair.
        offsets: crop offsets (line, sample) of the two crops in the grids' full scenes;
            default from the TIFFs (:func:`parproj_ros.io.scene_import.crop_offset`).

    Returns:
        ``{"pair_id", "methods": {name: stats}, "matches": {...}, "differences": {...},
        "rpc_points": {...}}``; stats in pixels (:func:`~parproj_ros.eval.evaluate.error_stats`).

    Raises:
        ValueError: the crops do not have the sizes of the StereoPair's scenes.

    """
    sp = read_stereo_pair(out_bag, pair_index)
    left, right = read_image(left_tif), read_image(right_tif)
    for img, prm, path in ((left, sp.left_params, left_tif), (right, sp.right_params, right_tif)):
        # `parproj import` pads a narrower crop with no-data columns up to the detector count.
        if img.shape[0] != prm.lines or not 0 <= prm.detectors - img.shape[1] <= 16:
            raise ValueError(
                f"{path} is {img.shape[0]} x {img.shape[1]} px but scene {prm.scene_id} of the "
                f"pair is {prm.lines} x {prm.detectors}: wrong image or order"
            )
    if offsets is None:
        offsets = (crop_offset(left_tif) or (0.0, 0.0), crop_offset(right_tif) or (0.0, 0.0))
    grids = load_grids(grids_dir)
    m = match_images(left, right)
    rows: dict[str, tuple[FloatArray, FloatArray]] = {"ours": ours_rows(sp, m.left, m.right)}
    for name, g in grids.items():
        rows[name] = grid_rows(g, m.left, m.right, offsets)
    ypar = {name: a - b for name, (a, b) in rows.items()}
    # Each method has its own sense of the epipolar y axis: orient the others like ours (the
    # sign of the dot product of the row gradients in the left image, at its centre).
    centre = np.array([[(left.shape[0] - 1) / 2.0, (left.shape[1] - 1) / 2.0]])
    ours_dir = _row_direction(lambda p: ours_rows(sp, p, p)[0], centre[0])
    sense = {"ours": 1.0}
    for name, g in grids.items():
        d = _row_direction(lambda p, g=g: grid_rows(g, p, p, offsets)[0], centre[0])
        sense[name] = 1.0 if float(d @ ours_dir) >= 0 else -1.0
    result: dict[str, Any] = {
        "pair_id": sp.pair_id,
        "methods_used": [int(sp.left_params.method), int(sp.right_params.method)],
        "published_y_parallax_source": sp.y_parallax_source,
        "offsets_line_sample": [list(o) for o in offsets],
        "matches": {
            "ratio_test": m.candidates,
            "ncc_refined": m.refined,
            "after_cut": len(m),
            "cut_threshold_px": m.cut_threshold_px,
        },
        "methods": {name: error_stats(y, finite_only=True) for name, y in ypar.items()},
        "y_axis_sense": sense,
        "grid_scale": {name: [grid_scale(g[0]), grid_scale(g[1])] for name, g in grids.items()},
        "differences": {},
    }
    names = list(ypar)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            d = sense[a] * ypar[a] - sense[b] * ypar[b]
            d = d[np.isfinite(d)]
            result["differences"][f"{a}-{b}"] = (
                {
                    "mean": float(d.mean()),
                    "std": float(d.std()),
                    "max_abs": float(np.abs(d).max()),
                }
                if d.size
                else {"mean": float("nan"), "std": float("nan"), "max_abs": float("nan")}
            )
    if truth_bag is not None:
        result["rpc_points"] = rpc_points_y_parallax(truth_bag, sp, grids, offsets)
    return result


def format_table(res: dict[str, Any]) -> str:
    """The result of :func:`evaluate_against_grids` as a text table."""
    m = res["matches"]
    lines = [
        f"pair {res['pair_id']}: {m['after_cut']} matches (ratio test {m['ratio_test']}, "
        f"NCC {m['ncc_refined']}, cut at {m['cut_threshold_px']:.2f} px)",
        f"{'method':10s} {'n':>5s} {'mean|y|':>9s} {'RMS':>9s} {'p95|y|':>9s} {'mean y':>9s}"
        f" {'std y':>9s}   (px)",
    ]
    for name, s in res["methods"].items():
        if not s.get("n"):
            lines.append(f"{name:10s}     0")
            continue
        lines.append(
            f"{name:10s} {s['n']:5d} {s['mean_abs']:9.3f} {s['rms']:9.3f} {s['p95_abs']:9.3f}"
            f" {s['mean']:+9.3f} {s['std']:9.3f}"
        )
    lines.append("differences, same matches, y axes oriented like ours (px):")
    for key, d in res["differences"].items():
        lines.append(
            f"  {key:14s} mean {d['mean']:+.4f}  std {d['std']:.4f}  max |d| {d['max_abs']:.4f}"
        )
    rp = res.get("rpc_points")
    if rp:
        lines.append("RPC-exact truth points (y-parallax, px):")
        for name, s in rp.items():
            lines.append(
                f"  {name:10s} n {s['n']:4d} mean|y| {s['mean_abs']:.4f} mean {s['mean']:+.4f}"
                f" max {s['max_abs']:.4f}"
            )
    return "\n".join(lines)
