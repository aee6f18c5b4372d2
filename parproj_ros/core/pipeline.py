"""The processing pipeline: strips + navigation (+ GCP) -> scene parameters and normalized pairs.

One object serves the live node and the offline ``parproj process``: both feed it with plain
arrays (see :mod:`parproj_ros.ros.conversions` for messages) and publish or record what it returns.
Nothing here imports ROS. :class:`Pipeline` is a facade: each step of paper 2's procedure is one
call into a focused module, and :meth:`Pipeline._process_scene` reads as those steps:

1. assemble: strips of each view make scenes (:class:`SceneAssembler`, :meth:`add_strip`);
2. orient: a complete scene's parallel projection parameters, from GCP (paper 1 Eq 8, roll
   estimated) or navigation (Eqs 9-13) (:func:`~parproj_ros.core.orientation.orient_scene`);
3. pair: which scenes make a pair (:class:`~parproj_ros.core.pairing.Pairing`);
4. normalize: paper 2 Eq 8 and the output grids, both scenes resampled, a GCP pair over the model
   error bound first cut into segments (:mod:`parproj_ros.core.normalization`);
5. refine: tie points remove the y-parallax left (:mod:`parproj_ros.core.tiepoints`);
6. publish: the :class:`Outputs` returned;
7. heights (``heights`` on): disparity, heights, DSM and ortho-image of every finished pair
   (:class:`~parproj_ros.core.heights.HeightsStage`, applied to what each public call returns);
8. fuse (``heights`` on): each pair's DSM with those of the earlier pairs it overlaps
   (:class:`~parproj_ros.core.fusion.FusionStage`).

Every pair's record and state is in one place, the ledger
(:class:`~parproj_ros.core.ledger.PairLedger`); the policies read it and record their decisions
there: navigation (its holds and pruning) :class:`~parproj_ros.core.navigation.NavigationFeed`,
pairing :class:`~parproj_ros.core.pairing.Pairing`, streaming (two views, normalized blocks while
the scenes arrive) :class:`~parproj_ros.core.streaming.Streamer`; GCP memory is
:class:`~parproj_ros.core.gcp_store.GcpStore`. Every problem becomes an :class:`Issue` that says
what was wrong and what was done (:mod:`parproj_ros.core.results`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..imaging.assembly import OpenScene, Scene, SceneAssembler, SceneEnd, StripRejectedError
from .config import PipelineConfig as PipelineConfig
from .config import ViewConfig as ViewConfig
from .dem_terrain import DemTerrain, terrain_issue
from .fusion import FusionStage
from .gcp_store import GcpStore
from .heights import HeightsStage, options_of
from .ledger import PairLedger, StreamPair
from .navigation import NavigationFeed
from .normalization import (
    cut_into_segments,
    interpolation_flag,
    normalize_pair,
    resample_scene,
)
from .orientation import orient_scene, start_unseen
from .pairing import Pairing
from .publish import finish_pair
from .render_process import RenderProcess
from .results import (
    MIN_SHARED_SHARE,
    BlockResult,
    GroundPoint,
    Issue,
    Level,
    Outputs,
    PairResult,
    SceneResult,
    YParallaxSource,
)
from .streaming import Streamer
from .terrain import TerrainSource, terrain_from_heights, with_dem
from .tiepoints import TieRefinement, refine_with_tie_points
from .tiles import TileStage, TileThread
from .trajectory import NavSample, TrajectoryBuffer

#: The facade's names: the pipeline, its settings and what it returns.
__all__ = [
    "GroundPoint",
    "Issue",
    "Outputs",
    "PairResult",
    "Pipeline",
    "PipelineConfig",
    "SceneResult",
    "ViewConfig",
]


class Pipeline:
    """Turns strips + navigation (+ GCP) into scene parameters and normalized pairs."""

    def __init__(self, config: PipelineConfig) -> None:
        if not 1 <= len(config.views) <= 2:
            raise ValueError("one view (single-camera mode) or two views (left, right) needed")
        self.config = config
        self.views = {v.name: v for v in config.views}
        self.assemblers = {
            v.name: SceneAssembler(
                v.name,
                v.camera.line_period,
                scene_lines=config.scenes.lines,
                max_gap_lines=config.scenes.max_gap_lines,
                nodata=config.output.nodata,
            )
            for v in config.views
        }
        #: Every pair's record and state (the policies below read it and record in it).
        self.ledger = PairLedger([v.name for v in config.views])
        self.feed = NavigationFeed(config.navigation, self.ledger)
        self.gcps = GcpStore()
        self.pairing = Pairing(config, self.ledger)
        self.streamer = Streamer(config, self.assemblers, self.feed, self.gcps, self.ledger)
        self.heights = HeightsStage(options_of(config)) if config.dense.enabled else None
        #: Streamed DSM tiles while the blocks arrive (core/tiles.py), with heights on.
        self.tiles: TileStage | TileThread | None = (
            TileStage(config, self.ledger.streams) if TileStage.applies(config) else None
        )
        self._draft_live: set[str] = set()  # the streams under way at the last collection
        self.fusion = (
            FusionStage(config.dense.fuse_mb)
            if config.dense.enabled and config.dense.fuse_mb > 0
            else None
        )
        #: The DEM of the pairs' terrain, given by the front end (:meth:`use_dem`), or None.
        self.dem: DemTerrain | None = None

    def use_dem(self, dem: DemTerrain | None) -> None:
        """Measure each pair's terrain with this DEM too (None: no DEM).

        The front end reads the DEM (the node's ``dem`` parameter, ``parproj process --dem``)
        and says in which object frame it is placed (:class:`~.dem_terrain.DemTerrain`); the
        output extent (step 4) and the heights step's disparity range (step 7) then search its
        heights over the pair's ground joined with the tie points' (:func:`~.terrain.with_dem`).
        A streamed pair's extent and its DSM tiles search the DEM's heights from the stream's
        start (the tiles' first window's tie points joined with them).
        """
        self.dem = dem
        self.streamer.dem = dem  # a streamed pair's extent and tiles: at the stream's start
        if self.heights is not None:
            self.heights.dem = dem

    def use_render_process(self, renderer: RenderProcess) -> None:
        """Render streamed blocks in ``renderer``'s process; line buffers in its shared memory.

        Call before the first strip (buffers allocated earlier stay private and their blocks
        are rendered in the calling thread).
        """
        self.streamer.renderer = renderer
        for asm in self.assemblers.values():
            asm.pool.allocate = renderer.allocate
            asm.pool.fence = renderer.drain_over  # drafts still reading lines about to move

    def use_tile_thread(self) -> None:
        """Make the streamed DSM tiles on a thread of their own (:class:`TileThread`).

        The node's: its pipeline thread goes on with strips and blocks meanwhile. Call before
        the first strip; :meth:`close` stops the thread. Nothing to do without tiles.
        """
        if isinstance(self.tiles, TileStage):
            self.tiles = TileThread(self.tiles)

    def close(self) -> None:
        """Stop the tile thread, if any (no input may be fed after).

        Draft blocks still in the render process are collected first.
        """
        if self.streamer.renderer is not None:
            self.streamer.renderer.drain()
        if self.tiles is not None:
            self.tiles.close()

    def set_block_sink(
        self,
        sink: Callable[[BlockResult], None] | None,
        wanted: Callable[[str], bool] | None = None,
    ) -> None:
        """Hand each streamed block to ``sink`` as soon as it is rendered (the node publishes it).

        The blocks are then no longer in the outputs; their pixels may be borrowed, valid only
        during the call (:attr:`Streamer.block_sink`). ``sink`` must not raise (the streamer
        would stop mid-input). With heights on, a copy of each block is kept for step 7 once
        ``sink`` has taken it; if there is no memory for the copy, that pair's heights are
        reported as incomplete. None: blocks come back in :attr:`Outputs.blocks` again.

        ``wanted``: side -> whether anybody takes that side's blocks themselves (the node: a
        subscriber on its block topic). With quick-look tiles only, the blocks of a side
        nobody takes are drafts (:attr:`Streamer.draft`, :data:`~.streaming.
        DRAFT_INTERPOLATION`): they feed the quick-look and are not published.
        """
        quick_only = self.heights is not None and self.heights.options.quicklook_only
        drafts = sink is not None and wanted is not None and quick_only and self.tiles is not None
        self.streamer.draft = (lambda side: not wanted(side)) if drafts and wanted else None
        self.streamer.drafts = _Drafts(self, sink) if drafts and sink is not None else None
        if sink is None or self.heights is None:
            self.streamer.block_sink = sink
            return
        heights, to = self.heights, sink

        def keep_and_sink(blk: BlockResult) -> None:
            to(blk)
            tiles = self.tiles  # the stage, or its thread (use_tile_thread)
            try:
                if heights.options.quicklook_only and tiles is not None:
                    # Nothing keeps the full-resolution block: the quick-look levels take
                    # their reduction of the borrowed pixels (no 7 MB copy per IKONOS block).
                    tiles.keep(blk, borrowed=True)
                    return
                kept = replace(blk, image=blk.image.copy())
                heights.keep(kept)
                if tiles is not None:
                    tiles.keep(kept)
            except MemoryError:  # step 7 then finds the pair's images incomplete: a WARN
                pass

        self.streamer.block_sink = keep_and_sink

    def _step7(self, out: Outputs) -> Outputs:
        """7. heights of the pairs ``out`` finishes (``heights`` on); ``out`` itself.

        And 8.: their DSMs fused with those of the earlier pairs they overlap.
        """
        if self.heights is None:
            return out
        self._collect_drafts(out)
        if self.tiles is not None:  # the tiles the blocks now cover (core/tiles.py)
            # The quick-look, shed or resumed by the node's admission under overload.
            out.issues += self.tiles.shed_quicklook(self.ledger.admission.quicklook_shed)
            out = self.tiles(out)
        out = self.heights(out)
        return out if self.fusion is None else self.fusion(out)

    def _collect_drafts(self, out: Outputs) -> None:
        """The draft blocks the render process has reduced since (:attr:`Streamer.drafts`).

        All of them, waiting, when ``out`` makes a pair or a stream ended since the last call
        (the pair's last tiles, or a broken pair's status, come with it); else those done.
        """
        renderer = self.streamer.renderer
        if renderer is None or self.streamer.drafts is None:
            return
        live = {s.geometry.pair_id for s in self.ledger.streams.values()}
        ended = bool(self._draft_live - live)
        self._draft_live = live
        if out.pairs or ended:
            renderer.drain()
        else:
            renderer.poll()

    @property
    def nav(self) -> TrajectoryBuffer:
        """The navigation samples kept."""
        return self.feed.buffer

    @property
    def gcp(self) -> dict[str, GroundPoint]:
        """The GCP and check points kept, by id."""
        return self.gcps.points

    @property
    def _ready(self) -> dict[str, dict[int, SceneResult]]:
        """Oriented scenes waiting for their partner (:attr:`PairLedger.ready`)."""
        return self.ledger.ready

    @property
    def pairs_done(self) -> int:
        """Pairs whose result was returned."""
        return self.ledger.pairs_made

    @property
    def has_open_scene(self) -> bool:
        """Whether any view has a scene still being assembled."""
        return any(a.is_open for a in self.assemblers.values())

    @property
    def interpolation_flag(self) -> int:
        """OpenCV interpolation flag of the configured interpolation."""
        return interpolation_flag(self.config.output)

    # ---- inputs -------------------------------------------------------------------------
    def add_navigation(self, sample: NavSample) -> Outputs:
        """Add a navigation sample; scenes waiting for navigation may now be processed.

        A sample more than ``nav_jump_s`` ahead of the newest one is held until the next sample
        confirms the jump (a clock jump or a stray stamp is then dropped and reported); one more
        than ``nav_jump_s`` behind is dropped and reported (:meth:`NavigationFeed.add`).
        """
        out = Outputs()
        accepted, issues = self.feed.add(sample)
        out.issues += issues
        if not accepted:
            return out
        out.extend(self._process_waiting())
        if self.ledger.held_until and self.streamer.can_stream:
            # A streaming decision held for navigation may be taken now; then the scenes it
            # held, if it could not stream them.
            out.extend(self.streamer.start())
            for view in self.assemblers:
                out.extend(self.streamer.advance(view))
            out.extend(self._process_waiting())
        self.feed.prune(self.assemblers, self.ledger.first_lines())
        return self._step7(out)

    def _process_waiting(self) -> Outputs:
        """Process the waiting scenes that navigation now covers, except held ones.

        A scene is held while its pair's streaming decision waits (:meth:`Streamer.held`).
        """
        out = Outputs()
        still = []
        for scene in self.ledger.waiting:
            end = scene.last_line_ns
            if self.streamer.held(scene) or not self.nav.covers(scene.first_line_ns, end):
                still.append(scene)
                continue
            k = scene.index
            if self.streamer.undecided(scene):
                # Navigation has passed the whole scene and its pair could still not be
                # decided (its other scene cannot be processed): give up streaming.
                self.ledger.not_stream(k)
                out.issues.append(
                    Issue(
                        Level.WARN,
                        f"{scene.view}/{scene.scene_id}",
                        "not streamed: navigation lagged behind the strips and its pair could "
                        "not be decided before navigation passed the scene: processed whole",
                    )
                )
            out.extend(self._process_scene(scene))
        self.ledger.waiting[:] = still
        return out

    def add_gcp(self, points: Sequence[GroundPoint]) -> Outputs:
        """Add or replace ground control points (by id).

        Observations in a scene already done with (processed without them, or skipped) are
        dropped and reported, one warning per scene: they come too late to be used.
        """
        return self._step7(self.gcps.add(points, self.ledger.done))

    def set_pairs(self, pairs: Sequence[tuple[str, str]]) -> Outputs:
        """Select which acquisitions pair up (single-camera mode; the node's ``pairs`` topic).

        See :meth:`Pairing.set_pairs`; two-view mode ignores the selection (a WARN).
        """
        return self._step7(self.pairing.set_pairs(pairs, self._make_pair, self.gcps))

    def add_strip(
        self, view: str, stamp_ns: int, scene_id: str, strip: NDArray[np.generic]
    ) -> Outputs:
        """Add one strip of ``view`` (first line exposed at ``stamp_ns``): step 1, assemble.

        ``strip``: (lines, detectors) pixels of the view's dtype. The scenes it completes are
        processed (:meth:`_scene_done`), or their streams closed; streamed blocks it completes
        are emitted.
        """
        out = Outputs()
        if view not in self.assemblers:
            out.issues.append(Issue(Level.ERROR, f"view {view}", "unknown view: strip dropped"))
            return out
        detectors = self.views[view].camera.detectors
        want = self.views[view].dtype
        if want is not None and strip.dtype != np.dtype(want):
            out.issues.append(
                Issue(
                    Level.WARN,
                    f"{view}/{scene_id}",
                    (f"strip is {strip.dtype}, the camera delivers {want}: dropped"),
                )
            )
            return out
        if strip.ndim == 2 and strip.shape[1] != detectors:
            out.issues.append(
                Issue(
                    Level.WARN,
                    f"{view}/{scene_id}",
                    (
                        f"strip is {strip.shape[1]} px wide, the camera has {detectors} "
                        "detectors: "
                        "dropped"
                    ),
                )
            )
            return out
        try:
            scenes = self.assemblers[view].add(stamp_ns, scene_id, strip)
        except StripRejectedError as err:
            out.issues.append(Issue(Level.WARN, f"{view}/{scene_id}", str(err)))
            return out
        for scene in scenes:
            if scene.reason == SceneEnd.GAP:
                out.issues.append(self._split(scene, stamp_ns))
            out.extend(self._closed(scene))
        if self.streamer.can_stream:
            out.extend(self.streamer.start())
            out.extend(self.streamer.advance(view))
        return self._step7(out)

    def _split(self, scene: Scene, next_ns: int) -> Issue:
        """The WARN for a scene ended by a jump of more than ``max_gap_lines`` lines."""
        jump = round((next_ns - scene.first_line_ns) / (scene.line_period * 1e9)) - scene.lines
        opened = self.assemblers[scene.view].open_scene()
        rest = f" ({opened.scene_id})" if opened is not None else ""
        return Issue(
            Level.WARN,
            f"{scene.view}/{scene.scene_id}",
            f"{jump} lines missing after line {scene.lines - 1} (more than max_gap_lines, "
            f"{self.config.scenes.max_gap_lines}): scene split; it ends there, with {scene.lines} "
            f"lines, and the strips after the hole make a new scene{rest}",
        )

    def close_view(self, view: str) -> Outputs:
        """Close and process the open scene of ``view`` alone (its next scene was shed whole).

        What :meth:`close_scenes` does, for one view: the scene is whole (its next one has
        begun), and the other view's open scene is left as it is.
        """
        out = Outputs()
        for scene in self.assemblers[view].flush():
            out.extend(self._closed(scene))
        return self._step7(out)

    def open_scenes(self) -> dict[str, OpenScene]:
        """The scene each view is assembling, by view (views with none left out)."""
        opened = {v: a.open_scene() for v, a in self.assemblers.items()}
        return {v: o for v, o in opened.items() if o is not None}

    def close_scenes(self) -> Outputs:
        """Close the open scene of every view (strips stopped coming) and process them."""
        return self._step7(self._close_all())

    def _close_all(self) -> Outputs:
        out = Outputs()
        for asm in self.assemblers.values():
            for scene in asm.flush():
                out.extend(self._closed(scene))
        return out

    def close_idle_scenes(self) -> Outputs:
        """Close the open scenes whose strips stopped coming (the node's ``scene_timeout``).

        Only a scene that the navigation has moved past, by more than ``max_gap_lines`` lines
        after its last line, is closed: the strips stopped while the platform went on (the end
        of a pass). When the navigation stopped with the strips (a publisher restarting, the
        network or a replay paused), the scene is kept open, since its strips may resume where
        they stopped. Without navigation at all, every open scene is closed.
        """
        out = Outputs()
        newest = self.nav.last_ns
        for name, asm in self.assemblers.items():
            opened = asm.open_scene()
            if opened is None:
                continue
            period_ns = self.views[name].camera.line_period * 1e9
            after_last = opened.first_line_ns + opened.lines * period_ns
            if (
                newest is not None
                and newest <= after_last + self.config.scenes.max_gap_lines * period_ns
            ):
                continue
            for scene in asm.flush():
                out.extend(self._closed(scene))
        return self._step7(out)

    def flush(self) -> Outputs:
        """End of data: close open scenes, process what can be, report what cannot."""
        out = self._close_all()
        for scene in self.ledger.waiting:
            if self.gcps.for_scene(scene)[0].shape[0] >= self.config.orientation.min_gcp:
                out.extend(self._process_scene(scene))  # navigation ended early: GCP only
                continue
            self.pairing.done_with(scene, "skipped")
            out.issues.append(
                Issue(
                    Level.ERROR,
                    f"{scene.view}/{scene.scene_id}",
                    "navigation never covered this scene and it has no GCP: scene skipped",
                )
            )
        self.ledger.waiting.clear()
        self.ledger.end_of_data()
        out.extend(self.pairing.unmade(self._make_pair, self.gcps))
        return self._step7(out)

    # ---- scenes -------------------------------------------------------------------------
    def _closed(self, scene: Scene) -> Outputs:
        """A scene is complete: the end of its stream, or processed whole (:meth:`_scene_done`)."""
        streamed = self.streamer.scene_closed(scene)
        return self._scene_done(scene) if streamed is None else streamed

    def _scene_done(self, scene: Scene) -> Outputs:
        """A complete scene not streamed: processed now, or waiting for navigation."""
        out = Outputs()
        if scene.gaps:
            out.issues.append(
                Issue(
                    Level.WARN,
                    f"{scene.view}/{scene.scene_id}",
                    f"{scene.gaps} missing lines filled with no-data "
                    f"({self.config.output.nodata})",
                )
            )
        has_gcp = self.gcps.for_scene(scene)[0].shape[0] >= self.config.orientation.min_gcp
        if not self.nav.covers(scene.first_line_ns, scene.last_line_ns):
            last = self.nav.last_ns
            if has_gcp and (last is None or last >= scene.last_line_ns):
                # GCP alone will do: no navigation at all, or it will never cover the scene.
                out.extend(self._process_scene(scene))
                return out
            if last is not None and last >= scene.last_line_ns:
                self.pairing.done_with(scene, "skipped")
                out.issues.append(
                    Issue(
                        Level.ERROR,
                        f"{scene.view}/{scene.scene_id}",
                        "navigation starts after the scene's first line and there are no GCP: "
                        "scene skipped",
                    )
                )
                return out
            self.ledger.waiting.append(scene)
            return out
        out.extend(self._process_scene(scene))
        return out

    def _process_scene(self, scene: Scene) -> Outputs:
        """Paper 2's procedure for one complete (assembled, step 1) scene: steps 2 to 6."""
        out = Outputs()
        # 2. orient: parameters from GCP (paper 1 Eq 8) or navigation (Eqs 9-13); a first
        #    scene that may have begun before navigation was received is not oriented.
        unseen = start_unseen(scene, self.feed.first_ns, self.config.navigation.start_margin_s)
        if unseen is not None:
            out.issues.append(unseen)
            return out
        view = self.views[scene.view]
        result, issues = orient_scene(scene, view, self.nav, self.gcps, self.config)
        out.issues += issues
        if result is None:
            self.pairing.done_with(scene, "skipped")
            return out
        self.pairing.done_with(scene, result.method)
        out.scenes.append(result)
        # 3. pair: the scene waits for its partner; pairs now complete are made (4 to 6).
        out.issues += self.pairing.add(result)
        out.extend(self.pairing.make_pairs(self._make_pair, self.gcps))
        return out

    # ---- pairs --------------------------------------------------------------------------
    def _make_pair(self, left: SceneResult, right: SceneResult) -> Outputs:
        """Steps 4 to 6 for a pair of oriented scenes.

        A GCP pair whose model error is over ``segment_max_error_px`` is first cut into segment
        pairs (:func:`cut_into_segments`), each made as a whole pair.
        """
        keep = self.pairing.selected_scene_ids()
        out, cut = cut_into_segments(
            left, right, self.config, self.gcps, self._make_whole_pair, keep
        )
        if not cut:
            out.extend(self._make_whole_pair(left, right))
        return out

    def _make_whole_pair(self, left: SceneResult, right: SceneResult) -> Outputs:
        """Steps 4 (normalize), 5 (refine) and 6 (publish) for a pair of whole scenes."""
        out = Outputs()
        # 4. normalize: paper 2 Eq 8, the output grids, both scenes resampled.
        normalized = normalize_pair(left, right, self.config, self.gcps, self.dem)
        if self.dem is not None:  # the DEM's issues with this pair, whatever came of it
            out.issues += self.dem.take_issues()
        if isinstance(normalized, Issue):
            out.issues.append(normalized)
            return out
        geo, img_l, img_r = normalized.geometry, normalized.left_image, normalized.right_image
        terrain = normalized.terrain
        stamp = max(left.scene.last_line_ns, right.scene.last_line_ns)
        # 5. refine: tie points correct the right normalization (its rows).
        tie: TieRefinement | None = None
        if self.config.ties.enabled:
            refined = refine_with_tie_points(
                geo,
                img_l,
                img_r,
                nodata=self.config.output.nodata,
                pixel=left.camera.pixel_size,
                threshold_px=self.config.ties.threshold_px,
            )
            if isinstance(refined, str):
                out.issues.append(Issue(Level.WARN, f"pair {geo.pair_id}", refined))
            else:
                tie = refined
                geo = tie.geometry
                img_r = resample_scene(right, geo.right_geom, geo.right_grid, self.config.output)
                out.issues.append(Issue(Level.OK, f"pair {geo.pair_id}", tie.summary))
                if self.config.ties.terrain == "tie_points":
                    # The full-resolution tie points measure the terrain more finely than the
                    # reduced pair the extent was chosen on.
                    fine = terrain_from_heights(
                        tie.heights_m,
                        terrain,
                        metres_per_px=geo.left_grid.pixel / geo.normalization.parallax_per_height,
                    )
                    if fine is not terrain:  # measured: joined with the DEM's again
                        terrain = with_dem(normalized.dem_terrain, fine)
        if self.dem is not None:
            # Which heights the pair's extent (and its heights step) searches, and whence.
            why = (
                ": too few tie points agree to measure the terrain from the pair, the DEM's "
                "heights are searched"
                if terrain.source == TerrainSource.DEM and self.config.ties.terrain == "tie_points"
                else ""
            )
            out.issues.append(terrain_issue(geo.pair_id, terrain, why))
        # 6. publish: the pair result, with its y-parallax and terrain.
        pair = finish_pair(
            left,
            right,
            geo,
            (img_l, img_r),
            stamp,
            config=self.config,
            gcps=self.gcps,
            ledger=self.ledger,
            terrain=terrain,
        )
        if tie is not None:
            pair = replace(
                pair, y_parallax_px=tie.residual_px, y_parallax_source=YParallaxSource.TIE_POINTS
            )
        nodata = self.config.output.nodata
        shared = float(np.mean((img_l != nodata) & (img_r != nodata))) if img_l.size else 0.0
        pair = replace(pair, shared_share=shared)
        if pair.unusable:
            out.issues.append(
                Issue(
                    Level.ERROR,
                    f"pair {pair.pair_id}",
                    f"its normalized images share only {100 * shared:.1f} % of their pixels "
                    f"with data in both (< {100 * MIN_SHARED_SHARE:g} %): the scenes see "
                    f"different ground at the heights used ({terrain.describe()}), nothing to "
                    "match. Check that the scenes overlap (crop origins, RPCs, the pair "
                    "selection)"
                    + (
                        ", and the DEM's heights (its vertical reference)"
                        if terrain.source in (TerrainSource.DEM, TerrainSource.DEM_TIE_POINTS)
                        else ", or give a DEM (parproj import --dem, or process --dem)"
                    ),
                )
            )
        out.pairs.append(pair)
        return out


class _Drafts:
    """The pipeline's :class:`~.streaming.DraftReducer`: its tile levels take the reductions.

    Args:
        pipeline: whose tile stage (or thread) holds them.
        sink: the block sink, given each draft block (its pixels none: a broadcast).
    """

    #: Pairs whose tile geometry is kept for their drafts still in the render process.
    GEOMETRIES = 8

    def __init__(self, pipeline: Pipeline, sink: Callable[[BlockResult], None]) -> None:
        self.pipeline = pipeline
        self.sink = sink
        self._geo: OrderedDict[str, Any] = OrderedDict()

    def factors(self, stream: StreamPair) -> tuple[int, ...]:
        tiles = self.pipeline.tiles
        if tiles is None:
            return ()
        pid = stream.geometry.pair_id
        factors = tuple(level.factor if level.takes(pid) else 0 for level in tiles.levels)
        if any(factors) and pid not in self._geo:
            # Built here, while the stream is under way: its last drafts may be collected
            # after it ended.
            self._geo[pid] = TileStage.stream_geometry(stream)
            while len(self._geo) > self.GEOMETRIES:
                self._geo.popitem(last=False)
        return factors

    def deliver(self, blk: BlockResult, reductions: list[NDArray[np.generic] | None]) -> None:
        self.sink(blk)
        tiles = self.pipeline.tiles
        if tiles is not None:
            tiles.keep_reduced(blk, reductions, self._geo.get(blk.pair_id))
