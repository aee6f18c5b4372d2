"""Long scenes: cutting a stereo pair into segments that the parallel model can represent.

The parallel projection (paper 1 Eq 1, with PTP Eq 7) describes a scene taken with constant
velocity and constant attitude. A long scene of a real sensor is not that: an agile satellite
turns during the acquisition (Pleiades steers its pitch), the orbit curves, and the model error
grows with the scene's length. This module cuts such a pair along track into segments, each
with its own A1..A8 (and roll), until every segment's model error is within a bound in pixels.

How the error is measured: the largest residual length of the Eq 8 fit over the points of the
segment (GCP, or virtual GCP of an RPC pair), in pixels of the detector pitch. With dense virtual
GCP that is the model error itself; with real GCP it also holds their measurement noise, so the
bound must be above the noise (the fit cannot go below it, and the cutting then stops: see
``reached``).

How a pair is cut: the left scene's lines into ``n`` equal cores, each widened by ``overlap``
(a fraction of the core) on both sides; the right segment of each is the span of right-scene
lines at which the points seen in the left segment are observed (points seen in both scenes tie
the two cuts to the same ground), widened by the same fraction. ``n`` grows from 2 until every
segment is within the bound, until a segment has fewer than ``min_points`` points, or until more
segments stop reducing the error (the rest of the error is then not along track: a wide swath
or a large height range, which shorter segments cannot fix).

Frames: a segment's scene frame has its origin at the segment's middle line, one line = one
``pixel_size`` along track (the affine absorbs the real scale), lines counted from the segment's
first line. Everything here is pure numpy; no ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError
from .estimation import AffineEstimate, estimate_affine
from .navigation import SceneFrame

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class SideCamera:
    """What the Eq 8 fit of one scene needs.

    Attributes:
        principal_distance: c, metres.
        pixel_size: detector pitch, metres.
        principal_point: sample of the principal point, pixels.
        psi: the roll for PTP, radians; None to estimate it (Eq 8).
    """

    principal_distance: float
    pixel_size: float
    principal_point: float
    psi: float | None = None


@dataclass(frozen=True)
class SegmentFit:
    """One segment of one scene.

    Attributes:
        start: first line of the segment in the scene (inclusive).
        stop: one past the segment's last line.
        estimate: the Eq 8 fit over the segment's points (scene coordinates in ``frame``).
        frame: image (lines counted from ``start``) -> scene metres.
        points: indices of the points used, into the arrays given.
    """

    start: int
    stop: int
    estimate: AffineEstimate
    frame: SceneFrame
    points: IntArray

    @property
    def lines(self) -> int:
        """Number of lines of the segment."""
        return self.stop - self.start

    @property
    def error_px(self) -> float:
        """Model error of the segment: its largest residual length, pixels."""
        return float(self.estimate.residual_norms_px.max())


@dataclass(frozen=True)
class PairSegmentation:
    """The segments of a pair (left[k] pairs with right[k]).

    Attributes:
        bound_px: the model error bound worked to, pixels.
        whole_error_px: (left, right) model error of one model per whole scene, pixels.
        left: segments of the left scene, in line order.
        right: segments of the right scene, same length as ``left``.
        tried: (number of segments, largest error) for every cut tried, pixels.
        note: why the cutting stopped, in words.
    """

    bound_px: float
    whole_error_px: tuple[float, float]
    left: tuple[SegmentFit, ...]
    right: tuple[SegmentFit, ...]
    tried: tuple[tuple[int, float], ...]
    note: str

    @property
    def count(self) -> int:
        """Number of segment pairs (1: the whole scenes)."""
        return len(self.left)

    @property
    def max_error_px(self) -> float:
        """Largest model error over all segments, pixels."""
        return max(s.error_px for s in self.left + self.right)

    @property
    def reached(self) -> bool:
        """Whether every segment is within the bound."""
        return self.max_error_px <= self.bound_px


def fit_segment(
    xyz: FloatArray,
    line_sample: FloatArray,
    start: int,
    stop: int,
    cam: SideCamera,
    *,
    min_points: int,
) -> SegmentFit | None:
    """Eq 8 fit over the points observed on lines ``start`` .. ``stop - 1`` (None: too few).

    Args:
        xyz: (n, 3) object coordinates, metres.
        line_sample: (n, 2) image coordinates in the whole scene, pixels.
        start: first line of the segment.
        stop: one past its last line.
        cam: interior orientation and roll mode.
        min_points: fewer points than this give None.

    Returns:
        The fit, or None when the segment has too few points or they are degenerate.

    """
    lines = line_sample[:, 0]
    idx = np.flatnonzero((lines >= start - 0.5) & (lines <= stop - 0.5))
    if idx.size < min_points:
        return None
    frame = SceneFrame(
        (stop - start - 1) / 2.0, cam.pixel_size, cam.pixel_size, cam.principal_point
    )
    obs = frame.to_scene(lines[idx] - start, line_sample[idx, 1])
    try:
        est = estimate_affine(
            xyz[idx],
            obs,
            principal_distance=cam.principal_distance,
            pixel_size=cam.pixel_size,
            psi=cam.psi,
        )
    except GeometryError:
        return None
    return SegmentFit(start, stop, est, frame, idx)


def _cut(
    n: int,
    lines: tuple[int, int],
    left_ls: FloatArray,
    right_ls: FloatArray,
    common: tuple[IntArray, IntArray],
    overlap: float,
) -> list[tuple[tuple[int, int], tuple[int, int]]] | None:
    """Line ranges ((left start, stop), (right start, stop)) of ``n`` segment pairs."""
    nl, nr = lines
    edges = np.round(np.linspace(0, nl, n + 1)).astype(int)
    cl, cr = left_ls[common[0], 0], right_ls[common[1], 0]
    out = []
    for k in range(n):
        core = int(edges[k + 1] - edges[k])
        ov = math.ceil(overlap * core)
        a, b = max(0, int(edges[k]) - ov), min(nl, int(edges[k + 1]) + ov)
        seen = (cl >= a - 0.5) & (cl <= b - 0.5)
        if not np.any(seen):
            return None
        rmin, rmax = float(cr[seen].min()), float(cr[seen].max())
        # The points span the segment's ground only up to the grid spacing: widen the right
        # span by the left segment's length ratio outside the points, then by the overlap.
        lmin, lmax = float(cl[seen].min()), float(cl[seen].max())
        scale = (rmax - rmin) / (lmax - lmin) if lmax > lmin else 1.0
        rmin -= (lmin - a) * abs(scale)
        rmax += (b - 1 - lmax) * abs(scale)
        ovr = math.ceil(0.02 * (rmax - rmin))  # round-off and the points' spread
        r0 = max(0, math.floor(rmin) - ovr)
        r1 = min(nr, math.ceil(rmax) + 1 + ovr)
        if r1 - r0 < 2:
            return None
        out.append(((a, b), (r0, r1)))
    return out


def segment_pair(
    left_xyz: ArrayLike,
    left_ls: ArrayLike,
    right_xyz: ArrayLike,
    right_ls: ArrayLike,
    common: tuple[ArrayLike, ArrayLike],
    *,
    lines: tuple[int, int],
    cameras: tuple[SideCamera, SideCamera],
    bound_px: float,
    overlap: float = 0.1,
    min_points: int = 10,
    max_segments: int = 64,
) -> PairSegmentation:
    """Cut a pair along track until each segment's parallel model error is within ``bound_px``.

    Args:
        left_xyz: (n, 3) object coordinates of the points observed in the left scene, metres.
        left_ls: (n, 2) their (line, sample) in the left scene, pixels.
        right_xyz: (m, 3) the same for the right scene.
        right_ls: (m, 2) their (line, sample) in the right scene.
        common: (indices into the left arrays, indices into the right arrays) of the points
            observed in both scenes, in corresponding order; they tie the two cuts together.
        lines: number of lines of the (left, right) scene.
        cameras: (left, right) interior orientation and roll mode for the fits.
        bound_px: model error bound, pixels (> 0).
        overlap: each segment extends this fraction of its core length into its neighbours.
        min_points: a segment needs this many points in each scene (Eq 8 has 9 unknowns).
        max_segments: the most segments tried.

    Returns:
        The segmentation; ``count == 1`` when the whole scenes are within the bound (or cannot
        be cut usefully), ``reached`` says whether the bound holds.

    Raises:
        GeometryError: bad arguments, or too few points to fit the whole scenes.

    """
    lx, ll = np.asarray(left_xyz, dtype=float), np.asarray(left_ls, dtype=float)
    rx, rl = np.asarray(right_xyz, dtype=float), np.asarray(right_ls, dtype=float)
    ci = (np.asarray(common[0], dtype=np.intp), np.asarray(common[1], dtype=np.intp))
    if not (np.isfinite(bound_px) and bound_px > 0):
        raise GeometryError(f"bound_px must be a finite number > 0, got {bound_px}")
    if not (0.0 <= overlap < 1.0):
        raise GeometryError(f"overlap must be in [0, 1), got {overlap}")
    if ci[0].shape != ci[1].shape:
        raise GeometryError("common: index arrays of different lengths")
    nl, nr = (int(v) for v in lines)
    whole_l = fit_segment(lx, ll, 0, nl, cameras[0], min_points=min_points)
    whole_r = fit_segment(rx, rl, 0, nr, cameras[1], min_points=min_points)
    if whole_l is None or whole_r is None:
        raise GeometryError(f"fewer than {min_points} usable points in a scene: cannot fit it")
    whole = (whole_l.error_px, whole_r.error_px)
    best: tuple[list[SegmentFit], list[SegmentFit]] = ([whole_l], [whole_r])
    best_err = max(whole)
    tried = [(1, best_err)]
    if best_err <= bound_px:
        note = f"whole scenes within the bound ({best_err:.3f} <= {bound_px:g} px)"
        return PairSegmentation(bound_px, whole, (whole_l,), (whole_r,), tuple(tried), note)
    note = ""
    stalled = 0
    for n in range(2, max_segments + 1):
        cuts = _cut(n, (nl, nr), ll, rl, ci, overlap)
        if cuts is None:
            note = f"{n} segments would leave a segment without common points"
            break
        fits_l, fits_r = [], []
        for (a, b), (c, d) in cuts:
            fl = fit_segment(lx, ll, a, b, cameras[0], min_points=min_points)
            fr = fit_segment(rx, rl, c, d, cameras[1], min_points=min_points)
            if fl is None or fr is None:
                break
            fits_l.append(fl)
            fits_r.append(fr)
        else:
            err = max(s.error_px for s in fits_l + fits_r)
            tried.append((n, err))
            if err < best_err:
                stalled = 0 if err < 0.95 * best_err else stalled + 1
                best, best_err = (fits_l, fits_r), err
            else:
                stalled += 1
            if err <= bound_px:
                note = f"bound met with {n} segments"
                break
            if stalled >= 3:
                note = (
                    f"the error stopped shrinking with shorter segments ({best_err:.3f} px with "
                    f"{len(best[0])}): what is left is not along track (swath width, height range "
                    "or noise)"
                )
                break
            continue
        note = f"{n} segments would leave a segment with fewer than {min_points} points"
        break
    else:
        note = f"bound not met with {max_segments} segments"
    return PairSegmentation(bound_px, whole, tuple(best[0]), tuple(best[1]), tuple(tried), note)
