"""What the pipeline returns: issues, scene and pair results, and the closed sets they name.

The types that :mod:`.pipeline`, :mod:`.streaming`, :mod:`.tiepoints` and the adapters share
live here, below all of them, so that none of those modules needs another's. Nothing here imports
ROS: :mod:`parproj_ros.ros.conversions` turns these results into messages.

Closed sets are :class:`enum.StrEnum` members, so they are still the same strings in messages,
logs and JSON (``Level.WARN == "warn"``, ``f"{Method.NAVIGATION}" == "navigation"``); the
dataclasses below accept the plain strings too and store the member (an unknown value raises
``ValueError``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from ..geometry import (
    AffineModel,
    LineCamera,
    NavigationParameters,
    Normalization,
    ParallelProjection,
    PushbroomModel,
    SceneFrame,
)
from ..imaging.assembly import Scene, SceneEnd
from ..imaging.dense import DenseStatus
from ..imaging.fusion import FusedDsm
from ..imaging.heights import Dsm, DsmGrid
from ..imaging.resample import OutputGrid, SceneGeometry
from .terrain import Terrain

__all__ = [
    "METHODS",
    "BlockResult",
    "GroundPoint",
    "HeightTile",
    "HeightsResult",
    "Issue",
    "Level",
    "Method",
    "Outputs",
    "PairGeometry",
    "PairResult",
    "SceneEnd",
    "SceneResult",
    "YParallaxSource",
]

FloatArray = NDArray[np.float64]


class Level(StrEnum):
    """Severity of an :class:`Issue` (a diagnostic_msgs/DiagnosticStatus level)."""

    OK = "ok"
    WARN = "warn"
    ERROR = "error"


class Method(StrEnum):
    """How a scene's parameters were obtained (parproj_msgs/ParallelProjection ``method``).

    The order is that of the message's METHOD_* constants: the message carries the index.
    """

    NAVIGATION = "navigation"
    NAVIGATION_VIRTUAL_GCP = "navigation_virtual_gcp"
    GCP_AFFINE = "gcp_affine"
    GCP_KNOWN_ROLL = "gcp_known_roll"
    GCP_ROLL_ESTIMATED = "gcp_roll_estimated"
    TIE_POINTS = "tie_points"


#: Method names in message order (``METHODS.index(method)`` is the message's ``method``).
METHODS: tuple[str, ...] = tuple(m.value for m in Method)


class YParallaxSource(StrEnum):
    """Where a pair's y-parallax samples come from (parproj_msgs/StereoPair)."""

    GCP = "gcp"
    VIRTUAL = "virtual"
    TIE_POINTS = "tie_points"
    NONE = "none"


@dataclass(frozen=True)
class Issue:
    """A problem met, for the log and for diagnostics.

    Attributes:
        level: ok, warn or error (a plain string is accepted and stored as the member).
        where: the scene, view or input concerned.
        message: what was wrong and what was done about it.
    """

    level: Level
    where: str
    message: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "level", Level(self.level))


@dataclass(frozen=True)
class GroundPoint:
    """A ground control (or check) point.

    Attributes:
        id: name.
        xyz: object coordinates, metres, (3,).
        check: True for a check point (not used in the estimation).
        observations: scene_id -> (line, sample) pixels.
    """

    id: str
    xyz: FloatArray
    check: bool
    observations: dict[str, tuple[float, float]]


