"""The processing pipeline: strips + navigation (+ GCP) -> scene parameters and normalized pairs.

One object serves the live node and the offline ``parproj process``: both feed it with plain
arrays (see :mod:`parproj_ros.ros.conversions` for messages) and publish or record what it returns.
Nothing here imports ROS.

Flow: strips of each view go to a :class:`SceneAssembler`; a completed scene gets its parallel
projection parameters from GCP (when at least 5 non-check GCP are observed in it: Eq 8 with the
roll estimated) or else from navigation (Eqs 9-13, with the crab-angle fallback); when both scenes
of a pair have parameters, the pair is normalized (paper 2 Eq 8) and both scenes are resampled.
Pairs are the two views' scenes with the same sequence number (two-view mode) or consecutive
scenes of the one view (single-camera mode, e.g. an agile satellite looking forward then back).
Every problem becomes an :class:`Issue` that says what was wrong and what was done. The result
types (issues, scene and pair results, the closed sets they name) are in
:mod:`parproj_ros.core.results`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry import (
    DegenerateGeometryError,
    GeometryError,
    Normalization,
    ParallelProjection,
    PushbroomModel,
    SceneFrame,
    affine_to_nonlinear,
    estimate_affine,
    normalize_pair,
    parameters_from_navigation,
)
from ..geometry.navigation import virtual_points
from ..geometry.segmentation import SideCamera, segment_pair
from ..imaging.assembly import OpenScene, Scene, SceneAssembler, SceneEnd, StripRejectedError
from ..imaging.resample import OutputGrid, SceneGeometry, footprint, native_pixel, resample
from .config import PipelineConfig as PipelineConfig
from .config import ViewConfig as ViewConfig
from .results import (
    BlockResult,
    GroundPoint,
    Issue,
    Method,
    Outputs,
    PairGeometry,
    PairResult,
    SceneResult,
)
from .streaming import SideStream, StreamPair, plan_blocks, render_block
from .tiepoints import TieRefinement, refine_with_tie_points
from .trajectory import NavigationError, NavSample, TrajectoryBuffer

FloatArray = NDArray[np.float64]


class Pipeline:
    """Turns strips + navigation (+ GCP) into scene parameters and normalized pairs."""

    def __init__(self, config: PipelineConfig) -> None:
        if not 1 <= len(config.views) <= 2:
            raise ValueError("one view (single-camera mode) or two views (left, right) needed")
        self.config = config
        self.views = {v.name: v for v in config.views}
        self.nav = TrajectoryBuffer()
        self.assemblers = {
            v.name: SceneAssembler(
                v.name,
                v.camera.line_period,
                scene_lines=config.scene_lines,
                max_gap_lines=config.max_gap_lines,
                nodata=config.nodata,
            )
            for v in config.views
        }
        self.gcp: dict[str, GroundPoint] = {}
        self._waiting_nav: list[Scene] = []
        self._ready: dict[str, dict[int, SceneResult]] = {v.name: {} for v in config.views}
        self.pairs_done = 0
        self._streams: dict[int, StreamPair] = {}
        self._nav_pending: NavSample | None = None
        self._nav_first_ns: int | None = None  # earliest navigation stamp accepted
        self._no_stream: set[int] = set()
        # Pairs whose streaming decision waits for navigation (it lagged behind their first
        # strips): pair index -> the scene start it must reach (see _predict_scene).
        self._stream_wait: dict[int, int] = {}
        # The latest scenes done with (processed or skipped): scene id -> (view, method), so
        # that GCP arriving after their scene are reported, not kept.
        self._done: dict[str, tuple[str, str]] = {}
        # Single-camera pair selection (the `pairs` topic): the (left, right) scene ids of the
        # pairs still to make, in order; None: acquisitions 2k and 2k+1 pair up.
        self._selection: list[tuple[str, str]] | None = None
        # single-camera pairs made (their two scene ids; an ordered set of the latest 1024)
        self._made: dict[frozenset[str], None] = {}

    # ---- inputs -------------------------------------------------------------------------
    def add_navigation(self, sample: NavSample) -> Outputs:
        """Add a navigation sample; scenes waiting for navigation may now be processed.

        A sample more than ``nav_jump_s`` ahead of the newest one is held until the next sample
        confirms the jump (a clock jump or a stray stamp is then dropped and reported); one more
        than ``nav_jump_s`` behind is dropped and reported.
        """
        out = Outputs()
        jump = self.config.nav_jump_s * 1e9
        last = self.nav.last_ns
        if self._nav_pending is not None:
            pending, self._nav_pending = self._nav_pending, None
            if abs(sample.t_ns - pending.t_ns) <= jump:
                self._add_nav(pending)  # the jump is confirmed by this sample
            else:
                out.issues.append(
                    Issue(
                        "warn",
                        "navigation",
                        (
                            f"a sample stamped {(pending.t_ns - (last or 0)) / 1e9:+.3f} s "
                            "from the "
                            "newest one was not followed by others: dropped"
                        ),
                    )
                )
        elif last is not None and sample.t_ns > last + jump:
            self._nav_pending = sample
            return out
        if last is not None and sample.t_ns < last - jump:
            out.issues.append(
                Issue(
                    "warn",
                    "navigation",
                    (
                        f"sample stamped {(sample.t_ns - last) / 1e9:+.3f} s from the newest one "
                        "(stamps going backwards; too late for any scene still open): dropped"
                    ),
                )
            )
            return out
        self._add_nav(sample)
        out.extend(self._process_waiting())
        if self._stream_wait and self._can_stream:
            # A streaming decision held for navigation may be taken now; then the scenes it
            # held, if it could not stream them.
            out.extend(self._stream_start())
            for view in self.assemblers:
                out.extend(self._stream_advance(view))
            out.extend(self._process_waiting())
        self._prune_navigation()
        return out

    def _process_waiting(self) -> Outputs:
        """Process the waiting scenes that navigation now covers, except held ones (_held)."""
        out = Outputs()
        still = []
        for scene in self._waiting_nav:
            end = scene.last_line_ns
            if self._held(scene) or not self.nav.covers(scene.first_line_ns, end):
                still.append(scene)
                continue
            k = scene.index
            if self._undecided(scene):
                # Navigation has passed the whole scene and its pair could still not be
                # decided (its other scene cannot be processed): give up streaming.
                self._no_stream.add(k)
                out.issues.append(
                    Issue(
                        "warn",
                        f"{scene.view}/{scene.scene_id}",
                        "not streamed: navigation lagged behind the strips and its pair could "
                        "not be decided before navigation passed the scene: processed whole",
                    )
                )
            out.extend(self._process_scene(scene))
        self._waiting_nav = still
        return out

    def _undecided(self, scene: Scene) -> bool:
        """Whether ``scene``'s pair waits for navigation to decide streaming (``_stream_wait``).

        Only a scene still arriving at the decision time counts: one complete before it would
        have been processed whole anyway.
        """
        t = self._stream_wait.get(scene.index)
        return (
            t is not None
            and scene.index not in self._streams
            and scene.index not in self._no_stream
            and scene.last_line_ns >= t
        )

    def _held(self, scene: Scene) -> bool:
        """Whether a complete scene is held for its pair's streaming decision.

        Undecided (:meth:`_undecided`), and navigation has not passed the scene yet (the bound).
        """
        last = self.nav.last_ns
        return self._undecided(scene) and (last is None or last <= scene.last_line_ns)

    def _add_nav(self, sample: NavSample) -> None:
        self.nav.add(sample)
        if self._nav_first_ns is None or sample.t_ns < self._nav_first_ns:
            self._nav_first_ns = sample.t_ns

    def _navigation_needed_from(self) -> int | None:
        """Earliest line time (ns) for which a scene may still need navigation (None: unknown).

        The first lines of the open scenes, of the scenes waiting for navigation and of the
        streamed pairs' scenes; for a view with no open scene, the end of its data (its next
        scene cannot start earlier). Unknown while a view has received no strip.
        """
        times = [s.first_line_ns for s in self._waiting_nav]
        times += [
            side.result.scene.first_line_ns
            for stream in self._streams.values()
            for side in stream.sides.values()
        ]
        for asm in self.assemblers.values():
            opened = asm.open_scene()
            if opened is not None:
                times.append(opened.first_line_ns)
            elif asm.latest_ns is not None:
                times.append(asm.latest_ns)
            else:
                return None
        return min(times)

    def _prune_navigation(self) -> None:
        """Forget navigation no scene can need any more (``nav_history_s`` before it is kept)."""
        needed = self._navigation_needed_from()
        last = self.nav.last_ns
        if needed is not None and last is not None:
            self.nav.prune_before(min(needed, last) - round(self.config.nav_history_s * 1e9))

    def _forget_gcp(self, scene_ids: tuple[str, ...]) -> None:
        """Drop the GCP observations in the scenes of a finished pair (scene ids never repeat).

        A point left with no observation is dropped, so GCP sets that arrive with every
        acquisition do not pile up. Scenes that a selected pair still needs keep theirs.
        """
        needed = self._selected_scene_ids()
        scene_ids = tuple(s for s in scene_ids if s not in needed)
        for pid, p in list(self.gcp.items()):
            if not any(s in p.observations for s in scene_ids):
                continue
            obs = {s: o for s, o in p.observations.items() if s not in scene_ids}
            if obs:
                self.gcp[pid] = replace(p, observations=obs)
            else:
                del self.gcp[pid]

    def add_gcp(self, points: Sequence[GroundPoint]) -> Outputs:
        """Add or replace ground control points (by id).

        Observations in a scene already done with (processed without them, or skipped) are
        dropped and reported, one warning per scene: they come too late to be used.
        """
        out = Outputs()
        late: dict[str, int] = {}
        for p in points:
            xyz = np.asarray(p.xyz, dtype=float)
            if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
                out.issues.append(Issue("warn", f"gcp {p.id}", "non-finite coordinates: ignored"))
                continue
            done = [s for s in p.observations if s in self._done]
            if done:
                for s in done:
                    late[s] = late.get(s, 0) + 1
                p = replace(
                    p, observations={s: o for s, o in p.observations.items() if s not in done}
                )
                if not p.observations:
                    continue
            self.gcp[p.id] = p
        for sid, n in late.items():
            view, method = self._done[sid]
            out.issues.append(
                Issue(
                    "warn",
                    f"{view}/{sid}",
                    f"{n} GCP and check points observed in this scene arrived after it was "
                    + ("skipped" if method == "skipped" else f"processed ({method})")
                    + ": not used",
                )
            )
        return out

    def _done_with(self, scene: Scene, method: str) -> None:
        """Remember that a scene is done with (``method``, or "skipped"); the latest 256 kept."""
        self._done[scene.scene_id] = (scene.view, method)
        while len(self._done) > 256:
            del self._done[next(iter(self._done))]

    def add_strip(
        self, view: str, stamp_ns: int, scene_id: str, strip: NDArray[np.generic]
    ) -> Outputs:
        """Add one strip of ``view`` (first line exposed at ``stamp_ns``)."""
        out = Outputs()
        if view not in self.assemblers:
            out.issues.append(Issue("error", f"view {view}", "unknown view: strip dropped"))
            return out
        detectors = self.views[view].camera.detectors
        want = self.views[view].dtype
        if want is not None and strip.dtype != np.dtype(want):
            out.issues.append(
                Issue(
                    "warn",
                    f"{view}/{scene_id}",
                    (f"strip is {strip.dtype}, the camera delivers {want}: dropped"),
                )
            )
            return out
        if strip.ndim == 2 and strip.shape[1] != detectors:
            out.issues.append(
                Issue(
                    "warn",
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
            out.issues.append(Issue("warn", f"{view}/{scene_id}", str(err)))
            return out
        for scene in scenes:
            if scene.reason == SceneEnd.GAP:
                out.issues.append(self._split(scene, stamp_ns))
            out.extend(self._scene_closed(scene))
        if self._can_stream:
            out.extend(self._stream_start())
            out.extend(self._stream_advance(view))
        return out

    def _split(self, scene: Scene, next_ns: int) -> Issue:
        """The WARN for a scene ended by a jump of more than ``max_gap_lines`` lines."""
        jump = round((next_ns - scene.first_line_ns) / (scene.line_period * 1e9)) - scene.lines
        opened = self.assemblers[scene.view].open_scene()
        rest = f" ({opened.scene_id})" if opened is not None else ""
        return Issue(
            "warn",
            f"{scene.view}/{scene.scene_id}",
            f"{jump} lines missing after line {scene.lines - 1} (more than max_gap_lines, "
            f"{self.config.max_gap_lines}): scene split; it ends there, with {scene.lines} "
            f"lines, and the strips after the hole make a new scene{rest}",
        )

    def close_scenes(self) -> Outputs:
        """Close the open scene of every view (strips stopped coming) and process them."""
        out = Outputs()
        for asm in self.assemblers.values():
            for scene in asm.flush():
                out.extend(self._scene_closed(scene))
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
            if newest is not None and newest <= after_last + self.config.max_gap_lines * period_ns:
                continue
            for scene in asm.flush():
                out.extend(self._scene_closed(scene))
        return out

    # ---- streaming ----------------------------------------------------------------------
    @property
    def _can_stream(self) -> bool:
        c = self.config
        return c.streaming and not c.single_camera and c.scene_lines > 0

    def _scene_closed(self, scene: Scene) -> Outputs:
        stream = self._streams.get(scene.index)
        if stream is None or scene.view not in [s.view for s in stream.sides.values()]:
            return self._scene_done(scene)
        return self._stream_close(stream, scene)

    def _stream_start(self) -> Outputs:
        """Start streaming pair k once the scenes of both sides have begun (or one is done).

        A side whose scene is still arriving gets parameters extrapolated from the latest
        navigation; a side whose scene is already complete (fore/aft cameras: the aft camera
        sees the same ground later) keeps its parameters and has all its blocks emitted at once.
        When navigation lags behind the strips (separate topics, no ordering between them), the
        decision is held (``_stream_wait``: pair -> the decision time, the first line of the
        later scene) until navigation reaches that time; a scene still arriving then but
        completed in the meantime is held too (it waits for navigation anyway) and streamed at
        once, and a scene completed before it is processed whole first, as it would have been.
        So the outputs do not depend on the order in which the topics were delivered.
        """
        out = Outputs()
        for k in list(self._stream_wait):
            if k in self._streams or k in self._no_stream:
                del self._stream_wait[k]
        names = [v.name for v in self.config.views]
        opened = {n: self.assemblers[n].open_scene() for n in names}
        pending = {o.index for o in opened.values() if o is not None} | set(self._stream_wait)
        for k in sorted(pending):
            if k in self._streams or k in self._no_stream:
                continue
            parts: list[tuple[str, OpenScene | SceneResult]] = []
            held: dict[str, Scene] = {}  # complete scenes held for the decision, by view
            waiting = False  # a complete scene of the pair waits for navigation
            for n in names:
                o = opened[n]
                sc = next((w for w in self._waiting_nav if w.view == n and w.index == k), None)
                if o is not None and o.index == k:
                    parts.append((n, o))
                elif k in self._ready[n]:
                    parts.append((n, self._ready[n][k]))
                elif sc is not None and self._held(sc):
                    held[n] = sc
                    parts.append((n, OpenScene(sc.scene_id, k, sc.first_line_ns, sc.lines)))
                elif sc is not None:
                    waiting = True
            if len(parts) < 2:
                opens = [p.first_line_ns for _, p in parts if not isinstance(p, SceneResult)]
                last = self.nav.last_ns
                if (
                    waiting
                    and opens
                    and k not in self._stream_wait
                    and (last is None or last < max(opens) - self.nav.max_gap_s * 1e9)
                ):
                    # The other scene, complete, waits for navigation, which lags far behind
                    # this one's start: the decision waits for navigation (see above).
                    self._stream_wait[k] = max(opens)
                continue
            short = [sc for sc in held.values() if sc.lines != self.config.scene_lines]
            if short:
                self._no_stream.add(k)
                out.issues.append(
                    Issue(
                        "warn",
                        f"pair {k}",
                        "not streamed: navigation lagged behind the strips until "
                        + ", ".join(f"{sc.view}/{sc.scene_id}" for sc in short)
                        + f" ended short ({short[0].lines} of {self.config.scene_lines} "
                        "lines): processed whole",
                    )
                )
                continue
            if k == 0 and any(
                not isinstance(part, SceneResult) and not self._start_seen(part.first_line_ns)
                for _, part in parts
            ):
                # Perhaps the rest of a scene under way when the pipeline started: it will be
                # skipped when complete (_start_unseen), not streamed.
                self._no_stream.add(k)
                continue
            # Time of the line after the last one received, per open scene.
            ends = {
                o.scene_id: o.first_line_ns + o.lines * self._period(o)
                for o in opened.values()
                if o is not None
            }
            newest = max(ends.values(), default=0)
            duration = self.config.scene_lines * max(
                v.camera.line_period for v in self.config.views
            )
            stale_ns = max(1.0, 0.5 * duration) * 1e9
            overdue = [
                part
                for _, part in parts
                if not isinstance(part, SceneResult)
                and part.scene_id in ends
                and newest - ends[part.scene_id] > stale_ns
            ]
            if overdue:
                # Strips of a scene stopped coming while the other view went on (by more than
                # half a scene, at least 1 s): it is short (end of a pass) and its length is
                # unknown, so it is processed whole. A view merely delivered late is not stale.
                self._no_stream.add(k)
                out.issues.append(
                    Issue(
                        "ok",
                        f"pair {k}",
                        (
                            "not streamed: the strips of "
                            + ", ".join(p[0] for p in overdue)
                            + " stopped arriving (a short scene): processed whole"
                        ),
                    )
                )
                continue
            results: list[SceneResult] = []
            for name, part in parts:
                if isinstance(part, SceneResult):
                    results.append(part)
                    continue
                sc = held.get(name)
                res = self._predict_scene(
                    name,
                    part,
                    out,
                    max(p[2] for _, p in parts if not isinstance(p, SceneResult)),
                    None if sc is None else sc.image.dtype,
                )
                if res is None:
                    return out
                results.append(res)
            if k in self._no_stream:
                continue
            out.extend(self._open_stream(k, results))
            stream = self._streams.get(k)
            if stream is not None:
                if k in self._stream_wait:
                    out.issues.append(
                        Issue(
                            "ok",
                            f"pair {stream.geometry.pair_id}",
                            "navigation reached the scenes' start after their first strips: "
                            "streaming decision held until then",
                        )
                    )
                for sc in held.values():
                    self._waiting_nav.remove(sc)
                    out.extend(self._stream_close(stream, sc))
        return out

    def _period(self, opened: OpenScene) -> float:
        """Line period (ns) of the view whose open scene is ``opened``."""
        for name, asm in self.assemblers.items():
            if asm.open_scene() == opened:
                return self.views[name].camera.line_period * 1e9
        return 0.0

    def _predict_scene(
        self,
        name: str,
        opened: OpenScene,
        out: Outputs,
        decide_ns: int,
        dtype: np.dtype | None = None,
    ) -> SceneResult | None:
        """Parameters of a scene that has just started, from the latest navigation.

        ``decide_ns``: the decision time (the first line of the pair's later scene). When
        navigation has not reached within ``max_gap_s`` of the scene start then (it lags:
        separate topics), the pair waits (``_stream_wait``) until navigation reaches the
        decision time, and the motion is then fitted on the navigation up to that time only,
        as an on-time decision would have been. None: not (yet) possible.
        """
        sid, k, t0, _ = opened
        n_gcp = sum(1 for p in self.gcp.values() if sid in p.observations and not p.check)
        if n_gcp >= self.config.min_gcp:
            self._no_stream.add(k)  # GCP-based parameters need the whole scene
            return None
        view = self.views[name]
        lines = self.config.scene_lines
        until = self._stream_wait.get(k)
        last = self.nav.last_ns
        if until is not None and (last is None or last < until):
            return None  # navigation has not reached the decision time yet: keep waiting
        try:
            fit = self.nav.fit_recent(t0, view.mounting, until_ns=until)
        except NavigationError as err:
            if until is None:
                self._stream_wait[k] = decide_ns  # navigation lags: wait for it (see above)
                return None
            self._no_stream.add(k)
            out.issues.append(
                Issue(
                    "warn",
                    f"{name}/{sid}",
                    f"not streamed (navigation at the scene start: {err}): processed whole",
                )
            )
            return None
        model = PushbroomModel(view.camera, fit.motion)
        try:
            nav = parameters_from_navigation(
                model,
                line_mid=(lines - 1) / 2.0,
                z_avg=self.config.z_avg,
                scene_lines=lines,
                height_range=self.config.height_range,
                crab_tolerance_px=self.config.crab_tolerance_px,
            )
        except GeometryError as err:
            self._no_stream.add(k)
            out.issues.append(
                Issue("warn", f"{name}/{sid}", f"cannot stream ({err}): whole-scene processing")
            )
            return None
        if dtype is None:
            dtype = self.assemblers[name].retained()[1].dtype
        placeholder = Scene(
            name,
            sid,
            k,
            t0,
            view.camera.line_period,
            np.empty((0, view.camera.detectors), dtype=dtype),
            0,
            SceneEnd.STREAMING,
            lines,
        )
        return SceneResult.from_navigation(
            placeholder,
            nav,
            model,
            view.camera,
            note_suffix="; extrapolated from the navigation at the scene start (streaming)",
        )

    def _open_stream(self, k: int, results: list[SceneResult]) -> Outputs:
        out = Outputs()
        geo = self._pair_geometry(
            results[0], results[1], (results[0].scene.lines, results[1].scene.lines)
        )
        if isinstance(geo, Issue):
            self._no_stream.add(k)
            out.issues.append(geo)
            return out
        sides = {}
        for side, res, geom, grid in (
            ("left", results[0], geo.left_geom, geo.left_grid),
            ("right", results[1], geo.right_geom, geo.right_grid),
        ):
            sides[side] = SideStream(
                side,
                res.scene.view,
                res,
                geom,
                grid,
                res.scene.lines,
                plan_blocks(geom, grid, res.scene.lines),
            )
        stamp = max(r.scene.last_line_ns for r in results)
        stream = StreamPair(k, geo, sides, stamp)
        self._streams[k] = stream
        out.issues.append(
            Issue(
                "ok",
                f"pair {geo.pair_id}",
                f"streaming: {geo.left_grid.width} x {geo.left_grid.height} px in "
                f"{len(sides['left'].blocks)} + {len(sides['right'].blocks)} column blocks",
            )
        )
        for side in sides.values():
            if side.result.scene.image.shape[0] > 0:  # a side that was already complete
                self._ready[side.view].pop(k, None)
                out.extend(self._stream_close(stream, side.result.scene, prefetched=True))
        return out

    def _emit_blocks(
        self,
        stream: StreamPair,
        side: SideStream,
        received: int,
        data: NDArray[np.generic],
        first: int,
        complete: bool,
    ) -> Outputs:
        out = Outputs()
        while side.next_block < len(side.blocks):
            b = side.blocks[side.next_block]
            if not complete and b.max_line >= received:
                break
            img = render_block(
                b,
                data,
                first,
                side.grid,
                nodata=self.config.nodata,
                interpolation=self.interpolation_flag,
            )
            side.next_block += 1
            out.blocks.append(
                BlockResult(
                    stream.geometry.pair_id,
                    side.side,
                    side.next_block - 1,
                    b.col0,
                    img,
                    side.grid,
                    stream.stamp_ns,
                    side.next_block == len(side.blocks),
                )
            )
        return out

    def _stream_advance(self, view: str) -> Outputs:
        out = Outputs()
        asm = self.assemblers[view]
        opened = asm.open_scene()
        if opened is None:
            return out
        stream = self._streams.get(opened.index)
        if stream is None:
            return out
        for side in stream.sides.values():
            if side.view != view or side.done:
                continue
            first, data = asm.retained()
            out.extend(self._emit_blocks(stream, side, opened.lines, data, first, False))
            if side.next_block > 0:  # keep every line until the stream has really begun
                asm.release(side.needed_from())
        return out

    def _stream_close(self, stream: StreamPair, scene: Scene, prefetched: bool = False) -> Outputs:
        """A streamed side's scene is complete: its last blocks, and the pair if both are.

        ``prefetched``: the scene was complete before the stream started (its result is known;
        no parameters are published for it again).
        """
        out = Outputs()
        side = next(s for s in stream.sides.values() if s.view == scene.view)
        where = f"{scene.view}/{scene.scene_id}"
        if scene.lines != side.lines:
            self._streams.pop(stream.index, None)
            self._no_stream.add(stream.index)
            if all(s.next_block == 0 for s in stream.sides.values()) and scene.released == 0:
                # Nothing was published or released yet: fall back to whole scenes, unseen.
                for s in stream.sides.values():
                    if s.prefetched or (s.done and s.result.scene.image.shape[0] > 0):
                        self._ready[s.view][stream.index] = s.result
                return self._scene_done(scene)
            out.issues.append(
                Issue(
                    "error",
                    where,
                    f"scene ended after {scene.lines} of {side.lines} lines ({scene.reason}): "
                    f"streamed pair {stream.geometry.pair_id} abandoned after "
                    f"{side.next_block} of {len(side.blocks)} blocks; the blocks published "
                    "so far stay valid, the pair is not completed",
                )
            )
            return out
        out.extend(self._emit_blocks(stream, side, scene.lines, scene.image, scene.released, True))
        side.done = True
        side.prefetched = prefetched
        stream.scenes[side.side] = scene
        if not all(s.done for s in stream.sides.values()):
            return out
        self._streams.pop(stream.index, None)
        results = []
        for s in (stream.sides["left"], stream.sides["right"]):
            results.append(s.result)
            if s.prefetched:
                continue  # published when its scene completed
            check = self._check_extrapolation(s)
            if check is not None:
                out.issues.append(check)
            out.scenes.append(s.result)
            self._done_with(s.result.scene, s.result.method)
        out.pairs.append(
            self._pair_result(
                results[0], results[1], stream.geometry, (None, None), stream.stamp_ns
            )
        )
        return out

    def _check_extrapolation(self, side: SideStream) -> Issue | None:
        """Compare the extrapolated motion with a fit on the scene's own navigation."""
        res = side.result
        sc = res.scene
        if res.model is None or not self.nav.covers(sc.first_line_ns, sc.last_line_ns):
            return None
        try:
            fit = self.nav.fit(sc.first_line_ns, sc.last_line_ns, self.views[sc.view].mounting)
        except NavigationError:
            return None
        actual = PushbroomModel(res.camera, fit.motion)
        pts = virtual_points(
            res.model,
            (0.0, sc.lines - 1.0),
            [
                self.config.z_avg - self.config.height_range,
                self.config.z_avg + self.config.height_range,
            ],
            grid=5,
        )
        diff = float(np.abs(actual.project(pts) - res.model.project(pts)).max())
        if diff > 0.1:
            return Issue(
                "warn",
                f"{sc.view}/{sc.scene_id}",
                (
                    f"the motion extrapolated at the scene start differs from the scene's "
                    f"navigation by up to {diff:.3f} px: the streamed pair carries that error"
                ),
            )
        return None

    @property
    def has_open_scene(self) -> bool:
        """Whether any view has a scene still being assembled."""
        return any(a.is_open for a in self.assemblers.values())

    def flush(self) -> Outputs:
        """End of data: close open scenes, process what can be, report what cannot."""
        out = self.close_scenes()
        for scene in self._waiting_nav:
            if self._gcp_for(scene)[0].shape[0] >= self.config.min_gcp:
                out.extend(self._process_scene(scene))  # navigation ended early: GCP only
                continue
            self._done_with(scene, "skipped")
            out.issues.append(
                Issue(
                    "error",
                    f"{scene.view}/{scene.scene_id}",
                    "navigation never covered this scene and it has no GCP: scene skipped",
                )
            )
        self._waiting_nav = []
        self._stream_wait.clear()
        out.extend(self._unmade_pairs())
        return out

    # ---- scenes -------------------------------------------------------------------------
    def _scene_done(self, scene: Scene) -> Outputs:
        out = Outputs()
        if scene.gaps:
            out.issues.append(
                Issue(
                    "warn",
                    f"{scene.view}/{scene.scene_id}",
                    f"{scene.gaps} missing lines filled with no-data ({self.config.nodata})",
                )
            )
        has_gcp = self._gcp_for(scene)[0].shape[0] >= self.config.min_gcp
        if not self.nav.covers(scene.first_line_ns, scene.last_line_ns):
            last = self.nav.last_ns
            if has_gcp and (last is None or last >= scene.last_line_ns):
                # GCP alone will do: no navigation at all, or it will never cover the scene.
                out.extend(self._process_scene(scene))
                return out
            if last is not None and last >= scene.last_line_ns:
                self._done_with(scene, "skipped")
                out.issues.append(
                    Issue(
                        "error",
                        f"{scene.view}/{scene.scene_id}",
                        "navigation starts after the scene's first line and there are no GCP: "
                        "scene skipped",
                    )
                )
                return out
            self._waiting_nav.append(scene)
            return out
        out.extend(self._process_scene(scene))
        return out

    def _bad_observations(self, scene: Scene) -> list[str]:
        """Ids of GCP whose observation in this scene is non-finite or far outside it."""
        bad = []
        margin = 0.5 * max(scene.lines, scene.detectors)
        for p in self.gcp.values():
            obs = p.observations.get(scene.scene_id)
            if obs is None:
                continue
            line, sample = obs
            if not (np.isfinite(line) and np.isfinite(sample)) or not (
                -margin <= line <= scene.lines + margin
                and -margin <= sample <= scene.detectors + margin
            ):
                bad.append(p.id)
        return bad

    def _gcp_for(self, scene: Scene) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(xyz, line/sample) of GCP and of check points observed in this scene.

        Observations that are non-finite or far outside the scene are left out
        (:meth:`_bad_observations`).
        """
        _, gxyz, gls = self._gcp_observed(scene, check=False)
        _, cxyz, cls = self._gcp_observed(scene, check=True)
        return gxyz, gls, cxyz, cls

    def _start_seen(self, first_line_ns: int) -> bool:
        """Whether navigation arrived from ``start_margin_s`` before ``first_line_ns``.

        Also True without any navigation: it cannot be told then.
        """
        if self._nav_first_ns is None:
            return True
        return first_line_ns - self._nav_first_ns >= self.config.start_margin_s * 1e9

    def _start_unseen(self, scene: Scene) -> Issue | None:
        """An ERROR when ``scene`` may have begun before the pipeline was listening.

        Only a view's first scene can (``start_margin_s``). Its line numbers (to which GCP
        observations refer) and its place in the pairs would be guesses: it is not processed.
        """
        if scene.index > 0 or self._start_seen(scene.first_line_ns):
            return None
        lead = (scene.first_line_ns - (self._nav_first_ns or 0)) / 1e9
        when = f"{lead:.3f} s before" if lead >= 0 else f"{-lead:.3f} s after"
        return Issue(
            "error",
            f"{scene.view}/{scene.scene_id}",
            f"first scene received on view {scene.view} ({scene.lines} lines), and navigation "
            f"starts only {when} its first line (less than {self.config.start_margin_s} s "
            "before): the node may have started, or restarted, while this scene was under "
            "way, so its beginning, its line numbers (GCP observations) and its pair are "
            "unknown: scene skipped",
        )

    def _process_scene(self, scene: Scene) -> Outputs:
        out = Outputs()
        where = f"{scene.view}/{scene.scene_id}"
        unseen = self._start_unseen(scene)
        if unseen is not None:
            out.issues.append(unseen)
            return out
        view = self.views[scene.view]
        cam = view.camera
        nav_result = None
        model = None
        try:
            fit = self.nav.fit(scene.first_line_ns, scene.last_line_ns, view.mounting)
            model = PushbroomModel(cam, fit.motion)
            if fit.position_rms_m > self.config.nav_position_tolerance_m:
                out.issues.append(
                    Issue(
                        "warn",
                        where,
                        (
                            f"navigation positions scatter by {fit.position_rms_m:.3f} m rms "
                            "about the "
                            "constant-velocity line "
                            f"(> {self.config.nav_position_tolerance_m} m): an "
                            "outlier or a manoeuvre; the parameters carry that error"
                        ),
                    )
                )
            if fit.attitude_spread_rad > 1e-3:
                out.issues.append(
                    Issue(
                        "warn",
                        where,
                        (
                            f"attitude varies by {np.degrees(fit.attitude_spread_rad):.3f} deg "
                            "over the scene: the constant-attitude model is an approximation"
                        ),
                    )
                )
            nav_result = parameters_from_navigation(
                model,
                line_mid=(scene.lines - 1) / 2.0,
                z_avg=self.config.z_avg,
                scene_lines=scene.lines,
                height_range=self.config.height_range,
                crab_tolerance_px=self.config.crab_tolerance_px,
            )
        except (NavigationError, GeometryError) as err:
            out.issues.append(Issue("warn", where, f"no navigation-derived parameters: {err}"))
        for pid in self._bad_observations(scene):
            obs = self.gcp[pid].observations[scene.scene_id]
            out.issues.append(
                Issue(
                    "warn",
                    f"gcp {pid}",
                    (
                        f"observation in {scene.scene_id} at line {obs[0]}, sample {obs[1]} "
                        "is not in "
                        f"the scene ({scene.lines} x {scene.detectors}): ignored"
                    ),
                )
            )
        gxyz, gls, cxyz, cls = self._gcp_for(scene)
        result: SceneResult | None = None
        if len(gxyz) >= self.config.min_gcp:
            try:
                result = self._from_gcp(scene, nav_result, gxyz, gls, cxyz, cls)
            except GeometryError as err:
                out.issues.append(
                    Issue(
                        "warn",
                        where,
                        f"GCP estimation failed ({err}); "
                        + ("using navigation" if nav_result else ""),
                    )
                )
        elif len(gxyz) > 0:
            out.issues.append(
                Issue(
                    "warn",
                    where,
                    (f"only {len(gxyz)} GCP observed (need {self.config.min_gcp}): GCP not used"),
                )
            )
        if result is None and nav_result is not None and model is not None:
            result = SceneResult.from_navigation(scene, nav_result, model, cam)
            if nav_result.method != Method.NAVIGATION:
                out.issues.append(Issue("warn", where, nav_result.note))
        if result is None:
            self._done_with(scene, "skipped")
            out.issues.append(
                Issue("error", where, "no parameters (no usable navigation or GCP): scene skipped")
            )
            return out
        self._done_with(scene, result.method)
        out.scenes.append(result)
        if not self.config.single_camera:
            self._ready[scene.view][scene.index] = result
        elif scene.part == 0:
            # Single camera: pairs are acquisitions 2k and 2k+1 (a look forward, then back),
            # whatever parts a gap or scene_lines cut them into; each is paired by its first
            # part, so that one split does not shift every later pair.
            self._ready[scene.view][scene.acquisition] = result
        else:
            out.issues.append(
                Issue(
                    "warn",
                    where,
                    f"part {scene.part} of an acquisition that was split: its parameters are "
                    "published, but single-camera pairs are made of the first parts of two "
                    "acquisitions: not paired",
                )
            )
        out.extend(self._try_pairs())
        return out

    def _from_gcp(
        self,
        scene: Scene,
        nav_result: object,
        gxyz: FloatArray,
        gls: FloatArray,
        cxyz: FloatArray,
        cls: FloatArray,
        reference: ParallelProjection | None = None,
    ) -> SceneResult:
        view = self.views[scene.view]
        cam = view.camera
        from ..geometry.navigation import NavigationParameters

        nav = nav_result if isinstance(nav_result, NavigationParameters) else None
        frame = (
            nav.frame
            if nav
            else SceneFrame((scene.lines - 1) / 2.0, cam.pixel_size, cam.pixel_size, cam.pp)
        )
        obs = frame.to_scene(gls[:, 0], gls[:, 1])
        roll_mode = self.config.gcp_roll
        if roll_mode == "navigation" and nav is None:
            roll_mode = "estimate"
        psi_in = {"estimate": None, "navigation": nav.psi if nav else 0.0, "none": 0.0}[roll_mode]
        method = {
            "estimate": Method.GCP_ROLL_ESTIMATED,
            "navigation": Method.GCP_KNOWN_ROLL,
            "none": Method.GCP_AFFINE,
        }[roll_mode]
        est = estimate_affine(
            gxyz,
            obs,
            principal_distance=cam.principal_distance,
            pixel_size=cam.pixel_size,
            psi=psi_in,
        )
        if reference is None and nav is not None:
            reference = nav.params
        inv = (
            affine_to_nonlinear(est.affine, rule="reference", reference=reference)
            if reference is not None
            else affine_to_nonlinear(est.affine)
        )
        norms = est.residual_norms_px
        check_rms = float("nan")
        if len(cxyz):
            errs = est.check(cxyz, frame.to_scene(cls[:, 0], cls[:, 1]))
            check_rms = float(np.sqrt(np.mean(np.sum(errs**2, axis=1))) / cam.pixel_size)
        note = (
            f"{len(gxyz)} GCP, {method.replace('_', ' ')}, psi {np.degrees(est.psi):.3f} deg; "
            f"mirror solution: {inv.rule}"
        )
        return SceneResult(
            scene,
            inv.chosen,
            est.affine,
            est.psi,
            frame,
            method,
            note,
            None if nav is None else PushbroomModel(cam, self._model_motion(scene)),
            cam,
            sigma0_px=est.sigma0_px,
            residual_rms_px=float(np.sqrt(np.mean(norms**2))),
            residual_max_px=float(norms.max()),
            gcp_count=len(gxyz),
            check_count=len(cxyz),
            check_rms_px=check_rms,
            covariance=est.covariance,
            crab_angle=nav.crab_angle if nav else float("nan"),
        )

    def _model_motion(self, scene: Scene):  # type: ignore[no-untyped-def]
        return self.nav.fit(
            scene.first_line_ns, scene.last_line_ns, self.views[scene.view].mounting
        ).motion

    # ---- pair selection (single camera) -------------------------------------------------
    def set_pairs(self, pairs: Sequence[tuple[str, str]]) -> Outputs:
        """Select which acquisitions pair up (single-camera mode; the node's ``pairs`` topic).

        ``pairs`` are (left scene id, right scene id): acquisitions (strip frame_ids, their
        first parts). A scene may be in several pairs: it is kept until every selected pair
        that needs it is made, then released. The selection replaces any earlier one for the
        pairs not made yet; scenes held that it no longer needs are released (WARN). Bad
        entries are reported and left out, the others kept: an empty id, a scene paired with
        itself, a pair listed twice (in either order), a scene already done with and released
        (processed under an earlier rule, or skipped). Scene ids that never arrive are
        reported when the data end (:meth:`flush`). Two-view mode ignores the selection.
        """
        out = Outputs()
        if not self.config.single_camera:
            out.issues.append(
                Issue(
                    "warn",
                    "pairs",
                    "pair selection ignored: with two views the k-th scenes of the views pair "
                    "up (it is for single-camera mode)",
                )
            )
            return out
        held = {r.scene.scene_id for r in self._ready[self.config.views[0].name].values()}
        chosen: list[tuple[str, str]] = []
        seen: set[frozenset[str]] = set()
        for left, right in pairs:
            name = f"{left}:{right}"
            key = frozenset((left, right))
            why = ""
            if not left or not right:
                why = "an empty scene id"
            elif left == right:
                why = f"scene {left} paired with itself (no base)"
            elif key in seen:
                why = "listed twice (in this or the reverse order): the first one kept"
            elif key in self._made:
                seen.add(key)
                out.issues.append(Issue("ok", f"pair {name}", "already made: not made again"))
                continue
            else:
                gone = [s for s in (left, right) if s in self._done and s not in held]
                if gone:
                    why = "scene " + ", ".join(
                        f"{s} was already {self._done_how(s)} and released" for s in gone
                    )
            if why:
                out.issues.append(Issue("error", f"pair {name}", f"{why}: pair left out"))
                continue
            seen.add(key)
            chosen.append((left, right))
        self._selection = chosen
        out.issues.append(
            Issue(
                "ok" if chosen else "warn",
                "pairs",
                f"pair selection: {len(chosen)} pairs to make"
                + (": " + ", ".join(f"{a}:{b}" for a, b in chosen[:20]) if chosen else "")
                + (" ..." if len(chosen) > 20 else ""),
            )
        )
        out.extend(self._try_selected_pairs())
        return out

    def _mark_made(self, left: str, right: str) -> None:
        """Remember a single-camera pair as made (the latest 1024), for later selections."""
        self._made[frozenset((left, right))] = None
        while len(self._made) > 1024:
            del self._made[next(iter(self._made))]

    def _done_how(self, scene_id: str) -> str:
        method = self._done[scene_id][1]
        return "skipped" if method == "skipped" else f"processed ({method})"

    def _selected_scene_ids(self) -> set[str]:
        """Scene ids that a selected pair not made yet still needs."""
        return {s for pair in self._selection or () for s in pair}

    def _try_selected_pairs(self, warn_unpaired: bool = True) -> Outputs:
        """Make the selected pairs whose scenes are both ready; release scenes no pair needs.

        ``warn_unpaired``: a WARN for each released scene that no pair used.
        """
        out = Outputs()
        ready = self._ready[self.config.views[0].name]
        by_id = {r.scene.scene_id: r for r in ready.values()}
        remaining: list[tuple[str, str]] = []
        for left, right in self._selection or ():
            if left in by_id and right in by_id:
                self._mark_made(left, right)
                out.extend(self._make_pair(by_id[left], by_id[right]))
                continue
            gone = [s for s in (left, right) if s in self._done and s not in by_id]
            if gone:
                out.issues.append(
                    Issue(
                        "error",
                        f"pair {left}:{right}",
                        "scene "
                        + ", ".join(f"{s} was {self._done_how(s)}" for s in gone)
                        + ": pair not made",
                    )
                )
                continue
            remaining.append((left, right))
        self._selection = remaining
        needed = self._selected_scene_ids()
        for acq, res in list(ready.items()):
            sid = res.scene.scene_id
            if sid in needed:
                continue
            del ready[acq]  # every pair that needed it is made: its pixels are released
            if warn_unpaired and not any(sid in pair for pair in self._made):
                out.issues.append(
                    Issue(
                        "warn",
                        f"{res.scene.view}/{sid}",
                        "in no selected pair (pairs topic): parameters published, not paired",
                    )
                )
            self._forget_gcp((sid,))
        return out

    def _unmade_pairs(self) -> Outputs:
        """End of data: an ERROR per selected pair not made (a scene never arrived)."""
        out = Outputs()
        ready = self._ready[self.config.views[0].name] if self.config.single_camera else {}
        have = {r.scene.scene_id for r in ready.values()}
        for left, right in self._selection or ():
            missing = [s for s in (left, right) if s not in have]
            out.issues.append(
                Issue(
                    "error",
                    f"pair {left}:{right}",
                    "scene "
                    + ", ".join(missing)
                    + " never received (unknown scene id?): selected pair not made",
                )
            )
        if self._selection:
            self._selection = []
            out.extend(self._try_selected_pairs(warn_unpaired=False))  # release their scenes
        return out

    # ---- pairs --------------------------------------------------------------------------
    def _try_pairs(self) -> Outputs:
        out = Outputs()
        names = [v.name for v in self.config.views]
        if self.config.single_camera and self._selection is not None:
            out.extend(self._try_selected_pairs())
        elif self.config.single_camera:
            ready = self._ready[names[0]]
            for i in sorted(ready):
                if i % 2 == 0 and i + 1 in ready:
                    left, right = ready.pop(i), ready.pop(i + 1)
                    self._mark_made(left.scene.scene_id, right.scene.scene_id)
                    out.extend(self._make_pair(left, right))
        else:
            left, right = self._ready[names[0]], self._ready[names[1]]
            for i in sorted(set(left) & set(right)):
                out.extend(self._make_pair(left.pop(i), right.pop(i)))
        return out

    def _pair_geometry(
        self, left: SceneResult, right: SceneResult, lines: tuple[int, int]
    ) -> PairGeometry | Issue:
        """Normalization and output grids of a pair (scenes of ``lines`` lines each)."""
        pair_id = f"{left.scene.scene_id}+{right.scene.scene_id}"
        try:
            norm = normalize_pair(
                left.affine, right.affine, left_params=left.params, right_params=right.params
            )
        except DegenerateGeometryError as err:
            return Issue("error", f"pair {pair_id}", f"{err}: pair skipped")
        gl = left.geometry(norm.left)
        gr = right.geometry(norm.right)
        fl = footprint(gl, lines[0], left.scene.detectors)
        fr = footprint(gr, lines[1], right.scene.detectors)
        pix = self.config.output_pixel or min(native_pixel(gl), native_pixel(gr))
        y0 = max(fl[:, 1].min(), fr[:, 1].min())
        y1 = min(fl[:, 1].max(), fr[:, 1].max())
        if y1 <= y0:
            return Issue(
                "error",
                f"pair {pair_id}",
                "the scenes do not overlap across the epipolar lines: pair skipped",
            )
        shift = norm.parallax_per_height * self.config.z_avg + norm.parallax_offset
        xo_l = min(fl[:, 0].min(), fr[:, 0].min() + shift)
        x1 = max(fl[:, 0].max(), fr[:, 0].max() + shift)
        if self.config.output_extent == "overlap":
            span = self._overlap_columns(left, right, norm, fl, fr, shift)
            if span is None:
                return Issue(
                    "error",
                    f"pair {pair_id}",
                    "the scenes do not overlap along the epipolar lines at any height of the "
                    "pair (output_extent overlap): pair skipped",
                )
            xo_l, x1 = max(xo_l, span[0]), min(x1, span[1])
        width = int(np.floor((x1 - xo_l) / pix)) + 1
        height = int(np.floor((y1 - y0) / pix)) + 1
        if width * height > self.config.max_output_pixels:
            return Issue(
                "error",
                f"pair {pair_id}",
                f"normalized images would be {width} x {height} px (> max_output_pixels "
                f"{self.config.max_output_pixels}): pair skipped",
            )
        grid_l = OutputGrid(pix, xo_l, y0, width, height)
        grid_r = OutputGrid(pix, xo_l - shift, y0, width, height)
        return PairGeometry(pair_id, norm, gl, gr, grid_l, grid_r)

    def _pair_heights(self, left: SceneResult, right: SceneResult) -> tuple[float, float]:
        """Heights (m) of the pair's ground: its GCP and check points, else z_avg +- height_range.

        With at least ``min_gcp`` points observed in either scene, their height span widened
        by 10 % of it (at least 1 m) on each side; otherwise ``z_avg`` +- ``height_range``.
        """
        ids = (left.scene.scene_id, right.scene.scene_id)
        z = np.array(
            [p.xyz[2] for p in self.gcp.values() if any(s in p.observations for s in ids)]
        )
        if z.size >= self.config.min_gcp:
            pad = max(0.1 * float(np.ptp(z)), 1.0)
            return float(z.min()) - pad, float(z.max()) + pad
        c = self.config
        return c.z_avg - c.height_range, c.z_avg + c.height_range

    def _overlap_columns(
        self,
        left: SceneResult,
        right: SceneResult,
        norm: Normalization,
        fl: FloatArray,
        fr: FloatArray,
        shift: float,
    ) -> tuple[float, float] | None:
        """Normalized x range (left image metres) of the ground both scenes see (None: none).

        A point at height z is at x_l in the left image and at x_l - d, d = k (z - z_avg), in
        the right one (in the left image's x, the right grid being shifted by ``shift``). Over
        the pair's heights (:meth:`_pair_heights`) the left image needs the x_l in its
        footprint ``fl`` whose partner lies in the right footprint ``fr``, and the right image
        the converse; the range is the hull of both.
        """
        k = norm.parallax_per_height
        zlo, zhi = self._pair_heights(left, right)
        d = (k * (zlo - self.config.z_avg), k * (zhi - self.config.z_avg))
        dlo, dhi = min(d), max(d)
        l0, l1 = float(fl[:, 0].min()), float(fl[:, 0].max())
        r0, r1 = float(fr[:, 0].min()) + shift, float(fr[:, 0].max()) + shift
        lo = min(max(l0, r0 + dlo), max(r0, l0 - dhi))
        hi = max(min(l1, r1 + dhi), min(r1, l1 - dlo))
        return (lo, hi) if hi > lo else None

    @property
    def interpolation_flag(self) -> int:
        """OpenCV interpolation flag of the configured interpolation."""
        return cv2.INTER_CUBIC if self.config.interpolation == "cubic" else cv2.INTER_LINEAR

    def _pair_result(
        self,
        left: SceneResult,
        right: SceneResult,
        geo: PairGeometry,
        images: tuple[NDArray[np.generic] | None, NDArray[np.generic] | None],
        stamp_ns: int,
    ) -> PairResult:
        ypar, source = self._y_parallax(left, right, geo.left_geom, geo.right_geom)
        k = geo.normalization.parallax_per_height
        self.pairs_done += 1
        self._forget_gcp((left.scene.scene_id, right.scene.scene_id))
        self._no_stream.discard(left.scene.index)
        return PairResult(
            geo.pair_id,
            stamp_ns,
            left,
            right,
            geo.normalization,
            geo.left_grid,
            geo.right_grid,
            images[0],
            images[1],
            geo.left_grid.pixel / k,
            (geo.left_grid.x_origin - geo.right_grid.x_origin - geo.normalization.parallax_offset)
            / k,
            ypar,
            source,
        )

    def _gcp_observed(self, scene: Scene, check: bool) -> tuple[list[str], FloatArray, FloatArray]:
        """(ids, xyz, line/sample) of the GCP (or check points) observed in ``scene``."""
        bad = set(self._bad_observations(scene))
        ids = [
            p.id
            for p in self.gcp.values()
            if p.check == check and scene.scene_id in p.observations and p.id not in bad
        ]
        xyz = np.array([self.gcp[i].xyz for i in ids]).reshape(-1, 3)
        ls = np.array([self.gcp[i].observations[scene.scene_id] for i in ids]).reshape(-1, 2)
        return ids, xyz, ls

    def _segment(self, left: SceneResult, right: SceneResult) -> tuple[Outputs, bool]:
        """Cut a GCP pair whose model error exceeds the bound into segment pairs.

        Returns (outputs, cut): with ``cut`` the segments' scene results and pairs; otherwise
        the whole scenes are to be paired, and the outputs hold an issue when cutting was tried
        and did not help.
        """
        out = Outputs()
        bound = self.config.segment_max_error_px
        whole = max(left.residual_max_px, right.residual_max_px)
        if (
            bound <= 0
            or whole <= bound
            or not (left.method.startswith("gcp") and right.method.startswith("gcp"))
            or left.scene.released
            or right.scene.released
        ):
            return out, False
        pair_id = f"pair {left.scene.scene_id}+{right.scene.scene_id}"
        # (GCP, check points) observed in each whole scene
        observed = {
            r.scene.scene_id: [self._gcp_observed(r.scene, check) for check in (False, True)]
            for r in (left, right)
        }
        (idl, xl, ll), (idr, xr, lr) = (observed[r.scene.scene_id][0] for r in (left, right))
        pos_r = {pid: k for k, pid in enumerate(idr)}
        common = [(k, pos_r[pid]) for k, pid in enumerate(idl) if pid in pos_r]
        ci = np.array(common, dtype=np.intp).reshape(-1, 2)

        def side(r: SceneResult) -> SideCamera:
            psi = None if r.method == Method.GCP_ROLL_ESTIMATED else r.psi
            return SideCamera(r.camera.principal_distance, r.camera.pixel_size, r.camera.pp, psi)

        try:
            seg = segment_pair(
                xl,
                ll,
                xr,
                lr,
                (ci[:, 0], ci[:, 1]),
                lines=(left.scene.lines, right.scene.lines),
                cameras=(side(left), side(right)),
                bound_px=bound,
                overlap=self.config.segment_overlap,
                min_points=max(2 * self.config.min_gcp, 10),
            )
        except GeometryError as err:
            seg = None
            why = str(err)
        if seg is None or seg.count == 1:
            why = seg.note if seg is not None else why
            out.issues.append(
                Issue(
                    "warn",
                    pair_id,
                    f"model error {whole:.3f} px > bound {bound:g} px "
                    f"(segment_max_error_px), but cutting the scenes does not help: {why}; "
                    "the whole scenes are paired",
                )
            )
            return out, False
        out.issues.append(
            Issue(
                "ok" if seg.reached else "warn",
                pair_id,
                f"model error {seg.whole_error_px[0]:.3f} / {seg.whole_error_px[1]:.3f} px "
                f"(left / right) > bound {bound:g} px: cut into {seg.count} segment pairs "
                f"with {self.config.segment_overlap:.0%} overlap; largest segment error "
                f"{seg.max_error_px:.3f} px, "
                + ("bound met" if seg.reached else f"bound NOT met ({seg.note})"),
            )
        )
        for k, (sl, sr) in enumerate(zip(seg.left, seg.right, strict=True)):
            parts = []
            for whole_res, fit in ((left, sl), (right, sr)):
                sc = whole_res.scene
                sub = replace(
                    sc,
                    scene_id=f"{sc.scene_id}.seg{k}",
                    first_line_ns=sc.first_line_ns + round(fit.start * sc.line_period * 1e9),
                    image=sc.image[fit.start : fit.stop],
                    gaps=0,
                )
                for ids, _, ls in observed[sc.scene_id]:
                    for pid, (ln, smp) in zip(ids, ls, strict=True):
                        if fit.start - 0.5 <= ln <= fit.stop - 0.5:
                            self.gcp[pid].observations[sub.scene_id] = (ln - fit.start, smp)
                gx, gl, cx, cl = self._gcp_for(sub)
                try:
                    res = self._from_gcp(sub, None, gx, gl, cx, cl, reference=whole_res.params)
                except GeometryError as err:  # the segmentation fitted it: not expected
                    out.issues.append(Issue("error", pair_id, f"segment {k}: {err}: skipped"))
                    break
                res = replace(
                    res,
                    model=None,  # the rigorous model counts lines of the whole scene
                    segment_of=sc.scene_id,
                    segment_first_line=fit.start,
                    model_error_bound_px=bound,
                    note=f"segment {k + 1} of {seg.count}, lines {fit.start}..{fit.stop - 1} "
                    f"of {sc.scene_id}; {res.note}",
                )
                parts.append(res)
            else:
                out.scenes += parts
                out.extend(self._make_whole_pair(parts[0], parts[1]))
        self._forget_gcp((left.scene.scene_id, right.scene.scene_id))  # the segments' are gone
        return out, True

    def _make_pair(self, left: SceneResult, right: SceneResult) -> Outputs:
        out, cut = self._segment(left, right)
        if not cut:
            out.extend(self._make_whole_pair(left, right))
        return out

    def _make_whole_pair(self, left: SceneResult, right: SceneResult) -> Outputs:
        out = Outputs()
        geo = self._pair_geometry(left, right, (left.scene.lines, right.scene.lines))
        if isinstance(geo, Issue):
            out.issues.append(geo)
            return out

        def warp(res: SceneResult, geom: SceneGeometry, grid: OutputGrid) -> NDArray[np.generic]:
            return resample(
                res.scene.image,
                geom,
                grid,
                nodata=self.config.nodata,
                interpolation=self.interpolation_flag,
            )

        img_l = warp(left, geo.left_geom, geo.left_grid)
        img_r = warp(right, geo.right_geom, geo.right_grid)
        stamp = max(left.scene.last_line_ns, right.scene.last_line_ns)
        tie: TieRefinement | None = None
        if self.config.tie_points:
            refined = refine_with_tie_points(
                geo,
                img_l,
                img_r,
                nodata=self.config.nodata,
                pixel=left.camera.pixel_size,
                threshold_px=self.config.tie_threshold_px,
            )
            if isinstance(refined, str):
                out.issues.append(Issue("warn", f"pair {geo.pair_id}", refined))
            else:
                tie = refined
                geo = tie.geometry
                img_r = warp(right, geo.right_geom, geo.right_grid)
                out.issues.append(Issue("ok", f"pair {geo.pair_id}", tie.summary))
        pair = self._pair_result(left, right, geo, (img_l, img_r), stamp)
        if tie is not None:
            pair = replace(pair, y_parallax_px=tie.residual_px, y_parallax_source="tie_points")
        out.pairs.append(pair)
        return out

    def _y_parallax(
        self, left: SceneResult, right: SceneResult, gl: SceneGeometry, gr: SceneGeometry
    ) -> tuple[FloatArray, str]:
        """Geometric y-parallax (px): GCP/check points, else virtual points of the models."""
        pts, ls_l, ls_r = [], [], []
        for p in self.gcp.values():
            a = p.observations.get(left.scene.scene_id)
            b = p.observations.get(right.scene.scene_id)
            if a is not None and b is not None:
                ls_l.append(a)
                ls_r.append(b)
                pts.append(p.xyz)
        pixel = self.views[left.scene.view].camera.pixel_size
        if len(pts) >= 1:
            nl = gl.image_to_normalized(np.array(ls_l)[:, 0], np.array(ls_l)[:, 1])
            nr = gr.image_to_normalized(np.array(ls_r)[:, 0], np.array(ls_r)[:, 1])
            return (nl[:, 1] - nr[:, 1]) / pixel, "gcp"
        if left.model is not None and right.model is not None:
            z = self.config.z_avg
            h = self.config.height_range
            obj = virtual_points(
                left.model, (0.0, left.scene.lines - 1.0), [z - h, z, z + h], grid=11
            )
            lr = right.model.project(obj)
            inside = (
                (lr[:, 0] >= 0)
                & (lr[:, 0] <= right.scene.lines - 1)
                & (lr[:, 1] >= 0)
                & (lr[:, 1] <= right.scene.detectors - 1)
            )
            if inside.sum() >= 1:
                ll = left.model.project(obj[inside])
                nl = gl.image_to_normalized(ll[:, 0], ll[:, 1])
                nr = gr.image_to_normalized(lr[inside, 0], lr[inside, 1])
                return (nl[:, 1] - nr[:, 1]) / pixel, "virtual"
        return np.zeros(0), "none"
