"""The one table of parproj_node's parameters, and the pipeline settings built from it.

Every parameter of parproj_node is one :class:`Param` row: :data:`PARAMS` (node-wide) or
:data:`VIEW_PARAMS` (per view, declared as ``<view>.<name>`` for each name in ``views``). A row
gives the type, default, unit, range or choices, description, and what the value fills (a
:class:`PipelineConfig` field, a view's camera, or the node itself). Everything else follows
from the table:

- parproj_node declares its parameters from it (descriptors with the ranges, descriptions with
  the units) and builds its :class:`PipelineConfig` with :func:`config_from_values`;
- ``parproj process`` has one option per row marked ``offline`` (the name with dashes, the same
  range and default);
- docs/node.md's Parameters table is :func:`parameters_markdown` and ``config/parproj_node.yaml``
  (every parameter at its default, for ``--params-file``) is :func:`parameters_yaml`;
  tests/core/test_params.py fails when either file differs. ``python -m
  parproj_ros.core.config --write .`` (from the repository) rewrites both.

Nothing here imports ROS.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:  # numpy and the geometry are imported when needed: `parproj` starts fast
    import numpy as np
    from numpy.typing import NDArray

    from ..geometry import LineCamera

    FloatArray = NDArray[np.float64]

#: ROS parameter types (rcl_interfaces/ParameterType names, lower case).
ParamType = Literal["bool", "integer", "double", "string", "string_array", "double_array"]

_PYTHON_TYPES: dict[str, type | tuple[type, ...]] = {
    "bool": bool,
    "integer": int,
    "double": float,
    "string": str,
    "string_array": list,
    "double_array": list,
}


@dataclass(frozen=True)
class Param:
    """One parameter of parproj_node.

    Attributes:
        name: the parameter name (per-view ones without the ``<view>.`` prefix).
        type: its ROS type.
        default: value when not given, of ``type``.
        description: what it does, without the unit (see ``unit``).
        unit: unit of the value ("m", "px", "s", "deg", ...); "" for none.
        low: lowest value accepted (numbers), or None.
        high: highest value accepted (numbers), or None.
        choices: the values accepted (strings); empty for any.
        read_only: set at start only (every parameter of parproj_node is).
        strict: no safe default: an invalid value ends the node (exit 2) instead of being
            replaced by the default.
        fills: what the value sets: ``PipelineConfig.<field>``, ``ViewConfig.<what>`` (per
            view), or ``node`` (parproj_node itself: its frame, timers, GCP file).
        offline: ``parproj process`` has an option for it (``--`` + the name with dashes).
        aliases: further option names of ``parproj process`` kept working.
        low_open: ``parproj process`` refuses ``low`` itself (ROS ranges are closed: the node
            accepts it).
        shown: the default as the README writes it ("" = formatted from ``default``).
    """

    name: str
    type: ParamType
    default: Any
    description: str
    unit: str = ""
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True
    strict: bool = False
    fills: str = "node"
    offline: bool = False
    aliases: tuple[str, ...] = ()
    low_open: bool = False
    shown: str = ""

    @property
    def field(self) -> str | None:
        """The :class:`PipelineConfig` field the value fills, or None."""
        prefix = "PipelineConfig."
        return self.fills[len(prefix) :] if self.fills.startswith(prefix) else None

    @property
    def option(self) -> str:
        """The ``parproj process`` option: ``--`` and the name with dashes."""
        return "--" + self.name.replace("_", "-")

    @property
    def range_text(self) -> str:
        """The range or the choices, in words ("0 .. 9000", "'linear', 'cubic'"); "" if none."""
        if self.choices:
            return ", ".join(repr(c) for c in self.choices)
        if self.low is None or self.high is None:
            return ""
        text = f"{_number(self.low)} .. {_number(self.high)}"
        return f"{text} (process: > {_number(self.low)})" if self.low_open else text

    @property
    def option_range_text(self) -> str:
        """The range of the ``parproj process`` option in words ("> 0 .. 9000"); "" if none."""
        if self.choices or self.low is None or self.high is None:
            return ""
        return f"{'> ' if self.low_open else ''}{_number(self.low)} .. {_number(self.high)}"

    @property
    def ros_description(self) -> str:
        """The description declared to ROS: with the unit in brackets."""
        return f"{self.description} [{self.unit}]" if self.unit else self.description


def _p(name: str, type_: ParamType, default: Any, description: str, **kw: Any) -> Param:
    """A pipeline parameter: fills the :class:`PipelineConfig` field of the same name."""
    return Param(name, type_, default, description, fills=f"PipelineConfig.{name}", **kw)


#: Node-wide parameters, in the order parproj_node declares them.
PARAMS: tuple[Param, ...] = (
    Param(
        "views",
        "string_array",
        ["left", "right"],
        "view names: two (left, right) for fore/aft cameras, or one for single-camera mode "
        "(consecutive scenes pair up); each a letter, then letters, digits or underscores; "
        "invalid: the node does not start (exit 2)",
        strict=True,
        fills="PipelineConfig.views",
    ),
    Param(
        "frame_id",
        "string",
        "",
        "object frame (local Cartesian, Z up, metres) of the outputs; '' = the frame of the "
        "inputs (header.frame_id of the first GCP or navigation message), 'map' until one "
        "names it; an input in another frame is a WARN naming both",
    ),
    _p(
        "scene_lines",
        "integer",
        0,
        "lines per scene; 0 = scenes end only on a gap, a frame_id change or the scene timeout",
        unit="lines",
        low=0,
        high=10_000_000,
        offline=True,
    ),
    _p(
        "max_gap_lines",
        "integer",
        64,
        "a larger jump between strips ends the scene; a smaller one is filled with nodata and "
        "reported",
        unit="lines",
        low=0,
        high=1_000_000,
        offline=True,
    ),
    _p(
        "z_avg",
        "double",
        0.0,
        "average terrain height (Eq 12; the zero-disparity height of the outputs)",
        unit="m",
        low=-1000.0,
        high=9000.0,
        offline=True,
    ),
    _p(
        "height_range",
        "double",
        500.0,
        "half range of terrain heights: virtual check points, and the 'overlap' output extent "
        "of a pair without GCP",
        unit="m",
        low=0.0,
        high=9000.0,
        offline=True,
        low_open=True,
    ),
    _p(
        "crab_tolerance_px",
        "double",
        0.05,
        "largest predicted crab-angle error accepted from Eqs 10-13; above it A1..A8 are fitted "
        "to the rigorous model",
        unit="px",
        low=0.0,
        high=1000.0,
        offline=True,
    ),
    Param(
        "scene_timeout",
        "double",
        2.0,
        "close the open scenes when no strip arrived for this long (wall clock), once the "
        "navigation has moved past them (or without navigation); 0 = never",
        unit="s",
        low=0.0,
        high=3600.0,
    ),
    _p(
        "gcp_roll",
        "string",
        "estimate",
        "with GCP: 'estimate' the roll (Eq 8), use the 'navigation' roll, or 'none' (no PTP)",
        choices=("estimate", "navigation", "none"),
        offline=True,
    ),
    _p(
        "min_gcp",
        "integer",
        5,
        "non-check GCP observed in a scene needed to use them instead of navigation",
        unit="points",
        low=4,
        high=100000,
        offline=True,
    ),
    Param(
        "gcp_file",
        "string",
        "",
        "CSV/YAML file of GCP loaded at start (format in parproj_ros/io/gcp_file.py; UTF-8, a "
        "regular file of at most 16 MiB); '' = none",
    ),
    _p(
        "nodata",
        "double",
        0.0,
        "output value outside a scene and for missing lines",
        unit="DN",
        low=-1e30,
        high=1e30,
        offline=True,
    ),
    _p(
        "interpolation",
        "string",
        "linear",
        "resampling (OpenCV remap): 'linear' or 'cubic'",
        choices=("linear", "cubic"),
        offline=True,
    ),
    _p(
        "output_pixel",
        "double",
        0.0,
        "normalized metres per output pixel; 0 = the scenes' native resolution",
        unit="m",
        low=0.0,
        high=1.0,
        offline=True,
    ),
    _p(
        "max_output_pixels",
        "integer",
        200_000_000,
        "larger normalized images are refused (the pair is skipped and reported)",
        unit="px",
        low=1,
        high=2_000_000_000,
        offline=True,
        shown="2e8",
    ),
    _p(
        "output_extent",
        "string",
        "overlap",
        "columns of the normalized pair: 'overlap' (the ground both scenes see, at the heights "
        "of the pair's terrain: see terrain) or 'union' (both footprints whole)",
        choices=("overlap", "union"),
        offline=True,
    ),
    _p(
        "terrain",
        "string",
        "tie_points",
        "heights of a pair's ground, for the dense matching's disparity range and the "
        "'overlap' output extent: 'tie_points' (measured from the pair: tie points matched on a "
        "reduced normalized pair, robust percentiles plus a margin; the prior below when too "
        "few agree, with a WARN) or 'prior' (the span of the pair's GCP, else z_avg +- "
        "height_range)",
        choices=("tie_points", "prior"),
        offline=True,
    ),
    _p(
        "tie_points",
        "bool",
        True,
        "refine whole-scene pairs with tie points matched between the normalized images "
        "(RANSAC on G1..G4), removing y-parallax left by biased navigation, GCP or RPC",
        offline=True,
    ),
    _p(
        "tie_threshold_px",
        "double",
        1.0,
        "RANSAC inlier threshold on the epipolar residual",
        unit="px",
        low=0.05,
        high=50.0,
        offline=True,
    ),
    _p(
        "heights",
        "bool",
        False,
        "dense matching of each normalized pair: disparity, heights per pixel, a DSM and an "
        "ortho-image (topics disparity, height, dsm)",
        offline=True,
    ),
    _p(
        "heights_margin_px",
        "double",
        8.0,
        "added to both ends of the disparity range predicted from the pair's height range",
        unit="px",
        low=0.0,
        high=1000.0,
        offline=True,
    ),
    _p(
        "heights_cell_m",
        "double",
        0.0,
        "DSM cell side; 0 = the ground sample distance of the left normalized image",
        unit="m",
        low=0.0,
        high=1.0e4,
        offline=True,
    ),
    _p(
        "heights_fill",
        "string",
        "nearest",
        "DSM holes: 'none' (left as NaN) or 'nearest' (holes of up to heights_max_fill_cells "
        "take the nearest measured height; counted in ElevationGrid.filled_cells)",
        choices=("none", "nearest"),
        offline=True,
    ),
    _p(
        "heights_max_fill_cells",
        "double",
        1.0,
        "largest DSM hole filled with heights_fill 'nearest'",
        unit="cells",
        low=0.0,
        high=100.0,
        offline=True,
    ),
    _p(
        "heights_matcher",
        "string",
        "sgbm_3way",
        "semi-global matcher: 'sgbm_3way' (OpenCV's 3-direction SGBM: fast) or 'sgbm_8path' "
        "(8 paths: on the Marseille pair 1-2, NMAD against s2p 0.77 m instead of 0.84 m, about "
        "7x slower and the cost volume in memory: width x height x disparities x 2 bytes per "
        "tile)",
        choices=("sgbm_3way", "sgbm_8path"),
        offline=True,
    ),
    _p(
        "heights_fuse_mb",
        "double",
        512.0,
        "DSMs of earlier pairs kept to fuse each new pair's DSM with those it overlaps (topic "
        "dsm_fused: per cell the weighted mean of the samples near their median, after the "
        "pairs' level offsets); oldest dropped first; 0 = no fusion",
        unit="MB",
        low=0.0,
        high=1.0e6,
        offline=True,
    ),
    _p(
        "heights_tile_px",
        "integer",
        1024,
        "side of the dense matching tiles (memory: a few tiles at a time)",
        unit="px",
        low=64,
        high=16384,
        offline=True,
    ),
    _p(
        "segment_max_error_px",
        "double",
        1.0,
        "model error bound of a long GCP/RPC scene: a pair whose parallel model misses its "
        "points by more is cut along track into segment pairs; 0 = never cut",
        unit="px",
        low=0.0,
        high=1000.0,
        offline=True,
        aliases=("--segment-max-error",),
    ),
    _p(
        "segment_overlap",
        "double",
        0.1,
        "fraction of a segment's length by which it extends into its neighbours",
        low=0.0,
        high=0.5,
        offline=True,
    ),
    _p(
        "streaming",
        "bool",
        True,
        "publish normalized column blocks while the scenes arrive (two views, scene_lines > 0, "
        "navigation-derived parameters); otherwise whole images after both scenes",
        offline=True,
    ),
    _p(
        "nav_jump_s",
        "double",
        10.0,
        "a navigation stamp this far from the newest one is suspicious: held until confirmed "
        "when ahead, dropped and reported when behind",
        unit="s",
        low=0.01,
        high=86400.0,
        offline=True,
    ),
    _p(
        "nav_position_tolerance_m",
        "double",
        5.0,
        "RMS of a scene's navigation positions about the constant-velocity line above which "
        "its navigation is reported as inconsistent",
        unit="m",
        low=0.0,
        high=1e6,
        offline=True,
    ),
    _p(
        "nav_history_s",
        "double",
        10.0,
        "navigation kept before the earliest line a scene may still need it for; older "
        "samples are forgotten, so memory stays flat",
        unit="s",
        low=0.0,
        high=86400.0,
        offline=True,
    ),
    _p(
        "start_margin_s",
        "double",
        0.5,
        "a view's first scene is taken to begin at its first strip only when navigation "
        "arrived from this long before it (else it may be the rest of a scene under way: "
        "skipped, ERROR); without any navigation the scene is taken whole",
        unit="s",
        low=0.0,
        high=3600.0,
        offline=True,
    ),
    Param(
        "worker_stall_s",
        "double",
        120.0,
        "the 1 Hz summary turns ERROR when the worker has been on one input (a strip, the "
        "scene or pair it completes) for longer than this; a full-size pair takes tens of s",
        unit="s",
        low=1.0,
        high=86400.0,
    ),
    Param(
        "error_hold_s",
        "double",
        60.0,
        "the 1 Hz summary stays at ERROR for this long after an ERROR status",
        unit="s",
        low=0.0,
        high=86400.0,
    ),
    Param(
        "memory_budget_mb",
        "double",
        6144.0,
        "bounds the node's resident memory: a pair (both scenes) is admitted at its first strip "
        "only if the start-up memory, the raw data held (line buffers, queued strips) or one raw "
        "pair for each pair in flight (admitted, not yet published) and the new one, and the "
        "working set (learnt from the memory held) fit in it less 5 % headroom; otherwise every "
        "strip of both its scenes is shed, counted and reported on /diagnostics "
        "(docs/performance.md, Overload). It must hold "
        "two pairs in flight (consecutive pairs overlap), or pairs are shed at any rate (the WARN "
        "names the least budget that would); 6144 MB: 3 IKONOS-size pairs (737 MB each) in flight "
        "with the 3.3 GB peak measured at that size",
        unit="MB",
        low=64.0,
        high=1e6,
    ),
    Param(
        "render_process",
        "bool",
        True,
        "streamed column blocks are rendered in a child process reading the line buffers from "
        "shared memory, out of the node's GIL (which the executor holds while it takes each "
        "strip: at the IKONOS rate the worker otherwise waited for it between tiles); false: in "
        "the worker thread. Falls back to the worker, with a WARN, when the child cannot start",
    ),
    Param(
        "prefault_mb",
        "double",
        -1.0,
        "memory touched at start so that the first pairs do not pay for first touches: this "
        "many MB of heap kept for messages, strips and blocks, plus, when > 0, two line "
        "buffers of scene_lines x detectors x 2 bytes per view; on the project's VMs a page "
        "touched for the first time costs 2.2 ms per MB against 0.05 once resident "
        "(docs/performance.md, At the full IKONOS rate). -1: two raw pairs of the configured "
        "scenes (scene_lines x detectors x 2 bytes, both views, twice: 1476 MB for IKONOS-size "
        "scenes), 0 when "
        "scene_lines is 0; 0: off, memory as needed",
        unit="MB",
        low=-1.0,
        high=1e6,
    ),
    Param(
        "stereo_pair_images",
        "bool",
        True,
        "a whole-image pair's StereoPair carries both normalized images (as they also go out on "
        "left/right/image_normalized); false: it carries none (empty images, as a streamed "
        "pair's), so each image is serialized and sent once",
    ),
    Param(
        "anaglyph",
        "bool",
        True,
        "publish the red/cyan anaglyph of each whole-image pair (a preview: a third copy of "
        "the pixels, and a fifth of the worker's time in a profile of the live node)",
    ),
    Param(
        "stop_timeout_s",
        "double",
        60.0,
        "at SIGINT/SIGTERM: longest wait for the worker to process what is queued and the open "
        "scenes; after it (or at a second signal) the node exits with code 1",
        unit="s",
        low=0.0,
        high=3600.0,
    ),
)

#: Per-view parameters, declared as ``<view>.<name>`` for each view in ``views``.
VIEW_PARAMS: tuple[Param, ...] = (
    Param(
        "principal_distance",
        "double",
        10.0,
        "principal distance c",
        unit="m",
        low=1e-4,
        high=100.0,
        fills="ViewConfig.camera.principal_distance",
    ),
    Param(
        "pixel_size",
        "double",
        12e-6,
        "detector pitch",
        unit="m",
        low=1e-7,
        high=1e-3,
        fills="ViewConfig.camera.pixel_size",
    ),
    Param(
        "detectors",
        "integer",
        13816,
        "detectors in the line",
        low=1,
        high=1_000_000,
        fills="ViewConfig.camera.detectors",
    ),
    Param(
        "principal_point",
        "double",
        -1.0,
        "sample coordinate of the principal point; -1 = line centre",
        unit="px",
        low=-1.0,
        high=1e6,
        fills="ViewConfig.camera.principal_point",
    ),
    Param(
        "line_period",
        "double",
        1.0 / 6500.0,
        "time between scan lines",
        unit="s",
        low=1e-7,
        high=10.0,
        fills="ViewConfig.camera.line_period",
        shown="1/6500",
    ),
    Param(
        "mounting_rpy_deg",
        "double_array",
        [0.0, 0.0, 0.0],
        "sensor frame in the body frame: roll, pitch, yaw, R = Rx(roll) Ry(pitch) Rz(yaw); 3 "
        "finite numbers within +-360 (integers are fine); invalid: the node does not start "
        "(exit 2)",
        unit="deg",
        strict=True,
        fills="ViewConfig.mounting",
    ),
    Param(
        "encoding",
        "string",
        "",
        "pixel encoding the camera delivers; strips of another encoding are dropped; '' = "
        "whatever a scene's first strip has",
        choices=("", "mono8", "mono16", "32FC1"),
        fills="ViewConfig.dtype",
    ),
)


_BY_NAME = {p.name: p for p in PARAMS}


def _default(name: str) -> Any:
    """The table's default of the node-wide parameter ``name`` (PipelineConfig's defaults)."""
    return _BY_NAME[name].default


def _identity() -> FloatArray:
    """The 3x3 identity (a mounting aligned with the body)."""
    import numpy as np

    return np.eye(3)


# ---- the settings the table fills --------------------------------------------------------------


@dataclass(frozen=True)
class ViewConfig:
    """One camera (view) of the platform.

    Attributes:
        name: view name, also the topic namespace ("left", "right", "fore", "aft", ...).
        camera: interior orientation.
        mounting: 3x3 rotation of the sensor frame in the body frame.
        dtype: expected pixel type ("uint8", "uint16", "float32"); None accepts the type of a
            scene's first strip.
    """

    name: str
    camera: LineCamera
    mounting: FloatArray = field(default_factory=lambda: _identity())
    dtype: str | None = None


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the pipeline: one field per parameter of :data:`PARAMS` that fills it.

    Names, defaults, units and ranges are the table's (the defaults below are read from it);
    the attributes are listed from it after this paragraph.
    """

    views: tuple[ViewConfig, ...]
    scene_lines: int = _default("scene_lines")
    max_gap_lines: int = _default("max_gap_lines")
    z_avg: float = _default("z_avg")
    height_range: float = _default("height_range")
    crab_tolerance_px: float = _default("crab_tolerance_px")
    gcp_roll: Literal["estimate", "navigation", "none"] = _default("gcp_roll")
    min_gcp: int = _default("min_gcp")
    nodata: float = _default("nodata")
    interpolation: Literal["linear", "cubic"] = _default("interpolation")
    output_pixel: float = _default("output_pixel")
    output_extent: Literal["overlap", "union"] = _default("output_extent")
    max_output_pixels: int = _default("max_output_pixels")
    streaming: bool = _default("streaming")
    terrain: Literal["tie_points", "prior"] = _default("terrain")
    tie_points: bool = _default("tie_points")
    tie_threshold_px: float = _default("tie_threshold_px")
    heights: bool = _default("heights")
    heights_margin_px: float = _default("heights_margin_px")
    heights_cell_m: float = _default("heights_cell_m")
    heights_fill: Literal["none", "nearest"] = _default("heights_fill")
    heights_max_fill_cells: float = _default("heights_max_fill_cells")
    heights_tile_px: int = _default("heights_tile_px")
    heights_fuse_mb: float = _default("heights_fuse_mb")
    heights_matcher: Literal["sgbm_3way", "sgbm_8path"] = _default("heights_matcher")
    nav_jump_s: float = _default("nav_jump_s")
    nav_position_tolerance_m: float = _default("nav_position_tolerance_m")
    segment_max_error_px: float = _default("segment_max_error_px")
    segment_overlap: float = _default("segment_overlap")
    start_margin_s: float = _default("start_margin_s")
    nav_history_s: float = _default("nav_history_s")

    @property
    def single_camera(self) -> bool:
        """Whether consecutive scenes of the one view form the pairs."""
        return len(self.views) == 1