@dataclass(frozen=True)
class SceneResult:
    """Parameters of one scene.

    Attributes:
        scene: the assembled scene.
        params: non-linear parallel projection parameters.
        affine: A1..A8.
        psi: roll used for PTP, radians.
        frame: image <-> scene metres.
        method: how the parameters were obtained (a plain string is accepted).
        note: how and why the method was used.
        model: rigorous model from navigation (None when navigation did not cover the scene).
        camera: the view's camera (principal distance, pixel size, ...).
        sigma0_px: a-posteriori sigma0 of a GCP fit (or the virtual-point fit), pixels.
        residual_rms_px: RMS of per-point residual lengths, pixels.
        residual_max_px: largest residual length, pixels.
        gcp_count: GCP used.
        check_count: check points evaluated.
        check_rms_px: RMS check-point error, pixels (NaN without check points).
        covariance: 9x9 covariance of (A1..A8, psi) (zeros when not estimated).
        crab_angle: radians (NaN without navigation).
        segment_of: for a segment of a long scene, the scene it was cut from ("" otherwise).
        segment_first_line: the segment's line 0 is this line of ``segment_of``.
        model_error_bound_px: the bound the segmentation worked to, pixels (0: not cut).
    """

    scene: Scene
    params: ParallelProjection
    affine: AffineModel
    psi: float
    frame: SceneFrame
    method: Method
    note: str
    model: PushbroomModel | None
    camera: LineCamera
    sigma0_px: float = 0.0
    residual_rms_px: float = 0.0
    residual_max_px: float = 0.0
    gcp_count: int = 0
    check_count: int = 0
    check_rms_px: float = float("nan")
    covariance: FloatArray = field(default_factory=lambda: np.zeros((9, 9)))
    crab_angle: float = float("nan")
    segment_of: str = ""
    segment_first_line: int = 0
    model_error_bound_px: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", Method(self.method))

    @classmethod
    def from_navigation(
        cls,
        scene: Scene,
        nav: NavigationParameters,
        model: PushbroomModel,
        camera: LineCamera,
        *,
        note_suffix: str = "",
    ) -> SceneResult:
        """The result of a scene whose parameters come from navigation (Eqs 9-13 or the fit).

        sigma0 is NaN for Eqs 9-13 (nothing was fitted) and the virtual-point fit's RMS
        otherwise; ``note_suffix`` is appended to the method's note.
        """
        method = Method(nav.method)
        return cls(
            scene,
            nav.params,
            nav.affine,
            nav.psi,
            nav.frame,
            method,
            nav.note + note_suffix,
            model,
            camera,
            sigma0_px=(float("nan") if method == Method.NAVIGATION else nav.fit_rms_px),
            residual_rms_px=nav.fit_rms_px,
            crab_angle=nav.crab_angle,
        )

    def geometry(self, to_normalized: FloatArray) -> SceneGeometry:
        """Resampling geometry of this scene for a given normalization affine."""
        return SceneGeometry(self.frame, to_normalized, self.psi, self.camera.principal_distance)


@dataclass(frozen=True)
class PairGeometry:
    """Normalization and output grids of a pair, before any pixel is resampled."""

    pair_id: str
    normalization: Normalization
    left_geom: SceneGeometry
    right_geom: SceneGeometry
    left_grid: OutputGrid
    right_grid: OutputGrid


#: Below this share of pixels with data in both normalized images a pair is unusable: the
#: scenes see different ground (at the heights searched), nothing can be matched.
MIN_SHARED_SHARE = 0.05


@dataclass(frozen=True)
class PairResult:
    """A normalized stereo pair.

    Attributes:
        pair_id: "<left scene id>+<right scene id>".
        stamp_ns: the pair's stamp (the later scene's last line), nanoseconds.
        left: left scene parameters.
        right: right scene parameters.
        normalization: paper 2 Eq 8 result (2x3 affines, kappa_n, s_n, parallax relation).
        left_grid: output grid of the left image.
        right_grid: output grid of the right image (same rows, shifted columns).
        left_image: normalized left image (None when streamed block by block).
        right_image: normalized right image (None when streamed).
        height_per_disparity_px: a in Z = a (col_left - col_right) + b, metres per pixel.
        height_offset_m: b, metres.
        y_parallax_px: signed y-parallax samples used for the statistics, pixels.
        y_parallax_source: where they come from (a plain string is accepted).
        terrain: the heights of the pair's ground (for its heights step) and where they come
            from; None: not known yet (a streamed pair: measured on its images at step 7).
        shared_share: share of the normalized grid's pixels with data in both images, 0..1
            (None: a streamed pair, whose images are not held whole).
    """

    pair_id: str
    stamp_ns: int
    left: SceneResult
    right: SceneResult
    normalization: Normalization
    left_grid: OutputGrid
    right_grid: OutputGrid
    left_image: NDArray[np.generic] | None
    right_image: NDArray[np.generic] | None
    height_per_disparity_px: float
    height_offset_m: float
    y_parallax_px: FloatArray
    y_parallax_source: YParallaxSource
    terrain: Terrain | None = None
    shared_share: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "y_parallax_source", YParallaxSource(self.y_parallax_source))

    @property
    def unusable(self) -> bool:
        """Whether its normalized images share almost no ground (:data:`MIN_SHARED_SHARE`)."""
        return self.shared_share is not None and self.shared_share < MIN_SHARED_SHARE

    @property
    def y_parallax_stats(self) -> tuple[float, float, float]:
        """(mean |y|, rms, max |y|) in pixels (NaN when there are no samples)."""
        y = self.y_parallax_px
        if y.size == 0:
            return float("nan"), float("nan"), float("nan")
        return float(np.abs(y).mean()), float(np.sqrt(np.mean(y**2))), float(np.abs(y).max())


