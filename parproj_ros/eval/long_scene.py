"""Long scenes from a real RPC pair: how far one parallel model goes, and the segments it needs.

``parproj segments LEFT_RPC RIGHT_RPC``: the RPC of a full scene (not of a crop) gives its size
(2 line_off + 1 lines, 2 samp_off + 1 samples). A strip of ``width`` samples along the whole
scene, centred on the scene's middle column (and the right strip on the columns where it lands),
gets virtual GCP on a grid at heights spread over ``heights``; the pair is then cut with
:func:`parproj_ros.geometry.segmentation.segment_pair` for each bound, and independent check
points (another grid) measure the error reached in every segment.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry.segmentation import PairSegmentation, SideCamera, segment_pair
from ..io.scene_import import PIXEL_SIZE, PRINCIPAL_DISTANCE
from ..rpc import LocalTangentPlane, RPCError, RPCModel, VirtualGCP, read_rpc, virtual_gcp


@dataclass(frozen=True)
class RpcStrip:
    """A full-length strip of an RPC pair.

    Attributes:
        left: RPC of the left strip (columns shifted to the strip).
        right: RPC of the right strip.
        lines: (left, right) lines of the full scenes.
        width: samples of each strip.
        columns: (left, right) first column of the strips in the full scenes.
    """

    left: RPCModel
    right: RPCModel
    lines: tuple[int, int]
    width: int
    columns: tuple[int, int]

    def grid(
        self,
        heights: tuple[float, float],
        *,
        along: int,
        across: int = 5,
        levels: int = 3,
        shift: float = 0.0,
        frame: LocalTangentPlane | None = None,
    ) -> VirtualGCP:
        """Virtual GCP on ``along`` x ``across`` x ``levels`` points over the left strip.

        ``shift`` (lines) moves the grid (check points between the GCP); pass the GCP's
        ``frame`` so that both sets share one object frame.
        """
        w = self.width
        return virtual_gcp(
            self.left,
            self.right,
            lines=self.lines,
            samples=(w, w),
            heights=heights,
            grid=(across, along, levels),
            window=(shift, 2.0 + shift / 50.0, self.lines[0] - 1.0, w - 3.0),
            frame=frame,
        )


def rpc_strip(left: RPCModel, right: RPCModel, width: int, height: float = 1000.0) -> RpcStrip:
    """The strips of ``width`` samples along two full scenes (``height``: for the centring, m)."""
    nl, nr = int(2 * left.line_off + 1), int(2 * right.line_off + 1)
    s0 = int(left.samp_off) - width // 2
    h = np.array([height])
    lon, lat = left.localize(np.array([nl / 2.0]), np.array([s0 + width / 2.0]), h)
    r0 = round(float(right.project(lon, lat, h)[1][0])) - width // 2
    return RpcStrip(left.shifted(0.0, -s0), right.shifted(0.0, -r0), (nl, nr), width, (s0, r0))


def segment_strip(
    strip: RpcStrip, gcp: VirtualGCP, bound_px: float, *, overlap: float = 0.1
) -> PairSegmentation:
    """Cut the strip pair under ``bound_px`` using virtual GCP seen in both scenes."""
    idx = np.arange(len(gcp.points))
    cam = SideCamera(PRINCIPAL_DISTANCE, PIXEL_SIZE, (strip.width - 1) / 2.0)
    return segment_pair(
        gcp.points,
        gcp.left,
        gcp.points,
        gcp.right,
        (idx, idx),
        lines=strip.lines,
        cameras=(cam, cam),
        bound_px=bound_px,
        overlap=overlap,
    )


def check_errors(seg: PairSegmentation, check: VirtualGCP) -> float:
    """Largest error of independent check points over every segment, pixels."""
    worst = 0.0
    for side, ls in ((seg.left, check.left), (seg.right, check.right)):
        for s in side:
            inside = (ls[:, 0] >= s.start) & (ls[:, 0] <= s.stop - 1)
            if not inside.any():
                continue
            obs = s.frame.to_scene(ls[inside, 0] - s.start, ls[inside, 1])
            err = s.estimate.check(check.points[inside], obs) / PIXEL_SIZE
            worst = max(worst, float(np.hypot(err[:, 0], err[:, 1]).max()))
    return worst


def run(
    left_rpc: Path,
    right_rpc: Path,
    *,
    width: int = 400,
    heights: tuple[float, float] = (900.0, 1100.0),
    bounds: tuple[float, ...] = (1.0, 0.5, 0.3),
    overlap: float = 0.1,
) -> dict[str, Any]:
    """Segment the full-length strips of an RPC pair for each bound; a JSON-ready report.

    Raises:
        RPCError: an RPC whose denominator vanishes over its scene (named, with where).
    """
    models = (read_rpc(left_rpc), read_rpc(right_rpc))
    for path, m in zip((left_rpc, right_rpc), models, strict=True):
        # over the whole scene (11 x 11 pixels at 3 heights), before anything localizes
        g_l, g_s = np.meshgrid(
            np.linspace(0.0, 2 * m.line_off, 11), np.linspace(0.0, 2 * m.samp_off, 11)
        )
        hs = np.linspace(heights[0], heights[1], 3)
        why = m.image_denominator_check(g_l.ravel()[:, None], g_s.ravel()[:, None], hs)
        if why is not None:
            raise RPCError(f"{path}: {why.replace('the image', 'the scene')}: a damaged RPC")
    strip = rpc_strip(*models, width, sum(heights) / 2)
    gcp = strip.grid(heights, along=241)
    check = strip.grid(heights, along=97, shift=37.0, frame=gcp.frame)
    rows = []
    for b in bounds:
        seg = segment_strip(strip, gcp, b, overlap=overlap)
        rows.append(
            {
                "bound_px": b,
                "segments": seg.count,
                "whole_error_px": list(seg.whole_error_px),
                "max_error_px": seg.max_error_px,
                "check_max_error_px": check_errors(seg, check),
                "reached": seg.reached,
                "left_lines": [[s.start, s.stop] for s in seg.left],
                "right_lines": [[s.start, s.stop] for s in seg.right],
                "note": seg.note,
            }
        )
    return {
        "lines": list(strip.lines),
        "width": width,
        "columns": list(strip.columns),
        "heights_m": list(heights),
        "gcp": len(gcp.points),
        "check_points": len(check.points),
        "overlap": overlap,
        "runs": rows,
    }


def format_table(res: dict[str, Any]) -> str:
    """The report as a text table."""
    out = [
        f"strips of {res['width']} samples over {res['lines'][0]} / {res['lines'][1]} lines "
        f"(left / right), heights {res['heights_m'][0]:g}..{res['heights_m'][1]:g} m, "
        f"{res['gcp']} virtual GCP, {res['check_points']} check points",
        "bound px | segments | one model L / R px | segments max px | check max px | met",
    ]
    for r in res["runs"]:
        w = r["whole_error_px"]
        out.append(
            f"{r['bound_px']:8.3g} | {r['segments']:8d} | {w[0]:7.3f} / {w[1]:7.3f} | "
            f"{r['max_error_px']:15.3f} | {r['check_max_error_px']:12.3f} | "
            f"{'yes' if r['reached'] else 'no: ' + r['note']}"
        )
    return "\n".join(out)
