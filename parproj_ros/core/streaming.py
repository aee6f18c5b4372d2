"""Streaming normalization: normalized output published while the scenes are still arriving.

Applies to two-view configurations (fore/aft cameras with one line clock) with a configured scene
length and navigation-derived parameters: when both views have started scene k and navigation
reaches the scenes' start, the motion is fitted on the latest navigation and extrapolated over the
scene (constant velocity and attitude, the model's own assumption), both scenes' parameters and
the normalization are derived, and the output grids are fixed. From then on every arriving strip
may complete column blocks of the normalized images: in along-track stereo the epipolar lines run
along track, so a normalized *row* spans the whole scene, while a block of normalized *columns*
needs only a window of scan lines. A block is resampled and emitted as soon as its last needed
line has arrived, and lines no later block needs are released, so memory and latency no longer
grow with the scene length. When both scenes are complete, the scene parameters and the pair
(without pixels) are emitted, and the extrapolated motion is checked against a fit on all the
navigation of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from ..imaging.assembly import Scene
from ..imaging.resample import OutputGrid, SceneGeometry, Tile, plan_tiles
from .results import PairGeometry, SceneResult

FloatArray = NDArray[np.float64]

#: Columns per streamed block (the tile size of the resampler, so blocks hold whole tiles).
BLOCK_COLS = 256
#: Lines of margin around the lines a tile's affine map reaches (bicubic needs 2).
LINE_MARGIN = 3


@dataclass
class _Block:
    col0: int
    cols: int
    tiles: list[Tile]
    min_line: int
    max_line: int


@dataclass
class SideStream:
    """The streaming state of one side of a pair."""

    side: str
    view: str
    result: SceneResult
    geom: SceneGeometry
    grid: OutputGrid
    lines: int
    blocks: list[_Block]
    next_block: int = 0
    done: bool = False
    prefetched: bool = False

    def needed_from(self) -> int:
        """First line any block still to come needs."""
        rest = self.blocks[self.next_block :]
        return min((b.min_line for b in rest), default=self.lines)


@dataclass
class StreamPair:
    """Streaming state of pair k."""

    index: int
    geometry: PairGeometry
    sides: dict[str, SideStream]
    stamp_ns: int
    scenes: dict[str, Scene] = field(default_factory=dict)


def plan_blocks(geom: SceneGeometry, grid: OutputGrid, lines: int) -> list[_Block]:
    """Column blocks of the output with the tiles they contain and the lines they need."""
    tiles = plan_tiles(geom, grid, tile=BLOCK_COLS)
    groups: dict[int, list[Tile]] = {}
    for t in tiles:
        groups.setdefault(t.col0 // BLOCK_COLS, []).append(t)
    blocks = []
    for b in sorted(groups):
        ts = groups[b]
        lo, hi = np.inf, -np.inf
        for t in ts:
            corners = np.array(
                [[0, 0, 1], [t.cols - 1, 0, 1], [0, t.rows - 1, 1], [t.cols - 1, t.rows - 1, 1]],
                dtype=float,
            )
            ln = corners @ t.affine[1]
            lo, hi = min(lo, ln.min()), max(hi, ln.max())
        col0 = b * BLOCK_COLS
        cols = min(BLOCK_COLS, grid.width - col0)
        blocks.append(
            _Block(
                col0,
                cols,
                ts,
                int(np.clip(np.floor(lo) - LINE_MARGIN, 0, lines)),
                int(np.clip(np.ceil(hi) + LINE_MARGIN, 0, lines - 1)),
            )
        )
    return blocks


def render_block(
    block: _Block,
    data: NDArray[np.generic],
    first_line: int,
    grid: OutputGrid,
    *,
    nodata: float,
    interpolation: int,
) -> NDArray[np.generic]:
    """Resample one column block from the retained lines ``data`` (line ``first_line`` first)."""
    out = np.empty((grid.height, block.cols), dtype=data.dtype)
    flags = interpolation | cv2.WARP_INVERSE_MAP
    for t in block.tiles:
        m = t.affine.copy()
        m[1, 2] -= first_line
        out[t.row0 : t.row0 + t.rows, t.col0 - block.col0 : t.col0 - block.col0 + t.cols] = (
            cv2.warpAffine(
                cast("NDArray[Any]", data),
                m,
                (t.cols, t.rows),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float(nodata),
            )
        )
    return out