@dataclass(frozen=True)
class BlockResult:
    """A block of columns of one normalized image (streaming, see streaming.py).

    Attributes:
        pair_id: the pair.
        side: "left" or "right".
        index: block number from 0.
        col0: first column in the full normalized image.
        image: (full height, block columns) pixels.
        grid: the full image's output grid.
        stamp_ns: the pair's stamp (the later scene's last line), nanoseconds.
        last: whether this is the side's last block.
        draft: rendered with nearest-neighbour sampling for the quick-look only, nobody taking
            the block itself (:attr:`~.streaming.Streamer.draft`): not to be published.
    """

    pair_id: str
    side: str
    index: int
    col0: int
    image: NDArray[np.generic]
    grid: OutputGrid
    stamp_ns: int
    last: bool
    draft: bool = False


@dataclass(frozen=True)
class HeightsResult:
    """Heights of one normalized pair.

    Attributes:
        pair_id: the pair.
        stamp_ns: the pair's stamp, nanoseconds.
        status: the matching's outcome (``ok`` or why there are no heights).
        message: the outcome in words.
        d_range: (dmin, dmax) searched, pixels (``col_left - col_right``).
        valid_share: valid disparities / left pixels with data.
        disparity: float32 (rows, cols) in the left normalized grid, pixels, NaN invalid.
        height: float32, same grid, ``a d + b`` metres, NaN invalid.
        dsm: the DSM (None unless ``status`` is ok).
        ortho: the left normalized image on the DSM grid (None with ``dsm``); nodata where the
            DSM has none.
        height_per_disparity_px: a, metres per pixel.
        height_offset_m: b, metres.
        max_fill_cells: largest hole filled in the DSM, cells (0: none filled).
        terrain: the heights searched (``d_range`` before its margin) and where they come from.
    """

    pair_id: str
    stamp_ns: int
    status: DenseStatus
    message: str
    d_range: tuple[int, int]
    valid_share: float
    disparity: NDArray[np.float32]
    height: NDArray[np.float32]
    dsm: Dsm | None
    ortho: NDArray[np.generic] | None
    height_per_disparity_px: float
    height_offset_m: float
    max_fill_cells: float = 0.0
    terrain: Terrain | None = None

    @property
    def ok(self) -> bool:
        """Whether there is a DSM."""
        return self.status == DenseStatus.OK and self.dsm is not None


