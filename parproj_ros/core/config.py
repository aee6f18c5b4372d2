"""The pipeline's settings, built from the one parameter table (:mod:`parproj_ros.core.params`).

:class:`PipelineConfig` holds the views and one frozen settings group per concern (each part
of the work checks its own settings): a group's fields are the rows of
:data:`~parproj_ros.core.params.PARAMS` of its concern, with the table's defaults
(``config.dense.cell_m`` is ``heights_cell_m``). :func:`config_from_values` builds it from
parameter values as parproj_node has them, :func:`view_config` a :class:`ViewConfig` from a
view's values. The rows themselves are in :mod:`parproj_ros.core.params` (re-exported here),
what they render (docs/node.md's table, config/parproj_node.yaml) in
:mod:`parproj_ros.core.param_docs`; ``python -m parproj_ros.core.config --write .`` still runs
its writer.

Nothing here imports ROS.
"""

from __future__ import annotations

import numbers
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from .params import PARAMS, VIEW_PARAMS, Param, ParamType
from .params import default as _default

if TYPE_CHECKING:  # numpy and the geometry are imported when needed: `parproj` starts fast
    import numpy as np
    from numpy.typing import NDArray

    from ..geometry import LineCamera

    FloatArray = NDArray[np.float64]

__all__ = [
    "PARAMS",
    "VIEW_PARAMS",
    "Param",
    "ParamType",
    "PipelineConfig",
    "ViewConfig",
    "config_from_values",
    "view_config",
    "view_values",
]


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


# The closed sets of the table's string settings, as types (checked against the rows' choices).
GcpRoll = Literal["estimate", "navigation", "none"]
OutputExtent = Literal["overlap", "union"]
TerrainChoice = Literal["tie_points", "prior"]
HeightsFill = Literal["none", "nearest"]
HeightsMatcher = Literal["sgbm_3way", "sgbm_8path"]
HeightsCoarse = Literal["none", "support", "ranges"]

#: (settings group, setting) -> its row of :data:`PARAMS`.
_ROWS: dict[tuple[str, str], Param] = {p.target: p for p in PARAMS if p.target is not None}


def _check_value(p: Param, value: Any) -> None:
    """Raises ValueError unless ``value`` has the type of ``p`` and is among its choices.

    Ranges are checked where values come in (the node's descriptors, ``parproj process``'s
    options): ``--no-gcp`` sets ``min_gcp`` past its range on purpose.
    """
    ok: bool
    if p.type == "bool":
        ok = isinstance(value, bool)
    elif p.type == "integer":
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    elif p.type == "double":
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    else:
        ok = isinstance(value, str) and (not p.choices or value in p.choices)
    if not ok:
        want = f"one of {p.range_text}" if p.choices else f"a {p.type}"
        raise ValueError(f"{p.fills} ({p.name}) = {value!r}: must be {want}")


class _Settings:
    """Base of the settings groups: each checks its own values against its rows.

    A group is a frozen dataclass named for its concern (:data:`CONCERN`); each field is one
    row of :data:`PARAMS` whose ``fills`` is ``PipelineConfig.<concern>.<field>``, with the
    row's default. Types and choices are checked at construction (ValueError naming the
    setting and the parameter).
    """

    CONCERN: ClassVar[str]

    def __post_init__(self) -> None:
        """Checks each value against its row (type, choices)."""
        for f in fields(self):  # type: ignore[arg-type]
            _check_value(_ROWS[(self.CONCERN, f.name)], getattr(self, f.name))


@dataclass(frozen=True)
class SceneSettings(_Settings):
    """How strips make scenes (concern ``scenes``)."""

    CONCERN: ClassVar[str] = "scenes"
    lines: int = _default("scene_lines")
    max_gap_lines: int = _default("max_gap_lines")


@dataclass(frozen=True)
class NavigationSettings(_Settings):
    """The navigation feed (concern ``navigation``)."""

    CONCERN: ClassVar[str] = "navigation"
    jump_s: float = _default("nav_jump_s")
    position_tolerance_m: float = _default("nav_position_tolerance_m")
    history_s: float = _default("nav_history_s")
    start_margin_s: float = _default("start_margin_s")