def _attributes_doc() -> str:
    """The ``Attributes:`` section of PipelineConfig's docstring, from the table."""
    lines = ["", "    Attributes:"]
    for p in PARAMS:
        if p.field is None:
            continue
        unit = f" [{p.unit}]" if p.unit else ""
        text = f"{p.field}: {p.description}{unit}."
        lines += textwrap.wrap(
            text, 95, initial_indent=" " * 8, subsequent_indent=" " * 12, break_on_hyphens=False
        )
    return "\n".join(lines) + "\n"


PipelineConfig.__doc__ = (PipelineConfig.__doc__ or "") + _attributes_doc()


def view_config(name: str, values: Mapping[str, Any]) -> ViewConfig:
    """The :class:`ViewConfig` of view ``name`` from its :data:`VIEW_PARAMS` values.

    Args:
        name: the view name.
        values: parameter name (without the ``<view>.`` prefix) -> value, checked (ranges,
            choices, ``mounting_rpy_deg`` 3 finite angles in degrees); a name missing takes the
            table's default.
    """
    import numpy as np

    from ..geometry import LineCamera, rotation_from_angles
    from ..imaging.encodings import ENCODING_DTYPES

    v = {p.name: values.get(p.name, p.default) for p in VIEW_PARAMS}
    rpy = tuple(float(a) for a in v["mounting_rpy_deg"])
    pp = float(v["principal_point"])
    camera = LineCamera(
        float(v["principal_distance"]),
        float(v["pixel_size"]),
        int(v["detectors"]),
        float(v["line_period"]),
        None if pp < 0 else pp,
    )
    dtype = ENCODING_DTYPES.get(v["encoding"])  # "" accepts a scene's first strip's type
    return ViewConfig(
        name,
        camera,
        rotation_from_angles(*np.radians(rpy)),
        None if dtype is None else dtype.name,
    )