@dataclass(frozen=True)
class HeightTile:
    """One streamed DSM tile of a pair: the heights of a span of left columns (core/tiles.py).

    The pair's DSM grid (:attr:`pair_grid`) is chosen when its first tile is made; each of its
    cells belongs to exactly one tile (the tile holding the left column its centre maps to at
    the terrain's mid height), so the tiles assembled (:func:`~parproj_ros.core.tiles.
    assemble_tiles`) are the pair's DSM, without seams. A tile is final when emitted.

    Attributes:
        pair_id: the pair.
        index: tile number from 0 (left columns increasing).
        count: tiles of the pair.
        factor: reduction of the normalized images matched (1: full resolution; 2, 4, 8: the
            quick-look, ``heights_quicklook`` 1, 2, 3).
        col0: first left column of the span, in the level's pixels.
        cols: columns of the span, in the level's pixels.
        status: the matching's outcome (``ok``, or why the tile has no DSM).
        message: the outcome in words.
        d_range: (dmin, dmax) searched, pixels of the level (the same for every tile of a pair).
        valid_share: valid disparities / left pixels with data in the span.
        disparity: float32 (rows, cols) of the span's own columns, pixels of the level, NaN
            invalid.
        dsm: the cells of ``pair_grid`` the tile owns, on the bounding sub-grid of those cells
            (NaN: not owned or no height); None unless ``status`` is ok.
        owned: bool, same shape as ``dsm.heights``: the cells this tile owns.
        ortho: the left normalized image on ``dsm``'s grid (nodata where no height).
        pair_grid: the pair's whole DSM grid (every tile of the pair has the same).
        height_per_disparity_px: a in ``Z = a d + b``, metres per pixel of the level.
        height_offset_m: b, metres.
        terrain: the heights searched and where they come from (the pair's own, measured on
            the first window's tie points, or the prior).
        stretch: ((low, high) left, (low, high) right) DN mapped to 0 and 255 for the matcher,
            taken from the pair's first window and kept for all its tiles.
        stamp_ns: the pair's stamp, nanoseconds.
        last: whether this is the pair's last tile.
    """

    pair_id: str
    index: int
    count: int
    factor: int
    col0: int
    cols: int
    status: DenseStatus
    message: str
    d_range: tuple[int, int]
    valid_share: float
    disparity: NDArray[np.float32]
    dsm: Dsm | None
    owned: NDArray[np.bool_] | None
    ortho: NDArray[np.generic] | None
    pair_grid: DsmGrid | None
    height_per_disparity_px: float
    height_offset_m: float
    terrain: Terrain
    stretch: tuple[tuple[float, float], tuple[float, float]]
    stamp_ns: int
    last: bool

    @property
    def ok(self) -> bool:
        """Whether the tile has a DSM."""
        return self.status == DenseStatus.OK and self.dsm is not None

    @property
    def name(self) -> str:
        """The message's ``pair_id``: ``<pair>#<index>/<count>`` (quick-look: ``@<factor>``)."""
        level = f"@{self.factor}" if self.factor > 1 else ""
        return f"{self.pair_id}#{self.index}/{self.count}{level}"


@dataclass(frozen=True)
class FusedResult:
    """The DSMs of overlapping pairs fused into one (:mod:`~parproj_ros.core.fusion`).

    Attributes:
        pair_ids: the pairs fused, oldest first.
        stamp_ns: the stamp of the newest pair, nanoseconds.
        fused: the fused heights, count and spread layers, grid and level offsets.
    """

    pair_ids: tuple[str, ...]
    stamp_ns: int
    fused: FusedDsm

    @property
    def name(self) -> str:
        """The message's ``pair_id``: ``fused:`` and the pair ids joined by commas."""
        return "fused:" + ",".join(self.pair_ids)


@dataclass
class Outputs:
    """What one call of the pipeline produced."""

    scenes: list[SceneResult] = field(default_factory=list)
    pairs: list[PairResult] = field(default_factory=list)
    issues: list[Issue] = field(default_factory=list)
    blocks: list[BlockResult] = field(default_factory=list)
    heights: list[HeightsResult] = field(default_factory=list)
    fused: list[FusedResult] = field(default_factory=list)
    #: Streamed DSM tiles (full resolution and quick-look), in the order made.
    tiles: list[HeightTile] = field(default_factory=list)

    def extend(self, other: Outputs) -> None:
        """Append another call's outputs."""
        self.scenes += other.scenes
        self.pairs += other.pairs
        self.issues += other.issues
        self.blocks += other.blocks
        self.heights += other.heights
        self.fused += other.fused
        self.tiles += other.tiles