@dataclass(frozen=True)
class OrientationSettings(_Settings):
    """Each scene's parallel model: heights, crab tolerance, GCP use (concern ``orientation``)."""

    CONCERN: ClassVar[str] = "orientation"
    z_avg: float = _default("z_avg")
    height_range: float = _default("height_range")
    crab_tolerance_px: float = _default("crab_tolerance_px")
    gcp_roll: GcpRoll = field(default=_default("gcp_roll"))
    min_gcp: int = _default("min_gcp")

    @property
    def prior_heights(self) -> tuple[float, float]:
        """The terrain prior without GCP: ``z_avg`` -+ ``height_range`` [m]."""
        return (self.z_avg - self.height_range, self.z_avg + self.height_range)


@dataclass(frozen=True)
class SegmentSettings(_Settings):
    """Long GCP/RPC scenes cut into segment pairs (concern ``segments``)."""

    CONCERN: ClassVar[str] = "segments"
    max_error_px: float = _default("segment_max_error_px")
    overlap: float = _default("segment_overlap")


@dataclass(frozen=True)
class OutputSettings(_Settings):
    """The normalized pair's images (concern ``output``)."""

    CONCERN: ClassVar[str] = "output"
    nodata: float = _default("nodata")
    interpolation: str = _default("interpolation")
    pixel_m: float = _default("output_pixel")
    max_pixels: int = _default("max_output_pixels")
    extent: OutputExtent = field(default=_default("output_extent"))


@dataclass(frozen=True)
class TiePointSettings(_Settings):
    """Tie points between the normalized images, and the terrain from them (concern ``ties``)."""

    CONCERN: ClassVar[str] = "ties"
    terrain: TerrainChoice = field(default=_default("terrain"))
    enabled: bool = _default("tie_points")
    threshold_px: float = _default("tie_threshold_px")


@dataclass(frozen=True)
class DenseSettings(_Settings):
    """Dense matching: disparity, heights, DSM and its fusion (concern ``dense``)."""

    CONCERN: ClassVar[str] = "dense"
    enabled: bool = _default("heights")
    margin_px: float = _default("heights_margin_px")
    cell_m: float = _default("heights_cell_m")
    fill: HeightsFill = field(default=_default("heights_fill"))
    max_fill_cells: float = _default("heights_max_fill_cells")
    matcher: HeightsMatcher = field(default=_default("heights_matcher"))
    coarse: HeightsCoarse = field(default=_default("heights_coarse"))
    scale: int = _default("heights_scale")
    fuse_mb: float = _default("heights_fuse_mb")
    cloud_step: int = _default("dsm_cloud_step")
    tile_px: int = _default("heights_tile_px")
    quicklook: int = _default("heights_quicklook")


@dataclass(frozen=True)
class StreamSettings(_Settings):
    """Normalized column blocks while the scenes arrive (concern ``stream``)."""

    CONCERN: ClassVar[str] = "stream"
    enabled: bool = _default("streaming")


#: The settings groups of :class:`PipelineConfig`, by concern (its attribute names).
GROUPS: dict[str, type[_Settings]] = {
    cls.CONCERN: cls
    for cls in (
        SceneSettings,
        NavigationSettings,
        OrientationSettings,
        SegmentSettings,
        OutputSettings,
        TiePointSettings,
        DenseSettings,
        StreamSettings,
    )
}

#: The flat keywords :class:`PipelineConfig` accepts (the parameter names) -> (group, setting).
FLAT_NAMES: dict[str, tuple[str, str]] = {p.name: p.target for p in PARAMS if p.target is not None}