def view_values(view: ViewConfig) -> dict[str, Any]:
    """The :data:`VIEW_PARAMS` values of ``view``: the inverse of :func:`view_config`.

    Names without the ``<view>.`` prefix; the principal point is given explicitly (pixels), the
    mounting as roll, pitch, yaw in degrees, the encoding from the pixel type ("" for any).
    """
    import numpy as np

    from ..geometry import angles_from_rotation
    from ..imaging.encodings import DTYPE_ENCODINGS

    c = view.camera
    encodings = {dtype.name: enc for dtype, enc in DTYPE_ENCODINGS.items()}
    rpy = np.degrees(angles_from_rotation(view.mounting))
    return {
        "principal_distance": c.principal_distance,
        "pixel_size": c.pixel_size,
        "detectors": c.detectors,
        "principal_point": c.pp,
        "line_period": c.line_period,
        "mounting_rpy_deg": [float(a) for a in rpy],
        "encoding": encodings.get(view.dtype or "", ""),
    }


def _typed(p: Param, value: Any) -> Any:
    """``value`` as the Python type of ``p`` (ROS gives e.g. integers for some doubles)."""
    if p.type == "double":
        return float(value)
    if p.type == "integer":
        return int(value)
    if p.type == "bool":
        return bool(value)
    if p.type == "string":
        return str(value)
    return list(value)


