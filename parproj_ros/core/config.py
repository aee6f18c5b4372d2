"""The pipeline's settings, built from the one parameter table (:mod:`parproj_ros.core.params`).

:class:`PipelineConfig` has one field per row of :data:`~parproj_ros.core.params.PARAMS` that
fills it, with the table's default; :func:`config_from_values` builds it from parameter values
as parproj_node has them, :func:`view_config` a :class:`ViewConfig` from a view's values. The
rows themselves are in :mod:`parproj_ros.core.params` (re-exported here), what they render
(docs/node.md's table, config/parproj_node.yaml) in :mod:`parproj_ros.core.param_docs`;
``python -m parproj_ros.core.config --write .`` still runs its writer.

Nothing here imports ROS.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, Literal

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


def _check_table() -> None:
    """The table and PipelineConfig agree (a field per row that fills one); raises if not."""
    filled = {p.field for p in PARAMS if p.field is not None}
    have = {f.name for f in fields(PipelineConfig)}
    if filled != have:
        raise AssertionError(f"config: PipelineConfig fields {have ^ filled} not in step")


_check_table()

if __name__ == "__main__":  # the writer's old entrance: python -m parproj_ros.core.config
    from .param_docs import main

    sys.exit(main())
