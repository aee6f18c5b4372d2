"""Streamed DSM tiles (core/tiles.py, issue 26): made while the pass arrives, equal to the DSM
of the whole pair, a broken stream ended with its tiles and a status.

The fore/aft bag streams one pair of 768 x 791 normalized pixels: the left scene is complete
before the right one starts (it sees the ground first), so the left blocks come at once and the
right ones at right strips 5, 9 and 12 of 12. Tile 0 (left columns 0..256) needs the right
columns up to 256 + 64 (overlap) + |dmin| + 1, i.e. the right block 1: it must come with right
strip 9, before the pass ends.

Tolerances. The tiles and the whole pair are the same matcher on the same pixels; they differ
only in the SGM paths' context beyond a window (TILE_OVERLAP columns kept), the stretch limits
(the first window's, against the whole image's) and the disparity range (measured on the first
window against the whole pair). That is the matcher's sub-pixel noise: a quarter of a pixel of
parallax, |a| / 4 metres (the disparities come in 1/16 px steps; the left-right check accepts
1 px), bounds the NMAD of the difference and a tenth of a pixel its median; the cells measured
in one and not the other are those where the left-right check or the speckle filter decided
differently, a few per cent. A seam would show as a larger difference along the tile borders:
the same bounds hold on the cells next to a border.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import pytest
from testkit.paths import BAGS

from parproj_ros.core.heights import HeightsStage, assemble_tiles, heights_from_tiles, options_of
from parproj_ros.core.params import PARAMS
from parproj_ros.core.pipeline import Pipeline
from parproj_ros.core.render_process import RenderProcess
from parproj_ros.core.results import Level, Outputs
from parproj_ros.core.tiles import TILE_COLS, TileStage, tiles_of_pair
from parproj_ros.imaging.heights import Dsm, DsmGrid
from parproj_ros.ros import conversions as conv
from parproj_ros.ros.bag import BagReader
from parproj_ros.ros.inputs import config_from_bag

pytestmark = pytest.mark.ros  # reads a bag

BAG = BAGS / "airborne_foreaft"
LINES = 768
STRIPS = {"left/image_strip": "left", "right/image_strip": "right"}


def _pipeline(quicklook: int = 0) -> Pipeline:
    """A pipeline of the bag's configuration with heights on and ``heights_quicklook``."""
    cfg = config_from_bag(
        BagReader(BAG), scene_lines=LINES, heights=True, tie_points=False,
        heights_quicklook=quicklook,
    )  # fmt: skip
    return Pipeline(cfg)


def _all(calls: list[tuple[str, Outputs]], flushed: Outputs) -> Outputs:
    """Every output of a :func:`_run`, in order, in one Outputs."""
    out = Outputs()
    for _, o in calls:
        out.extend(o)
    out.extend(flushed)
    return out


def _run(
    quicklook: int = 0, drop_last_right: int = 0, pipe: Pipeline | None = None
) -> tuple[list[tuple[str, Outputs]], Outputs]:
    """The bag fed message by message: [(input kind, outputs)], and the flush's outputs.

    ``pipe``: the pipeline to feed (set up by the caller); else :func:`_pipeline`.
    """
    reader = BagReader(BAG)
    pipe = _pipeline(quicklook) if pipe is None else pipe
    items = [i for i in reader.messages() if i.topic == "navigation" or i.topic in STRIPS]
    rights = [k for k, i in enumerate(items) if i.topic == "right/image_strip"]
    skip = set(rights[len(rights) - drop_last_right :]) if drop_last_right else set()
    calls: list[tuple[str, Outputs]] = []
    for k, item in enumerate(items):
        if k in skip:
            continue
        if item.topic == "navigation":
            calls.append(("navigation", pipe.add_navigation(conv.odometry_to_sample(item.msg))))
            continue
        strip = conv.image_to_array(item.msg)
        out = pipe.add_strip(
            STRIPS[item.topic],
            conv.stamp_to_ns(item.msg.header.stamp),
            item.msg.header.frame_id,
            strip,
        )
        calls.append((item.topic, out))
    return calls, pipe.flush()


@pytest.fixture(scope="module")
def streamed() -> dict[str, Any]:
    calls, flushed = _run(quicklook=2)  # 1/4
    out = Outputs()
    for _, o in calls:
        out.extend(o)
    out.extend(flushed)
    # The reference: the whole-pair heights step on the pair's blocks joined (what step 7
    # did for a streamed pair before its tiles stood for it).
    cfg = config_from_bag(BagReader(BAG), scene_lines=LINES, heights=True, tie_points=False)
    ref = HeightsStage(options_of(cfg))(Outputs(pairs=list(out.pairs), blocks=list(out.blocks)))
    (whole,) = ref.heights
    return {"calls": calls, "flushed": flushed, "out": out, "whole": whole}


def _on_grid(dsm: Dsm, grid: DsmGrid) -> np.ndarray:
    """``dsm``'s heights at the cell centres of ``grid`` (cells on multiples of one size)."""
    step = round(grid.cell / dsm.grid.cell)
    assert abs(grid.cell - step * dsm.grid.cell) < 1e-9 * grid.cell
    rows = np.rint((dsm.grid.y0 - (grid.y0 - grid.cell * np.arange(grid.height))) / dsm.grid.cell)
    cols = np.rint(((grid.x0 + grid.cell * np.arange(grid.width)) - dsm.grid.x0) / dsm.grid.cell)
    r, c = rows.astype(int), cols.astype(int)
    out = np.full((grid.height, grid.width), np.nan, dtype=np.float32)
    rv = (r >= 0) & (r < dsm.grid.height)
    cv = (c >= 0) & (c < dsm.grid.width)
    out[np.ix_(rv, cv)] = dsm.heights[np.ix_(r[rv], c[cv])]
    return out