def config_from_values(values: Mapping[str, Any]) -> PipelineConfig:
    """The :class:`PipelineConfig` that parameter values fill.

    Args:
        values: parameter name -> value, as parproj_node has them: node-wide names of
            :data:`PARAMS` and ``<view>.<name>`` for each view in ``views`` and name of
            :data:`VIEW_PARAMS`. Values must be checked already (ranges, choices, ``views``,
            mountings: the node does it as it declares them); a name missing takes the
            table's default; names that fill no PipelineConfig field are ignored.
    """
    views = tuple(
        view_config(
            name,
            {
                p.name: values[f"{name}.{p.name}"]
                for p in VIEW_PARAMS
                if f"{name}.{p.name}" in values
            },
        )
        for name in values.get("views", _default("views"))
    )
    settings = {
        p.field: _typed(p, values.get(p.name, p.default))
        for p in PARAMS
        if p.field is not None and p.field != "views"
    }
    return PipelineConfig(views=views, **settings)


# ---- what the table renders: README table, parameters file ------------------------------------


def _number(x: float) -> str:
    """A bound or default for people: 9000, 0.05, 1e-07, 2e+09 -> 2e9."""
    if float(x).is_integer() and abs(x) < 1e6:
        return str(int(x))
    text = f"{x:g}"
    return re.sub(r"e([-+])0*(\d)", lambda m: f"e{'-' if m[1] == '-' else ''}{m[2]}", text)


