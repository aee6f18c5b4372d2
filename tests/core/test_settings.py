"""PipelineConfig's settings groups, one per concern, built from the one parameter table.

Every row of PARAMS that fills the pipeline lands in exactly one group (the one named by its
concern) and every group field is such a row; the flat parameter names still construct and read
(the migration), and each group checks its own values.
"""

from __future__ import annotations

import pickle
from dataclasses import fields, replace
from typing import Literal, get_args, get_origin, get_type_hints

import pytest

from parproj_ros.core import config
from parproj_ros.core.config import (
    FLAT_NAMES,
    GROUPS,
    DenseSettings,
    OutputSettings,
    PipelineConfig,
    SceneSettings,
)
from parproj_ros.core.params import CONCERNS, PARAMS, VIEW_PARAMS
from parproj_ros.sim.synthetic import make_platform

VIEWS = tuple(make_platform(64, 64).views)


def test_each_pipeline_row_lands_in_exactly_one_group_and_back() -> None:
    filling = [p for p in PARAMS if p.fills.startswith("PipelineConfig.") and p.name != "views"]
    assert (
        len(filling) == 34
    )  # 30, dsm_cloud_step, heights_quicklook, heights_coarse, heights_scale
    places = {(c, f.name) for c, cls in GROUPS.items() for f in fields(cls)}
    targets = [p.target for p in filling]
    assert None not in targets
    assert len(set(targets)) == len(targets) == len(places)
    assert set(targets) == places
    for p in filling:
        assert p.target is not None and p.target[0] == p.concern, p.name
    assert set(FLAT_NAMES) == {p.name for p in filling}


def test_every_row_has_a_concern_and_every_concern_a_row() -> None:
    rows = (*PARAMS, *VIEW_PARAMS)
    assert {p.concern for p in rows} == set(CONCERNS)
    assert set(GROUPS) == set(CONCERNS) - {"views", "runtime"}
    assert all(p.concern == "views" for p in VIEW_PARAMS)
    assert {p.name for p in PARAMS if p.concern == "runtime"} >= {"memory_budget_mb"}


def test_group_defaults_are_the_table_defaults() -> None:
    cfg = PipelineConfig(VIEWS)
    for p in PARAMS:
        if p.target is not None:
            assert getattr(getattr(cfg, p.target[0]), p.target[1]) == p.default, p.name


def test_flat_and_grouped_construction_agree() -> None:
    flat = PipelineConfig(VIEWS, heights=True, heights_cell_m=2.5, scene_lines=7, tie_points=False)
    grouped = PipelineConfig(
        VIEWS,
        dense=DenseSettings(enabled=True, cell_m=2.5),
        scenes=SceneSettings(lines=7),
        ties=config.TiePointSettings(enabled=False),
    )
    assert flat == grouped
    assert (flat.dense.cell_m, flat.scenes.lines) == (2.5, 7)
    # A flat name over a group given: the group, with that setting changed.
    both = PipelineConfig(VIEWS, output=OutputSettings(nodata=-1.0), output_pixel=0.5)
    assert (both.output.nodata, both.output.pixel_m) == (-1.0, 0.5)


def test_replace_takes_flat_names_and_groups() -> None:
    cfg = PipelineConfig(VIEWS, scene_lines=100)
    on = replace(cfg, heights=True)
    assert on.dense.enabled and on.scenes.lines == 100 and not cfg.dense.enabled
    off = replace(cfg, stream=replace(cfg.stream, enabled=False))
    assert off.stream.enabled is False and off.scenes == cfg.scenes
    one = replace(cfg, views=cfg.views[:1])
    assert one.single_camera and one.scenes.lines == 100


def test_flat_names_not_read_and_unknown_refused() -> None:
    """A flat name builds a config but is not an attribute: settings are read by group."""
    cfg = PipelineConfig(VIEWS, heights=True)
    assert cfg.dense.enabled
    for name in config.FLAT_NAMES:
        assert not hasattr(cfg, name) or name in config.GROUPS, name
    with pytest.raises(AttributeError):
        cfg.dense = DenseSettings()  # type: ignore[misc]
    with pytest.raises(TypeError, match="heights_cellm"):
        PipelineConfig(VIEWS, heights_cellm=1.0)


def test_each_group_checks_its_own_values() -> None:
    with pytest.raises(ValueError, match=r"output\.interpolation \(interpolation\) = 'area'"):
        OutputSettings(interpolation="area")
    with pytest.raises(ValueError, match=r"dense\.tile_px \(heights_tile_px\)"):
        PipelineConfig(VIEWS, heights_tile_px=512.0)  # a double for an integer
    with pytest.raises(ValueError, match=r"dense\.enabled \(heights\)"):
        DenseSettings(enabled=1)  # type: ignore[arg-type]
    assert OutputSettings(nodata=3).nodata == 3  # an integer for a double is a number
    # Ranges are checked where values come in: --no-gcp sets min_gcp past its range.
    assert PipelineConfig(VIEWS, min_gcp=10**9).orientation.min_gcp == 10**9


def test_config_survives_pickling() -> None:
    """The render child process gets the config pickled."""
    cfg = PipelineConfig(VIEWS, heights=True, output_extent="union")
    back = pickle.loads(pickle.dumps(cfg))
    assert back.dense == cfg.dense and back.output == cfg.output and back.dense.enabled


def test_group_field_types_are_the_row_types() -> None:
    """Each field's annotation is its row's type; a closed set is the row's choices."""
    plain = {"bool": bool, "integer": int, "double": float, "string": str}
    rows = {p.target: p for p in PARAMS if p.target is not None}
    for concern, cls in GROUPS.items():
        hints = get_type_hints(cls)
        for f in fields(cls):
            p, hint = rows[(concern, f.name)], hints[f.name]
            if get_origin(hint) is Literal:
                assert set(get_args(hint)) == set(p.choices), p.name
            else:
                assert hint is plain[p.type], p.name