def _nmad(d: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def test_tiles_come_while_the_pass_arrives(streamed: dict[str, Any]) -> None:
    calls, flushed = streamed["calls"], streamed["flushed"]
    full = [(k, t) for k, (_, o) in enumerate(calls) for t in o.tiles if t.factor == 1]
    assert not flushed.tiles
    tiles = [t for _, t in full]
    width = streamed["out"].heights[0].disparity.shape[1]
    n = -(-width // TILE_COLS)
    assert [t.index for t in tiles] == list(range(n)) and n == 3
    assert [t.last for t in tiles] == [False] * (n - 1) + [True]
    assert all(t.ok and t.count == n for t in tiles), [t.message for t in tiles]
    assert [t.col0 for t in tiles] == [i * TILE_COLS for i in range(n)]
    # The first tile comes in the outputs of a right strip before the last one: the pass has
    # not ended (right strip 9 of 12 completes the right block its window needs).
    rights = [k for k, (kind, _) in enumerate(calls) if kind == "right/image_strip"]
    first = full[0][0]
    assert calls[first][0] == "right/image_strip"
    assert rights.index(first) < len(rights) - 1
    assert rights.index(first) == 8  # right strip 9: its window reaches right column 370
    # Every tile of the pair searched the same range, terrain and stretch, measured once.
    assert len({(t.d_range, t.terrain, t.stretch) for t in tiles}) == 1
    assert tiles[0].terrain.source == "tie_points"


def test_assembled_tiles_equal_the_whole_pair_dsm(streamed: dict[str, Any]) -> None:
    out, whole = streamed["out"], streamed["whole"]
    assert whole.ok
    tiles = [t for t in out.tiles if t.factor == 1]
    # Each cell of the pair's grid belongs to one tile at most.
    pg = tiles[0].pair_grid
    owners = np.zeros((pg.height, pg.width), dtype=int)
    for t in tiles:
        g = t.dsm.grid
        r0, c0 = round((pg.y0 - g.y0) / pg.cell), round((g.x0 - pg.x0) / pg.cell)
        owners[r0 : r0 + g.height, c0 : c0 + g.width] += t.owned
    assert owners.max() == 1
    dsm = assemble_tiles(tiles)
    assert dsm is not None
    ref = _on_grid(whole.dsm, dsm.grid)
    a = abs(whole.height_per_disparity_px)
    both = np.isfinite(ref) & np.isfinite(dsm.heights)
    diff = (dsm.heights - ref)[both]
    print(
        f"|a| {a:.3f} m/px: NMAD {_nmad(diff):.4f} m, median {np.median(diff):.4f} m, "
        f"whole {np.isfinite(whole.dsm.heights).sum()} cells, tiles "
        f"{np.isfinite(dsm.heights).sum()}, both {both.sum()}"
    )
    assert _nmad(diff) <= a / 4
    assert abs(float(np.median(diff))) <= a / 10
    n_whole = int(np.isfinite(whole.dsm.heights).sum())
    assert both.sum() >= 0.97 * n_whole
    assert np.isfinite(dsm.heights).sum() <= 1.03 * n_whole
    # No seam: the cells next to an ownership border agree as well as the others.
    border = np.zeros_like(owners, dtype=bool)
    for t in tiles[1:]:
        g = t.dsm.grid
        r0, c0 = round((pg.y0 - g.y0) / pg.cell), round((g.x0 - pg.x0) / pg.cell)
        own = np.zeros_like(border)
        own[r0 : r0 + g.height, c0 : c0 + g.width] = t.owned
        edge = own ^ np.roll(own, 1, axis=1) | own ^ np.roll(own, -1, axis=1)
        for s in range(-3, 4):
            border |= np.roll(edge, s, axis=1)
    near = border & both
    assert near.sum() > 500
    d_near = (dsm.heights - ref)[near]
    print(f"border cells {near.sum()}: NMAD {_nmad(d_near):.4f} m")
    assert _nmad(d_near) <= a / 4
    assert abs(float(np.median(d_near))) <= a / 10


def test_tiles_matched_at_half_resolution_equal_the_whole_pair_dsm() -> None:
    """``heights_scale`` 2 reaches the streamed tiles: they match at half resolution as the
    whole-pair step does, and assembled they are its DSM within the same bounds."""
    cfg = config_from_bag(
        BagReader(BAG), scene_lines=LINES, heights=True, tie_points=False, heights_scale=2
    )
    pipe = Pipeline(cfg)
    calls, flushed = _run(pipe=pipe)
    out = _all(calls, flushed)
    tiles = [t for t in out.tiles if t.factor == 1]
    assert tiles and all(t.ok for t in tiles), [t.message for t in tiles]
    assert options_of(cfg).scale == 2
    ref = HeightsStage(options_of(cfg))(Outputs(pairs=list(out.pairs), blocks=list(out.blocks)))
    (whole,) = ref.heights
    dsm = assemble_tiles(tiles)
    assert dsm is not None and whole.dsm is not None
    on = _on_grid(whole.dsm, dsm.grid)
    a = abs(whole.height_per_disparity_px)
    both = np.isfinite(on) & np.isfinite(dsm.heights)
    diff = (dsm.heights - on)[both]
    print(f"|a| {a:.3f} m/px: NMAD {_nmad(diff):.4f} m, median {np.median(diff):.4f} m")
    assert _nmad(diff) <= a / 4
    assert abs(float(np.median(diff))) <= a / 10
    assert both.sum() >= 0.97 * int(np.isfinite(whole.dsm.heights).sum())


def test_quicklook_tiles_follow_the_dsm(streamed: dict[str, Any]) -> None:
    out = streamed["out"]
    (whole,) = out.heights
    quick = [t for t in out.tiles if t.factor == 4]
    assert quick and all(t.ok for t in quick) and quick[-1].last
    dsm = assemble_tiles(quick)
    assert dsm is not None
    assert dsm.grid.cell == pytest.approx(4 * whole.dsm.grid.cell, rel=1e-9)
    ref = _on_grid(whole.dsm, dsm.grid)
    both = np.isfinite(ref) & np.isfinite(dsm.heights)
    diff = (dsm.heights - ref)[both]
    a4 = abs(quick[0].height_per_disparity_px)
    assert a4 == pytest.approx(4 * abs(whole.height_per_disparity_px), rel=1e-9)
    print(f"quick-look |a| {a4:.3f} m/px: NMAD {_nmad(diff):.4f} m over {both.sum()} cells")
    # One reduced pixel of parallax: the reduced images cannot resolve finer, and a reduced
    # cell averages 4 x 4 full-resolution cells of the relief.
    assert _nmad(diff) <= a4 / 4
    assert abs(float(np.median(diff))) <= a4 / 4
    assert both.sum() >= 0.95 * np.isfinite(ref).sum()


def test_tile_messages_carry_the_owned_cells(streamed: dict[str, Any]) -> None:
    out = streamed["out"]
    msgs = conv.outputs_to_messages(out, frame_id="map", stamp_ns=0)
    tiles = [m for topic, m, _ in msgs if topic == "dsm_tile"]
    quick = [m for topic, m, _ in msgs if topic == "dsm_quicklook_tile"]
    full = [t for t in out.tiles if t.factor == 1]
    assert [m.pair_id for m in tiles] == [t.name for t in full]
    assert tiles[0].pair_id == f"{full[0].pair_id}#0/3" and quick[0].pair_id.endswith("@4")
    for m, t in zip(tiles, full, strict=True):
        heights, grid, ortho = conv.elevation_grid_from_msg(m)
        np.testing.assert_array_equal(heights, t.dsm.heights)
        assert grid == t.dsm.grid and ortho.shape == heights.shape
        assert m.terrain_source == "tie_points" and (m.disparity_min, m.disparity_max) == t.d_range


def test_a_broken_stream_ends_with_its_tiles_and_a_status() -> None:
    # The last two right strips lost: the right scene ends short at the flush, the streamer
    # abandons the pair; the tile its blocks covered stays, an ERROR says the rest.
    calls, flushed = _run(drop_last_right=2)
    tiles = [t for _, o in calls for t in o.tiles] + flushed.tiles
    assert [t.index for t in tiles] == [0] and tiles[0].ok and not tiles[0].last
    errors = [i for i in flushed.issues if i.level == Level.ERROR and "DSM tiles" in i.message]
    assert len(errors) == 1, flushed.issues
    e = errors[0]
    assert e.where == f"pair {tiles[0].pair_id}"
    assert "stopped after 1 of 3" in e.message and "left columns 0..256 of 768" in e.message
    assert "abandoned" in e.message  # the streamer's reason, quoted
    assert not flushed.pairs and not flushed.heights


def test_quicklook_factor_sign_and_range() -> None:
    reader = BagReader(BAG)

    def stage(q: int) -> TileStage:
        cfg = config_from_bag(reader, scene_lines=LINES, heights=True, heights_quicklook=q)
        return TileStage(cfg, {})

    assert {q: [lv.factor for lv in stage(q).levels] for q in (0, 1, 2, 3, -2)} == {
        0: [1],
        1: [1, 2],
        2: [1, 4],
        3: [1, 8],
        -2: [4],
    }
    row = next(p for p in PARAMS if p.name == "heights_quicklook")
    assert (row.low, row.high, row.default) == (-3, 3, 0)  # every value in range is valid


def test_no_tiles_without_streaming() -> None:
    cfg = config_from_bag(BagReader(BAG), heights=True)  # no scene_lines: no streaming
    assert not TileStage.applies(cfg)
    assert Pipeline(cfg).tiles is None


@pytest.fixture(scope="module")
def whole_pair() -> dict[str, Any]:
    """The fore/aft pair normalized whole (not streamed), and its settings with heights on."""
    reader = BagReader(BAG)
    cfg = config_from_bag(
        reader, scene_lines=LINES, heights=True, tie_points=False, streaming=False
    )
    calls: list[tuple[str, Outputs]] = []
    pipe = Pipeline(cfg)
    for item in reader.messages(topics=["navigation", *STRIPS]):
        if item.topic == "navigation":
            calls.append(("nav", pipe.add_navigation(conv.odometry_to_sample(item.msg))))
        else:
            arr = conv.image_to_array(item.msg)
            stamp = conv.stamp_to_ns(item.msg.header.stamp)
            calls.append(
                ("strip", pipe.add_strip(STRIPS[item.topic], stamp, item.msg.header.frame_id, arr))
            )
    pairs = [p for _, o in calls for p in o.pairs] + pipe.flush().pairs
    (pair,) = pairs
    return {"pair": pair, "config": cfg}


def test_tiles_of_a_whole_pair_fed_as_blocks(
    streamed: dict[str, Any], whole_pair: dict[str, Any]
) -> None:
    # The benchmarks' path: a pair normalized whole, cut into 256-column blocks fed left,
    # right, left, ...: tile 0 once both sides hold column 370 (2 blocks each), the same DSM
    # as the streamed tiles (the blocks of a whole pair differ from the streamed ones by
    # 1 DN at most, test_streaming.py).
    pair, cfg = whole_pair["pair"], whole_pair["config"]
    got = tiles_of_pair(cfg, pair, pair.left_image, pair.right_image)
    assert [(fed, t.index) for fed, t in got] == [(4, 0), (6, 1), (6, 2)]
    mine = assemble_tiles([t for _, t in got])
    ref = assemble_tiles([t for t in streamed["out"].tiles if t.factor == 1])
    assert mine is not None and ref is not None
    g, h = mine.grid, ref.grid
    assert (g.width, g.height) == (h.width, h.height)
    assert (g.x0, g.y0, g.cell) == pytest.approx((h.x0, h.y0, h.cell), abs=1e-6 * h.cell)
    both = np.isfinite(mine.heights) & np.isfinite(ref.heights)
    a = abs(got[0][1].height_per_disparity_px)
    assert both.sum() >= 0.97 * np.isfinite(ref.heights).sum()
    assert _nmad((mine.heights - ref.heights)[both]) <= a / 4


def test_heights_of_the_tiles_stand_for_the_whole_pair(streamed: dict[str, Any]) -> None:
    # heights_from_tiles: the pair's HeightsResult from its tiles, not matched again; against
    # the whole-pair step: the same grid of left pixels, disparities within the matcher's
    # noise (a quarter of a pixel, NMAD), the same share matched within 2 %.
    out, whole = streamed["out"], streamed["whole"]
    res = heights_from_tiles([t for t in out.tiles if t.factor == 1], max_fill_cells=1.0)
    assert res is not None and res.ok and res.pair_id == whole.pair_id
    assert res.disparity.shape == whole.disparity.shape
    both = np.isfinite(res.disparity) & np.isfinite(whole.disparity)
    assert both.sum() >= 0.97 * np.isfinite(whole.disparity).sum()
    assert _nmad((res.disparity - whole.disparity)[both]) <= 0.25
    assert abs(res.valid_share - whole.valid_share) <= 0.02
    np.testing.assert_allclose(
        res.height[both], res.height_per_disparity_px * res.disparity[both] + res.height_offset_m
    )
    assert res.ortho is not None and res.ortho.shape == res.dsm.heights.shape
    has = np.isfinite(res.dsm.heights)
    assert (res.ortho[has] > 0).mean() > 0.99 and np.all(res.ortho[~has] == 0)
    print(f"valid share tiles {res.valid_share:.4f}, whole {whole.valid_share:.4f}")


def test_a_tall_first_window_is_measured_by_row_bands(whole_pair: dict[str, Any]) -> None:
    # At IKONOS size a window of 256 columns has some 13,816 rows: measure_terrain reduces it
    # to 1,024 rows and some 20 columns, too few for tie points. The pair stacked 14 times
    # (11,074 rows) is such a window: measured whole, the prior; by bands of 1,024 rows, the
    # terrain of the pair (the same ground 14 times: the single window's, within its margin).
    from parproj_ros.core.terrain import Terrain, TerrainSource, measure_terrain
    from parproj_ros.core.tiles import _Geometry, _window_terrain

    pair = whole_pair["pair"]
    n = 256
    left = np.tile(pair.left_image[:, :n], (14, 1))
    right = np.tile(pair.right_image[:, :n], (14, 1))
    grids = [replace(g, width=n, height=left.shape[0]) for g in (pair.left_grid, pair.right_grid)]
    prior = Terrain(-500.0, 500.0, TerrainSource.PRIOR)
    whole = measure_terrain(left, right, *grids, pair.normalization, prior, nodata=0.0)
    assert whole.source == TerrainSource.PRIOR
    geo = _Geometry(
        pair.pair_id, pair.normalization, pair.left.affine, grids[0], grids[1], pair.stamp_ns
    )
    banded = _window_terrain(left, right, geo, prior, 0.0)
    one = _window_terrain(pair.left_image[:, :n], pair.right_image[:, :n], geo, prior, 0.0)
    assert banded.source == one.source == TerrainSource.TIE_POINTS
    print(f"banded {banded.describe()}; one window {one.describe()}")
    a = abs(pair.height_per_disparity_px)
    assert banded.low_m == pytest.approx(one.low_m, abs=4 * a)
    assert banded.high_m == pytest.approx(one.high_m, abs=4 * a)
    assert banded.points > 3 * one.points


def test_step7_takes_a_streamed_pairs_heights_from_its_tiles(streamed: dict[str, Any]) -> None:
    """The pipeline's heights of a streamed pair are its tiles assembled (to the bit), not a
    second matching of the whole pair (issue 26: the tiles are the full-resolution DSM)."""
    out = streamed["out"]
    (got,) = out.heights
    tiles = [t for t in out.tiles if t.factor == 1]
    assert got.message.endswith(f"in {len(tiles)} tiles"), got.message
    dsm = assemble_tiles(tiles)
    assert dsm is not None and got.dsm is not None
    np.testing.assert_array_equal(got.dsm.heights, dsm.heights)
    assert got.disparity.shape == streamed["whole"].disparity.shape


def test_quicklook_only_makes_no_full_resolution_heights(monkeypatch: pytest.MonkeyPatch) -> None:
    """``heights_quicklook`` -2: streamed pairs get their 1/4 tiles and nothing at full
    resolution: no block kept for step 7, no whole-pair matching (measure_heights is never
    called), an OK line saying so; the run's verdict counts the tiles as its heights."""
    from parproj_ros.apps.commands.process import verdict
    from parproj_ros.apps.process import ProcessSummary
    from parproj_ros.core import heights

    def never(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the whole pair was matched")

    monkeypatch.setattr(heights, "measure_heights", never)
    calls, flushed = _run(quicklook=-2)
    out = Outputs()
    for _, o in calls:
        out.extend(o)
    out.extend(flushed)
    assert out.pairs and not out.heights
    assert out.tiles and {t.factor for t in out.tiles} == {4} and all(t.ok for t in out.tiles)
    said = [i for i in out.issues if "quick-look tiles stand for them" in i.message]
    assert [i.level for i in said] == ["ok"] * len(out.pairs)
    summary = ProcessSummary(pairs=len(out.pairs), tiles=[(t.pair_id, t.ok) for t in out.tiles])
    assert verdict(summary, heights=True) == 0
    assert verdict(ProcessSummary(pairs=1), heights=True) == 1  # neither DSM nor tiles


def test_reduce_block_is_reduce_image_to_the_bit() -> None:
    # The quick-look's reduction (core/tiles.reduce_block) against core/terrain.reduce_image:
    # the same block means and the same no-data pixels (a reduced pixel whose block holds a
    # no-data pixel), with no-data at the image's edges, one isolated pixel, and none.
    from parproj_ros.core.terrain import reduce_image
    from parproj_ros.core.tiles import reduce_block
    from parproj_ros.imaging.resample import OutputGrid

    rng = np.random.default_rng(5)
    img = rng.integers(1, 2048, size=(203, 261)).astype(np.uint16)
    img[:17, :40] = 0  # a scene's corner
    img[120, 77] = 0  # one pixel
    grid = OutputGrid(1.0, 0.0, 0.0, img.shape[1], img.shape[0])
    for f in (2, 4, 8):
        for a in (img, img[40:, 60:], img[:, 100:200]):
            want, _ = reduce_image(a, grid, f, 0.0)
            got = reduce_block(a, f, 0.0)
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
    # a no-data value inside the data's range
    want, _ = reduce_image(img, grid, 4, 1000.0)
    np.testing.assert_array_equal(reduce_block(img, 4, 1000.0), want)


def _moved(right: np.ndarray, col: int, px: int) -> np.ndarray:
    """The right image with its content from column ``col`` on moved ``px`` columns left: the
    left pixels whose partners lie there get ``px`` more disparity (a step in the terrain)."""
    out = right.copy()
    out[:, col : right.shape[1] - px] = right[:, col + px :]
    return out


def test_the_range_widens_where_later_terrain_leaves_it(
    whole_pair: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    # The range is measured on the first window (-49..14 px searched here); the right image's
    # content from column 400 on moved 40 px: tiles 1 and 2 see disparities up to 40 px above
    # their own (tile 2: 21..48 px), beyond the range. Without widening, half of tile 1's
    # pixels are lost; with it, the tiles that crowd the range's end widen it and are matched
    # again: tile 2 keeps its share within the 40 right columns whose content the move
    # dropped (40 / 256 of its columns), and its range holds its disparities.
    from parproj_ros.core import tiles as core_tiles

    pair, cfg = whole_pair["pair"], whole_pair["config"]
    step = 40
    right = _moved(pair.right_image, 400, step)
    plain = [t for _, t in tiles_of_pair(cfg, pair, pair.left_image, pair.right_image)]
    wide = [t for _, t in tiles_of_pair(cfg, pair, pair.left_image, right)]
    monkeypatch.setattr(core_tiles, "MAX_WIDENINGS", 0)
    fixed = [t for _, t in tiles_of_pair(cfg, pair, pair.left_image, right)]
    assert len({t.d_range for t in plain}) == 1  # no widening on the unmoved pair
    assert wide[0].d_range == fixed[0].d_range == plain[0].d_range
    hi = float(np.nanpercentile(plain[2].disparity, 99.5)) + step
    print(
        "shares plain / fixed / widened: "
        + ", ".join(
            f"tile {i} {p.valid_share:.3f} / {f.valid_share:.3f} / {w.valid_share:.3f}"
            for i, (p, f, w) in enumerate(zip(plain, fixed, wide, strict=True))
        )
        + f"; ranges {[t.d_range for t in wide]}"
    )
    assert fixed[1].valid_share < 0.6 * plain[1].valid_share  # lost without widening
    assert wide[2].d_range[1] >= hi and fixed[2].d_range[1] < hi
    assert wide[2].valid_share >= plain[2].valid_share - step / TILE_COLS
    # tile 1 holds the step itself (SGM's smoothness spreads across it): half its loss back
    assert (
        wide[1].valid_share
        >= fixed[1].valid_share + (plain[1].valid_share - fixed[1].valid_share) / 2
    )
    dsms = [t.dsm for t in (plain[2], fixed[2], wide[2])]
    cells = [int(np.isfinite(d.heights).sum()) for d in dsms if d is not None]
    assert len(cells) == 3
    assert cells[2] >= (1 - step / TILE_COLS) * cells[0] > cells[1]


def test_a_quicklook_whose_prior_fits_16_disparities_measures_no_tie_points() -> None:
    # heights_quicklook 3 (1/8) and a prior of -10..0 m: 1.74 m per reduced pixel of parallax,
    # the prior and its 2 px margin fit SGBM's fewest 16 disparities, so the quick-look level
    # measures no tie points (they could not narrow the search); the full resolution does.
    from parproj_ros.core.tiles import _searched

    reader = BagReader(BAG)
    cfg = config_from_bag(
        reader,
        scene_lines=LINES,
        heights=True,
        tie_points=False,
        heights_quicklook=3,
        z_avg=-5.0,
        height_range=5.0,
    )
    pipe = Pipeline(cfg)
    out = Outputs()
    for item in reader.messages(topics=["navigation", *STRIPS]):
        if item.topic == "navigation":
            out.extend(pipe.add_navigation(conv.odometry_to_sample(item.msg)))
        else:
            arr = conv.image_to_array(item.msg)
            stamp = conv.stamp_to_ns(item.msg.header.stamp)
            out.extend(pipe.add_strip(STRIPS[item.topic], stamp, item.msg.header.frame_id, arr))
    out.extend(pipe.flush())
    quick = [t for t in out.tiles if t.factor == 8]
    full = [t for t in out.tiles if t.factor == 1]
    assert quick and all(t.ok for t in quick) and full
    a, b = quick[0].height_per_disparity_px, quick[0].height_offset_m
    assert _searched(a, b, quick[0].terrain, 2.0) == 16
    assert quick[0].terrain.source == "prior" and full[0].terrain.source == "tie_points"
    said = [i.message for i in out.issues if "quick-look (1/8) DSM tiles" in i.message]
    assert len(said) == 1 and "tie points not measured" in said[0]


def test_the_stage_says_its_quicklook_and_the_bytes_it_holds(whole_pair: dict[str, Any]) -> None:
    # The admission's hooks: a quick-look level or not, and the columns held for the tiles
    # to come (both sides, every level): after the first block of each side, exactly those
    # blocks (full resolution) and their 1/4 reductions (the quick-look).
    from parproj_ros.core.results import BlockResult

    pair, cfg = whole_pair["pair"], whole_pair["config"]
    assert not TileStage(cfg, {}).quicklook
    stage = TileStage(replace(cfg, dense=replace(cfg.dense, quicklook=2)), {})
    assert stage.quicklook and stage.held_bytes() == 0
    kept = 0
    for side, img, grid in (
        ("left", pair.left_image, pair.left_grid),
        ("right", pair.right_image, pair.right_grid),
    ):
        part = np.ascontiguousarray(img[:, :TILE_COLS])
        stage.keep(BlockResult(pair.pair_id, side, 0, 0, part, grid, pair.stamp_ns, False), [pair])
        rows, cols = part.shape[0] // 4, part.shape[1] // 4
        kept += part.nbytes + rows * cols * part.itemsize
    assert stage.held_bytes() == kept


def test_the_quicklook_is_shed_and_resumed(whole_pair: dict[str, Any]) -> None:
    # The admission's switch (core/pipeline.py passes the ledger's quicklook_shed): shed while
    # a pair is under way, its quick-look stops (columns freed, a WARN naming the pair and
    # the tiles made) and the full resolution goes on to its last tile; resumed, the next
    # pair gets its quick-look tiles again, and the pair shed meanwhile stays without.
    pair, cfg = whole_pair["pair"], whole_pair["config"]
    stage = TileStage(replace(cfg, dense=replace(cfg.dense, quicklook=2)), {})
    from parproj_ros.core.results import BlockResult

    def feed(pid: str, col0: int = 0, col1: int | None = None) -> list[Any]:
        p = replace(pair, pair_id=pid)
        got: list[Any] = []
        width = pair.left_image.shape[1]
        starts = list(range(0, width, TILE_COLS))
        for i, c0 in enumerate(starts):
            if c0 < col0 or (col1 is not None and c0 >= col1):
                continue
            for side, img, grid in (
                ("left", pair.left_image, pair.left_grid),
                ("right", pair.right_image, pair.right_grid),
            ):
                part = np.ascontiguousarray(img[:, c0 : c0 + TILE_COLS])
                last = i == len(starts) - 1
                stage.keep(BlockResult(pid, side, i, c0, part, grid, 0, last), [p])
                got += stage(Outputs(), blocks=False).tiles
        return got

    first = feed("a", col1=TILE_COLS)  # one block of each side: pair a under way
    assert stage.held_bytes() > 0 and not first
    said = stage.shed_quicklook(True)
    assert [(i.level, i.where) for i in said] == [(Level.WARN, "pair a")]
    assert "quick-look (1/4) DSM tiles shed after 0 of 1" in said[0].message
    assert stage.shed_quicklook(True) == []  # no change, nothing said
    rest = feed("a", col0=TILE_COLS)
    assert [(t.factor, t.index) for t in rest] == [(1, 0), (1, 1), (1, 2)]
    assert {t.factor for t in feed("b")} == {1}  # pair b starts while shed
    assert stage.shed_quicklook(False)[0].level == Level.OK
    again = feed("c")
    assert {t.factor for t in again} == {1, 4} and [t.index for t in again if t.factor == 4] == [0]
    assert stage.held_bytes() == 0


def test_a_borrowed_block_is_copied_at_full_resolution_only(whole_pair: dict[str, Any]) -> None:
    # keep(borrowed=True): the caller's pixels may change after the call (the streamer's
    # view); the full resolution holds a copy, the quick-look its reduction: both unchanged
    # when the caller's array is overwritten.
    from parproj_ros.core.results import BlockResult
    from parproj_ros.core.tiles import reduce_block

    pair, cfg = whole_pair["pair"], whole_pair["config"]
    stage = TileStage(replace(cfg, dense=replace(cfg.dense, quicklook=2)), {})
    view = np.ascontiguousarray(pair.left_image[:, :TILE_COLS])
    want = view.copy()
    blk = BlockResult(pair.pair_id, "left", 0, 0, view, pair.left_grid, pair.stamp_ns, False)
    stage.keep(blk, [pair], borrowed=True)
    view[...] = 7
    full, quick = (lv.pairs[pair.pair_id].sides["left"].parts[0] for lv in stage.levels)
    np.testing.assert_array_equal(full, want)
    np.testing.assert_array_equal(quick, reduce_block(want, 4, 0.0))


def test_quicklook_only_sink_takes_borrowed_blocks() -> None:
    """With a block sink (the node's path) and quick-look tiles only, the pipeline hands the
    tile stage the borrowed block (no copy): the sink's buffer, overwritten right after each
    call as the render process's next block overwrites it, must not change the tiles, which
    equal those made from blocks returned in the outputs (to the bit)."""
    from parproj_ros.core.results import BlockResult

    pipe = _pipeline(quicklook=-2)
    seen: list[int] = []

    def sink(blk: BlockResult) -> None:
        seen.append(blk.index)

    pipe.set_block_sink(sink)
    stage = pipe.tiles
    assert stage is not None
    keep = stage.keep
    flags: list[bool] = []

    def spy(blk: BlockResult, pairs: Any = None, *, borrowed: bool = False) -> None:
        flags.append(borrowed)
        keep(blk, pairs, borrowed=borrowed)

    stage.keep = spy  # type: ignore[method-assign]
    _scribble_after_the_sink(pipe)
    out = _all(*_run(pipe=pipe))
    ref = _all(*_run(quicklook=-2))
    assert seen and not out.blocks and out.tiles
    assert flags and all(flags)  # every block handed over borrowed: no copy made
    assert [t.pair_id for t in out.tiles] == [t.pair_id for t in ref.tiles]
    for a, b in zip(out.tiles, ref.tiles, strict=True):
        assert a.dsm is not None and b.dsm is not None
        np.testing.assert_array_equal(a.dsm.heights, b.dsm.heights)


def test_quicklook_only_pair_with_the_quicklook_shed_says_it_has_no_heights() -> None:
    """Quick-look tiles only, shed by the admission before the pair starts (the ledger book's
    flag, as the node's admission sets it): no tile, and the pair's heights line is a WARN that
    it has none and why, not the OK line of a pair whose tiles stand for its heights."""
    pipe = _pipeline(quicklook=-2)
    pipe.ledger.admission.quicklook_shed = True
    out = _all(*_run(pipe=pipe))
    assert len(out.pairs) == 1 and not out.tiles and not out.heights
    (said,) = [i for i in out.issues if i.where == f"pair {out.pairs[0].pair_id}"
               and "heights" in i.message]  # fmt: skip
    assert said.level == Level.WARN and "none was made of this pair (shed" in said.message
    assert not any("stand for them" in i.message for i in out.issues)


def _scribble_after_the_sink(pipe: Pipeline) -> None:
    """Hand the pipeline's block sink borrowed pixels that are scribbled over right after
    each call, as the render process's next block overwrites its output buffer."""
    from parproj_ros.core.results import BlockResult

    inner = pipe.streamer.block_sink
    assert inner is not None

    def borrowed(blk: BlockResult) -> None:
        buf = blk.image.copy()
        inner(replace(blk, image=buf))
        buf[...] = 0

    pipe.streamer.block_sink = borrowed


def _threaded(quicklook: int, **run: Any) -> tuple[list[tuple[str, Outputs]], Outputs]:
    """:func:`_run` with the node's set-up: a block sink (borrowed pixels, scribbled over
    after each call) and the tiles on their thread (``Pipeline.use_tile_thread``)."""
    from parproj_ros.core.tiles import TileThread

    pipe = _pipeline(quicklook)
    pipe.set_block_sink(lambda blk: None)
    pipe.use_tile_thread()
    assert isinstance(pipe.tiles, TileThread)
    _scribble_after_the_sink(pipe)
    try:
        return _run(pipe=pipe, **run)
    finally:
        pipe.close()
        assert not pipe.tiles._thread.is_alive()
        assert cv2.getNumThreads() == pipe.tiles._opencv_threads  # set back


def test_the_tile_thread_makes_the_same_tiles_before_their_pair(
    streamed: dict[str, Any],
) -> None:
    """The node's tiles on their own thread (full resolution and 1/4): the same tiles as the
    stage called in the pipeline's thread, to the bit, in the same order, and every tile of
    the pair in an output no later than the pair's own."""
    calls, flushed = _threaded(2)
    got = _all(calls, flushed)
    ref = streamed["out"]
    assert [(t.pair_id, t.index, t.factor) for t in got.tiles] == [
        (t.pair_id, t.index, t.factor) for t in ref.tiles
    ]
    for a, b in zip(got.tiles, ref.tiles, strict=True):
        assert a.dsm is not None and b.dsm is not None
        np.testing.assert_array_equal(a.dsm.heights, b.dsm.heights)
        np.testing.assert_array_equal(a.owned, b.owned)
    outs = [o for _, o in calls] + [flushed]
    (when,) = [k for k, o in enumerate(outs) if o.pairs]
    assert all(t in got.tiles for o in outs[: when + 1] for t in o.tiles)
    assert sum(len(o.tiles) for o in outs[: when + 1]) == len(got.tiles)
    # The pair's heights stand on its tiles, as in the pipeline's thread.
    assert len(got.heights) == len(ref.heights) == 1
    np.testing.assert_array_equal(got.heights[0].dsm.heights, ref.heights[0].dsm.heights)


def test_a_broken_stream_on_the_tile_thread_ends_with_its_status() -> None:
    """As test_a_broken_stream_ends_with_its_tiles_and_a_status, the tiles on their thread:
    the flush that abandons the pair waits for the thread, so the ERROR comes with it."""
    calls, flushed = _threaded(0, drop_last_right=2)
    tiles = [t for _, o in calls for t in o.tiles] + flushed.tiles
    assert [t.index for t in tiles] == [0] and tiles[0].ok
    errors = [i for i in flushed.issues if i.level == Level.ERROR and "DSM tiles" in i.message]
    assert len(errors) == 1 and "stopped after 1 of 3" in errors[0].message, flushed.issues


def test_an_error_on_the_tile_thread_is_reported_and_the_pair_still_made(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bug while a tile is made on the thread (here: the matcher raising) does not stop
    the pipeline nor lose the pair: one ERROR names the pair whose tiles stop, and the pair
    comes as without it."""
    from parproj_ros.core.tiles import TileLevel

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("matcher exploded")

    monkeypatch.setattr(TileLevel, "_match", broken)
    calls, flushed = _threaded(0)
    out = _all(calls, flushed)
    assert not out.tiles and len(out.pairs) == 1
    errors = [i for i in out.issues if "internal error making DSM tiles" in i.message]
    assert len(errors) == 1 and errors[0].level == Level.ERROR, out.issues
    assert "RuntimeError: matcher exploded" in errors[0].message
    assert out.pairs[0].pair_id in errors[0].message


@pytest.mark.parametrize("quicklook", [-2, -3])
def test_blocks_nobody_takes_are_drafts_for_the_quicklook_only(quicklook: int) -> None:
    """Quick-look tiles only and nobody taking a side's blocks (the node: no subscriber on its
    block topic): that side's blocks are drafts, sampled nearest-neighbour (3x less render
    time; at 1/8 every 2nd row and column, core/streaming.draft_stride), flagged so that the
    node does not publish them; the other side's are not. The quick-look tiles from drafts
    stand within half a full-resolution pixel of disparity of those from the configured
    resampling: a sample moves by half a pixel at most, and a reduced pixel averages 4 x 4
    of them."""
    from parproj_ros.core.results import BlockResult
    from parproj_ros.core.streaming import draft_stride

    assert draft_stride((2**-quicklook,)) == (1 if quicklook == -2 else 2)
    got: list[BlockResult] = []
    pipe = _pipeline(quicklook=quicklook)
    pipe.set_block_sink(got.append, wanted=lambda side: side == "left")
    out = _all(*_run(pipe=pipe))
    ref = _all(*_run(quicklook=quicklook))
    assert {b.side for b in got if b.draft} == {"right"}
    assert {b.side for b in got if not b.draft} == {"left"}
    assert [t.index for t in out.tiles] == [t.index for t in ref.tiles] and out.tiles
    (pair,) = out.pairs
    bound = 0.5 * abs(pair.height_per_disparity_px)  # metres: half a full-resolution pixel
    diffs = []
    for a, b in zip(out.tiles, ref.tiles, strict=True):
        assert a.dsm is not None and b.dsm is not None and a.dsm.grid == b.dsm.grid
        both = np.isfinite(a.dsm.heights) & np.isfinite(b.dsm.heights)
        assert both.mean() > 0.9 * np.isfinite(b.dsm.heights).mean()
        diffs.append((a.dsm.heights - b.dsm.heights)[both])
    d = np.concatenate(diffs)
    assert abs(float(np.median(d))) <= 0.5 * bound and _nmad(d) <= bound, (
        float(np.median(d)), _nmad(d), bound)  # fmt: skip
    # Without ``wanted`` (offline, or nobody asked) no block is a draft.
    pipe = _pipeline(quicklook=quicklook)
    plain: list[BlockResult] = []
    pipe.set_block_sink(plain.append)
    _run(pipe=pipe)
    assert plain and not any(b.draft for b in plain)


def _drafted(
    renderer: RenderProcess | None, fences: list[int] | None = None
) -> tuple[list[tuple[str, Outputs]], Outputs, int]:
    """The node's quick-look-only set-up (1/4), nobody taking either side's blocks: drafts,
    rendered and reduced in ``renderer``'s process (None: in this thread), tiles on their
    thread. The outputs, and the draft blocks the sink was given. ``fences``: whether a
    draft still pending read the lines a line buffer was about to write over, each time it
    moved them (after the pipeline's fence)."""
    pipe = _pipeline(-2)
    if renderer is not None:
        pipe.use_render_process(renderer)
        if fences is not None:
            for asm in pipe.assemblers.values():

                def fence(
                    dest: np.ndarray, rp: RenderProcess = renderer, wait: Any = asm.pool.fence
                ) -> None:
                    wait(dest)  # the pipeline's own fence
                    fences.append(rp.reading(dest))

                asm.pool.fence = fence
    drafts = []
    pipe.set_block_sink(lambda blk: drafts.append(blk.draft), wanted=lambda side: False)
    pipe.use_tile_thread()
    try:
        calls, flushed = _run(pipe=pipe)
    finally:
        pipe.close()
    assert all(drafts)
    return calls, flushed, len(drafts)


def _same_tiles(a: Outputs, b: Outputs) -> None:
    assert [(t.pair_id, t.index) for t in a.tiles] == [(t.pair_id, t.index) for t in b.tiles]
    assert a.tiles
    for x, y in zip(a.tiles, b.tiles, strict=True):
        assert x.dsm is not None and y.dsm is not None
        np.testing.assert_array_equal(x.dsm.heights, y.dsm.heights)


def test_drafts_reduced_in_the_render_process_are_those_of_the_worker() -> None:
    """With the render process, a draft block is rendered and reduced there and not waited
    for (core/render_process.RenderProcess.submit_reduced): the quick-look tiles are those
    of the drafts rendered and reduced in the worker, to the bit; every tile comes no later
    than its pair; a line buffer moves its lines only once no draft reads them."""
    ref_calls, ref_flushed, n_ref = _drafted(None)
    rp = RenderProcess()
    fences: list[int] = []
    try:
        calls, flushed, n = _drafted(rp, fences)
        assert rp.alive and rp.error is None
    finally:
        rp.close()
    assert n == n_ref >= 4 and (rp.drafts, rp.fallbacks, rp.rendered) == (n, 0, 0)
    assert rp.pending == 0 and fences and not any(fences)
    _same_tiles(_all(calls, flushed), _all(ref_calls, ref_flushed))
    seen: set[tuple[str, int]] = set()
    for _, o in [*calls, ("flush", flushed)]:
        seen |= {(t.pair_id, t.index) for t in o.tiles}
        for p in o.pairs:
            assert {i for pid, i in seen if pid == p.pair_id}, p.pair_id


def test_the_draft_ring_wraps_and_waits(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ring of 40 kB (three reductions of 12.6 kB, this pair's blocks at 1/4), at most 3
    drafts in flight, none collected by a poll: the drafts wrap around the ring and wait for
    the oldest; the same tiles."""
    from parproj_ros.core import render_process as rpm

    ref_calls, ref_flushed, _ = _drafted(None)
    monkeypatch.setattr(rpm, "RING_BYTES", 40_000)
    monkeypatch.setattr(rpm, "DRAFTS_IN_FLIGHT", 3)
    monkeypatch.setattr(RenderProcess, "poll", lambda self: 0)
    starts: list[tuple[int, int]] = []
    space = RenderProcess._ring_space

    def spy(self: RenderProcess, nbytes: int) -> int | None:
        at = space(self, nbytes)
        starts.append((-1 if at is None else at, self.pending))
        return at

    monkeypatch.setattr(RenderProcess, "_ring_space", spy)
    rp = RenderProcess()
    try:
        calls, flushed, n = _drafted(rp)
    finally:
        rp.close()
    assert (rp.drafts, rp.fallbacks) == (n, 0)
    assert any(at == 0 and pending > 0 for at, pending in starts), starts  # wrapped
    assert max(pending for _, pending in starts) == 2, starts  # the fourth waited
    _same_tiles(_all(calls, flushed), _all(ref_calls, ref_flushed))


def test_drafts_of_a_dead_render_process_are_made_in_the_worker() -> None:
    """The render process killed before the pass: its drafts are rendered and reduced in
    the worker, the same tiles."""
    ref_calls, ref_flushed, _ = _drafted(None)
    rp = RenderProcess()
    rp._proc.kill()
    rp._proc.join(5)
    try:
        calls, flushed, _ = _drafted(rp)
    finally:
        rp.close()
    assert not rp.alive and rp.drafts == 0
    _same_tiles(_all(calls, flushed), _all(ref_calls, ref_flushed))