@dataclass(frozen=True, init=False)
class PipelineConfig:
    """Settings of the pipeline: the views and one settings group per concern.

    Each group is a frozen dataclass of the rows of :data:`PARAMS` with that concern
    (``config.dense.cell_m`` is ``heights_cell_m``, ``config.output.pixel_m`` is
    ``output_pixel``); names, defaults, units and ranges are the table's. A function that needs
    one concern takes that group, not the whole config.

    Construction: ``PipelineConfig(views, dense=DenseSettings(enabled=True))``, or with the
    flat parameter names as keywords (``PipelineConfig(views, heights=True, scene_lines=0)``,
    ``dataclasses.replace(config, heights=True)``): each sets its group's setting, over the
    group given or its defaults. Settings are read by group only (``config.dense.cell_m``).

    Attributes:
        views: the cameras, in ``views`` order.
        scenes: how strips make scenes (:class:`SceneSettings`).
        navigation: the navigation feed (:class:`NavigationSettings`).
        orientation: each scene's parallel model (:class:`OrientationSettings`).
        segments: long scenes cut into segment pairs (:class:`SegmentSettings`).
        output: the normalized images (:class:`OutputSettings`).
        ties: tie points and the terrain from them (:class:`TiePointSettings`).
        dense: dense matching, heights, DSM (:class:`DenseSettings`).
        stream: column blocks while the scenes arrive (:class:`StreamSettings`).
    """

    views: tuple[ViewConfig, ...]
    scenes: SceneSettings
    navigation: NavigationSettings
    orientation: OrientationSettings
    segments: SegmentSettings
    output: OutputSettings
    ties: TiePointSettings
    dense: DenseSettings
    stream: StreamSettings

    def __init__(
        self,
        views: Sequence[ViewConfig],
        *,
        scenes: SceneSettings | None = None,
        navigation: NavigationSettings | None = None,
        orientation: OrientationSettings | None = None,
        segments: SegmentSettings | None = None,
        output: OutputSettings | None = None,
        ties: TiePointSettings | None = None,
        dense: DenseSettings | None = None,
        stream: StreamSettings | None = None,
        **flat: Any,
    ) -> None:
        """The views, each group given (else its defaults), then the flat names in ``flat``.

        Raises:
            TypeError: a keyword that is no flat parameter name.
            ValueError: a value of the wrong type or not among its choices.
        """
        unknown = sorted(set(flat) - set(FLAT_NAMES))
        if unknown:
            raise TypeError(f"PipelineConfig() got unexpected keyword arguments {unknown}")
        given: dict[str, Any] = {
            "scenes": scenes,
            "navigation": navigation,
            "orientation": orientation,
            "segments": segments,
            "output": output,
            "ties": ties,
            "dense": dense,
            "stream": stream,
        }
        object.__setattr__(self, "views", tuple(views))
        for concern, cls in GROUPS.items():
            group: Any = given[concern] or cls()
            changes = {FLAT_NAMES[k][1]: v for k, v in flat.items() if FLAT_NAMES[k][0] == concern}
            object.__setattr__(self, concern, replace(group, **changes) if changes else group)

    @property
    def single_camera(self) -> bool:
        """Whether consecutive scenes of the one view form the pairs."""
        return len(self.views) == 1


def _attributes_doc(concern: str) -> str:
    """The ``Attributes:`` section of a group's docstring, from the table."""
    lines = ["", "    Attributes:"]
    for p in PARAMS:
        if p.target is None or p.target[0] != concern:
            continue
        unit = f" [{p.unit}]" if p.unit else ""
        text = f"{p.target[1]}: {p.description}{unit} (parameter ``{p.name}``)."
        lines += textwrap.wrap(
            text, 95, initial_indent=" " * 8, subsequent_indent=" " * 12, break_on_hyphens=False
        )
    return "\n".join(lines) + "\n"


for _cls in GROUPS.values():
    _cls.__doc__ = (_cls.__doc__ or "") + "\n" + _attributes_doc(_cls.CONCERN)


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
    settings: dict[str, dict[str, Any]] = {concern: {} for concern in GROUPS}
    for p in PARAMS:
        if p.target is not None:
            settings[p.target[0]][p.target[1]] = _typed(p, values.get(p.name, p.default))
    groups: dict[str, Any] = {c: cls(**settings[c]) for c, cls in GROUPS.items()}
    return PipelineConfig(views, **groups)


def _check_table() -> None:
    """The table and the groups agree: a field per row that fills one, of its type; or raises."""
    have = {(concern, f.name) for concern, cls in GROUPS.items() for f in fields(cls)}  # type: ignore[arg-type]
    if have != set(_ROWS):
        raise AssertionError(f"config: settings {sorted(have ^ set(_ROWS))} not in step")
    for cls in GROUPS.values():
        cls()  # every default passes its group's checks


_check_table()

if __name__ == "__main__":  # the writer's old entrance: python -m parproj_ros.core.config
    from .param_docs import main

    sys.exit(main())
