"""Assembling scenes from image strips (blocks of consecutive scan lines).

A strip is a 2-D array (lines, detectors) whose first line was exposed at ``stamp_ns``; line i of
the strip was exposed at ``stamp_ns + i * line_period``. A scene ends when it reaches its
configured length, when the next strip starts after a time gap, or when the scene id of the strip
(the image header's frame_id) changes. Bad strips are rejected with a reason and never reach a
scene; the caller logs and reports them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .resample import ENCODINGS


@dataclass(frozen=True)
class Scene:
    """A complete scene of one view.

    Attributes:
        view: the camera/view name ("left", "fore", ...).
        scene_id: identifier (the strips' frame_id, or view + sequence number).
        index: sequence number of this scene within its view, from 0.
        first_line_ns: exposure time of line 0, nanoseconds.
        line_period: seconds between lines.
        image: (lines, detectors) pixels, uint8 / uint16 / float32.
        gaps: number of missing lines that were filled with no-data.
        reason: why the scene was closed ("length", "gap", "scene_change", "flush").
    """

    view: str
    scene_id: str
    index: int
    first_line_ns: int
    line_period: float
    image: NDArray[np.generic]
    gaps: int = 0
    reason: str = "length"

    @property
    def lines(self) -> int:
        """Number of lines."""
        return int(self.image.shape[0])

    @property
    def detectors(self) -> int:
        """Number of detectors."""
        return int(self.image.shape[1])

    @property
    def last_line_ns(self) -> int:
        """Exposure time of the last line, nanoseconds."""
        return self.first_line_ns + round((self.lines - 1) * self.line_period * 1e9)


class StripRejectedError(ValueError):
    """A strip that cannot be used, with the reason (the scene it would belong to is unchanged)."""


@dataclass
class _Open:
    scene_id: str
    first_line_ns: int
    blocks: list[NDArray[np.generic]] = field(default_factory=list)
    lines: int = 0
    gaps: int = 0
    dtype: np.dtype | None = None
    width: int = 0


class SceneAssembler:
    """Collects strips of one view into scenes.

    Args:
        view: view name.
        line_period: seconds between lines.
        scene_lines: close a scene after this many lines (0 = no length limit).
        max_gap_lines: a jump of more than this many lines between strips closes the scene;
            a smaller positive jump is filled with ``nodata`` lines and counted in ``gaps``.
        nodata: fill value for missing lines.
    """

    def __init__(
        self,
        view: str,
        line_period: float,
        *,
        scene_lines: int = 0,
        max_gap_lines: int = 64,
        nodata: float = 0.0,
    ) -> None:
        self.view = view
        self.line_period = float(line_period)
        self.scene_lines = int(scene_lines)
        self.max_gap_lines = int(max_gap_lines)
        self.nodata = nodata
        self._open: _Open | None = None
        self._count = 0

    def _close(self, reason: str) -> Scene | None:
        op = self._open
        self._open = None
        if op is None or op.lines == 0:
            return None
        image = np.concatenate(op.blocks, axis=0) if len(op.blocks) > 1 else op.blocks[0]
        scene = Scene(
            self.view,
            op.scene_id,
            self._count,
            op.first_line_ns,
            self.line_period,
            image,
            op.gaps,
            reason,
        )
        self._count += 1
        return scene

    @property
    def is_open(self) -> bool:
        """Whether a scene is being assembled."""
        return self._open is not None

    def flush(self) -> list[Scene]:
        """Close the open scene (end of data)."""
        s = self._close("flush")
        return [s] if s is not None else []

    def add(self, stamp_ns: int, scene_id: str, strip: NDArray[np.generic]) -> list[Scene]:
        """Add one strip; return the scenes it completed (0, 1 or 2).

        Raises:
            StripRejectedError: the strip is empty, of an unsupported type, of another width or
                type than the open scene, or overlaps lines already received (duplicate or out of
                order). Nothing is changed then.
        """
        if strip.ndim != 2 or strip.shape[0] == 0 or strip.shape[1] == 0:
            raise StripRejectedError(
                f"strip has shape {strip.shape}: expected (lines >= 1, detectors)"
            )
        if strip.dtype not in ENCODINGS:
            raise StripRejectedError(f"unsupported pixel type {strip.dtype}")
        done: list[Scene] = []
        op = self._open
        if op is not None:
            expected = op.first_line_ns + round(op.lines * self.line_period * 1e9)
            jump = (stamp_ns - expected) / (self.line_period * 1e9)
            if scene_id != op.scene_id:
                done += [s for s in [self._close("scene_change")] if s]
            elif round(jump) < 0:
                raise StripRejectedError(
                    f"strip at {stamp_ns} ns starts {-round(jump)} lines before the end of "
                    "scene data already received (duplicate or out of order): dropped"
                )
            elif strip.shape[1] != op.width or strip.dtype != op.dtype:
                raise StripRejectedError(
                    f"strip is {strip.shape[1]} px {strip.dtype}, scene {op.scene_id} is "
                    f"{op.width} px {op.dtype}: dropped"
                )
            elif round(jump) > self.max_gap_lines:
                done += [s for s in [self._close("gap")] if s]
            elif round(jump) > 0:
                fill = np.full((round(jump), op.width), self.nodata, dtype=op.dtype)
                op.blocks.append(fill)
                op.lines += fill.shape[0]
                op.gaps += fill.shape[0]
        if self._open is None:
            self._open = _Open(scene_id, int(stamp_ns), dtype=strip.dtype, width=strip.shape[1])
        op = self._open
        block = np.ascontiguousarray(strip)
        while block.shape[0] > 0:
            room = self.scene_lines - op.lines if self.scene_lines > 0 else block.shape[0]
            take = block[:room]
            op.blocks.append(take)
            op.lines += take.shape[0]
            block = block[room:]
            if self.scene_lines > 0 and op.lines >= self.scene_lines:
                closed = self._close("length")
                if closed:
                    done.append(closed)
                if block.shape[0] > 0:
                    start = closed.last_line_ns if closed else stamp_ns
                    self._open = _Open(
                        scene_id,
                        start + round(self.line_period * 1e9),
                        dtype=strip.dtype,
                        width=strip.shape[1],
                    )
                    op = self._open
        return done