def _shown(p: Param) -> str:
    """The default of ``p`` as the README writes it."""
    if p.shown:
        return p.shown
    d = p.default
    if isinstance(d, bool):
        return "true" if d else "false"
    if isinstance(d, list):
        return "`[" + ", ".join(str(x) if isinstance(x, str) else _number(x) for x in d) + "]`"
    if isinstance(d, str):
        return f"`{d}`" if d else '`""`'
    if isinstance(d, float):
        return repr(d) if d.is_integer() and abs(d) < 1e7 else _number(d)
    return _number(d)


def _md(text: str) -> str:
    """Description text for a markdown table: 'x' quotes become code, pipes escaped."""
    text = re.sub(r"'([^' ]+)'", r"`\1`", text.replace("''", '`""`'))
    return text.replace("|", "\\|")


def _all_params() -> list[tuple[str, Param]]:
    """(shown name, row): node-wide parameters, then ``<view>.<name>``."""
    return [(p.name, p) for p in PARAMS] + [(f"<view>.{p.name}", p) for p in VIEW_PARAMS]


def parameters_markdown() -> str:
    """docs/node.md's Parameters table (markdown, ends with a newline)."""
    rows = [
        "| parameter | type | default | unit | range | `process` option | meaning |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, p in _all_params():
        rng = p.range_text
        option = f"`{p.option}`" if p.offline else ""
        if p.offline and p.type == "bool":
            option = f"`{p.option}`, `--no-{p.option[2:]}`"
        option += "".join(f", `{a}`" for a in p.aliases)
        ro = "" if p.read_only else " (can be changed while running)"
        rows.append(
            f"| `{name}` | {p.type} | {_shown(p)} | {p.unit} | {_md(rng)} | {option} "
            f"| {_md(p.description)}{ro} |"
        )
    return "\n".join(rows) + "\n"


def _yaml_scalar(value: Any) -> str:
    """``value`` in YAML that rcl and PyYAML read back as the same type and value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value)
        if "e" in text and "." not in text.split("e")[0]:
            mantissa, exp = text.split("e")
            text = f"{mantissa}.0e{exp}"  # YAML 1.1 floats need the dot
        return text
    if isinstance(value, str):
        return json.dumps(value)
    return "[" + ", ".join(_yaml_scalar(x) for x in value) + "]"


def _yaml_comment(p: Param, indent: str) -> list[str]:
    """Comment lines before ``p`` in the parameters file: description, then type, unit, range."""
    facts: list[str] = [p.type]
    if p.unit:
        facts.append(f"unit {p.unit}")
    if p.range_text:
        facts.append(("one of " if p.choices else "range ") + p.range_text)
    lines = textwrap.wrap(
        p.description,
        99,
        initial_indent=f"{indent}# ",
        subsequent_indent=f"{indent}# ",
        break_on_hyphens=False,
    )
    return [*lines, f"{indent}# ({', '.join(facts)})"]


def parameters_yaml() -> str:
    """A ``--params-file`` with every parameter of parproj_node at its default.

    Each parameter is preceded by a comment with its description, type, unit and range; the
    per-view parameters are given for each of the default ``views``.
    """
    lines = [
        "# parproj_node: every parameter at its default, with its type, unit and range.",
        "# Generated by parproj_ros.core.config.parameters_yaml() (checked by",
        "# tests/core/test_params.py): edit the table in parproj_ros/core/config.py, then:",
        "#   python -m parproj_ros.core.config --write .",
        "# Use: parproj_node --ros-args --params-file config/parproj_node.yaml",
        "# Every parameter is read-only (set at start).",
        "parproj_node:",
        "  ros__parameters:",
    ]
    for p in PARAMS:
        lines += _yaml_comment(p, "    ")
        lines.append(f"    {p.name}: {_yaml_scalar(p.default)}")
    for view in _default("views"):
        lines.append(f"    {view}:")
        for p in VIEW_PARAMS:
            lines += _yaml_comment(p, "      ")
            lines.append(f"      {p.name}: {_yaml_scalar(p.default)}")
    return "\n".join(lines) + "\n"


def default_values() -> dict[str, Any]:
    """Every parameter of parproj_node (``<view>.<name>`` for the default views) -> default."""
    out = {p.name: p.default for p in PARAMS}
    for view in _default("views"):
        out.update({f"{view}.{p.name}": p.default for p in VIEW_PARAMS})
    return out


#: The page that holds the generated Parameters table, relative to the repository.
NODE_DOC = "docs/node.md"
#: Markers around the generated table in :data:`NODE_DOC`.
README_BEGIN = (
    "<!-- parameters: generated from parproj_ros/core/config.py (parameters_markdown) -->"
)
README_END = "<!-- end of parameters -->"
#: Where the parameters file is, relative to the repository.
PARAMS_FILE = Path("config") / "parproj_node.yaml"


def readme_with_table(readme: str) -> str:
    """``readme`` with the text between the markers replaced by :func:`parameters_markdown`.

    Raises:
        ValueError: the markers are not there once each, in order.
    """
    begin, end = readme.find(README_BEGIN), readme.find(README_END)
    if readme.count(README_BEGIN) != 1 or readme.count(README_END) != 1 or end < begin:
        raise ValueError(f"{NODE_DOC} needs the lines {README_BEGIN!r} and {README_END!r}")
    head = readme[: begin + len(README_BEGIN)]
    return f"{head}\n{parameters_markdown()}{readme[end:]}"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m parproj_ros.core.config``: print the table, or rewrite the repo's copies."""
    parser = argparse.ArgumentParser(prog="python -m parproj_ros.core.config", description=__doc__)
    parser.add_argument(
        "--write",
        metavar="REPO",
        help="rewrite REPO/docs/node.md's table and REPO/config/parproj_node.yaml",
    )
    parser.add_argument("--yaml", action="store_true", help="print the parameters file")
    args = parser.parse_args(argv)
    if args.write:
        repo = Path(args.write)
        readme = repo / NODE_DOC
        readme.write_text(readme_with_table(readme.read_text()))
        (repo / PARAMS_FILE).parent.mkdir(exist_ok=True)
        (repo / PARAMS_FILE).write_text(parameters_yaml())
        print(f"wrote {readme} and {repo / PARAMS_FILE}")
    else:
        sys.stdout.write(parameters_yaml() if args.yaml else parameters_markdown())
    return 0


def _check_table() -> None:
    """The table and PipelineConfig agree (field per row, type, default); raises if not."""
    names = [p.name for p in PARAMS] + [f"<view>.{p.name}" for p in VIEW_PARAMS]
    if len(set(names)) != len(names):
        raise AssertionError("config: a parameter name is in the table twice")
    filled = {p.field for p in PARAMS if p.field is not None}
    have = {f.name for f in fields(PipelineConfig)}
    if filled != have:
        raise AssertionError(f"config: PipelineConfig fields {have ^ filled} not in step")
    for p in (*PARAMS, *VIEW_PARAMS):
        d: Any = p.default
        if not isinstance(d, _PYTHON_TYPES[p.type]) or (p.type != "bool" and isinstance(d, bool)):
            raise AssertionError(f"config: {p.name}: default {d!r} is not {p.type}")
        if p.low is not None and p.high is not None:
            if not (p.low <= p.default <= p.high and math.isfinite(p.high - p.low)):
                raise AssertionError(f"config: {p.name}: default out of its range")
        if p.choices and p.default not in p.choices:
            raise AssertionError(f"config: {p.name}: default not among the choices")


_check_table()

if __name__ == "__main__":
    sys.exit(main())
