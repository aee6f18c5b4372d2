"""Micro-benchmark of dense matching and DSM: ``python -m tools.bench.heights [--size N]``.

A synthetic uint16 pair (band-limited random texture, the right image displaced by a smooth
disparity field of about ``--range`` pixels) is matched by

* :func:`parproj_ros.imaging.dense.match_pair` with its default tiles (1024 x 1024, 64 px
  overlap), and as one tile;
* bare ``cv2.StereoSGBM`` with the same settings on the already stretched uint8 images, one
  pass (the lower bound), and two passes (left-right and mirrored right-left, the work the
  consistency check needs); and ``match_pair`` with the check on a right pass at half
  resolution (``lr_check="reduced"``), that with the photometric check (``min_ncc=0.7``), and
  without the check (``lr_check="none"``);

and the disparity map is gridded into a DSM (:func:`~parproj_ros.imaging.heights.make_dsm`)
and ortho-resampled (:func:`~parproj_ros.imaging.heights.orthoimage`). Figures are left-image
megapixels per second (best of ``--repeat``); the ratio is the time relative to one bare pass.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from parproj_ros.geometry import AffineModel
from parproj_ros.imaging.dense import SgbmParams, match_pair, sgbm_matcher, to_uint8
from parproj_ros.imaging.heights import GroundMapping, make_dsm, orthoimage
from parproj_ros.imaging.resample import OutputGrid


def synthetic_pair(size: int, d_span: float, seed: int = 0) -> tuple[NDArray[Any], NDArray[Any]]:
    """(left, right) uint16 (size, size): right(c - d(c, r)) = left(c), d in [0, d_span] px."""
    rng = np.random.default_rng(seed)
    pad = int(d_span) + 8
    noise = rng.uniform(0, 2047, (size, size + pad)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 1.0)
    rr, cc = np.mgrid[0:size, 0 : size + pad].astype(np.float32)
    d = (0.5 * d_span * (1 + np.sin(cc / 90.0) * np.cos(rr / 70.0))).astype(np.float32)
    xr = np.arange(size, dtype=np.float32)[None, :] + np.zeros((size, 1), np.float32)
    xl = xr + 0.5 * d_span
    for _ in range(10):
        xl = xr + cv2.remap(d, xl, rr[:, :size], cv2.INTER_LINEAR)
    right = cv2.remap(tex, xl, rr[:, :size], cv2.INTER_CUBIC)
    to16: Callable[[NDArray[Any]], NDArray[Any]] = lambda a: np.clip(a, 1, 2047).astype(  # noqa: E731
        np.uint16
    )
    return to16(tex[:, :size]), to16(right)


def best_of(repeat: int, fn: Callable[[], object]) -> float:
    """Shortest wall time of ``repeat`` calls, seconds."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2048, help="image side, pixels")
    ap.add_argument("--range", type=int, default=48, help="disparity span, pixels")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (best kept)")
    args = ap.parse_args(argv)
    left, right = synthetic_pair(args.size, float(args.range))
    d_range = (-8, args.range + 8)
    p = SgbmParams()
    mpx = left.size / 1e6
    l8 = to_uint8(left, *np.percentile(left, p.stretch_percentiles))
    r8 = to_uint8(right, *np.percentile(right, p.stretch_percentiles))
    ndisp = int(np.ceil((d_range[1] - d_range[0] + 1) / 16)) * 16
    sgbm = sgbm_matcher(p, d_range[0], ndisp)
    l8f, r8f = np.ascontiguousarray(l8[:, ::-1]), np.ascontiguousarray(r8[:, ::-1])
    res = match_pair(left, right, d_range=d_range)
    rows: list[tuple[str, float]] = [
        ("cv2.StereoSGBM, one pass (uint8)", best_of(args.repeat, lambda: sgbm.compute(l8, r8))),
        (
            "cv2.StereoSGBM, two passes (LR + RL)",
            best_of(args.repeat, lambda: (sgbm.compute(l8, r8), sgbm.compute(r8f, l8f))),
        ),
        (
            "match_pair, one tile",
            best_of(
                args.repeat,
                lambda: match_pair(
                    left, right, d_range=d_range, tile_rows=args.size, tile_cols=args.size
                ),
            ),
        ),
        (
            "match_pair, 1024 px tiles, 64 px overlap",
            best_of(args.repeat, lambda: match_pair(left, right, d_range=d_range)),
        ),
        (
            "match_pair, 1024 px tiles, lr_check reduced",
            best_of(
                args.repeat,
                lambda: match_pair(
                    left, right, d_range=d_range, params=SgbmParams(lr_check="reduced")
                ),
            ),
        ),
        (
            "match_pair, lr_check reduced, min_ncc 0.7",
            best_of(
                args.repeat,
                lambda: match_pair(
                    left,
                    right,
                    d_range=d_range,
                    params=SgbmParams(lr_check="reduced", min_ncc=0.7),
                ),
            ),
        ),
        (
            "match_pair, 1024 px tiles, lr_check none",
            best_of(
                args.repeat,
                lambda: match_pair(
                    left, right, d_range=d_range, params=SgbmParams(lr_check="none")
                ),
            ),
        ),
    ]
    grid = OutputGrid(1.0, 0.0, 0.0, args.size, args.size)
    mapping = GroundMapping(
        grid,
        np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
        AffineModel.from_array([1, 0, 0.3, 0, 0, 1, 0, 0]),
    )
    dsm = make_dsm(res.disparity, 1.0, 0.0, mapping)
    rows.append(
        (
            "make_dsm (mean)",
            best_of(args.repeat, lambda: make_dsm(res.disparity, 1.0, 0.0, mapping)),
        )
    )
    rows.append(("orthoimage", best_of(args.repeat, lambda: orthoimage(left, dsm, mapping))))
    base = rows[0][1]
    print(
        f"pair {args.size} x {args.size} px ({mpx:.1f} Mpx), disparities {res.d_range}, "
        f"valid {100 * res.valid_share:.1f} %, OpenCV threads {cv2.getNumThreads()}"
    )
    print(f"{'step':44s} {'s':>8s} {'Mpx/s':>8s} {'x SGBM':>7s}")
    for name, t in rows:
        print(f"{name:44s} {t:8.3f} {mpx / t:8.2f} {t / base:7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
