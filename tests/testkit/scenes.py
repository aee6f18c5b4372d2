"""Synthetic scenarios fed to the Pipeline as events (no ROS): images, navigation, strips."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from parproj_ros.core.pipeline import Outputs, Pipeline
from parproj_ros.core.trajectory import NavSample
from parproj_ros.sim.scenarios import Scenario

#: (time ns, kind, item): kind 0 is a NavSample, kind 1 the arguments of Pipeline.add_strip.
Event = tuple[int, int, Any]


def render(scn: Scenario, dtype: type, *, smooth: bool = False, low: int = 1) -> list[np.ndarray]:
    """One image per scene: random texture in [low, high), or a smooth pattern."""
    rng = np.random.default_rng(0)
    out = []
    for sc in scn.scenes:
        det = next(v for v in scn.views if v.name == sc.view).camera.detectors
        if smooth:
            ll, ss = np.mgrid[0 : sc.lines, 0:det].astype(float)
            img = 1000.0 + 400.0 * np.sin(ll / 41.0 + 0.3) * np.cos(ss / 53.0) + 0.5 * ss
        else:
            img = rng.integers(low, 250 if dtype == np.uint8 else 2000, (sc.lines, det))
        out.append(img.astype(dtype))
    return out


def nav_samples(
    scn: Scenario, offset: Callable[[float], np.ndarray] | None = None
) -> list[NavSample]:
    """The true navigation at nav_rate_hz, from 1 s before the first scene to 1 s after the
    last; ``offset(t)`` is added to the positions."""
    lp = scn.views[0].camera.line_period
    first = min(sc.start_s for sc in scn.scenes) - 1.0
    last = max(sc.start_s + sc.lines * lp for sc in scn.scenes) + 1.0
    vel = np.array(scn.velocity)
    out = []
    for t in np.arange(first, last, 1.0 / scn.nav_rate_hz):
        pos = np.array(scn.position0) + t * vel
        if offset is not None:
            pos = pos + offset(float(t))
        out.append(NavSample(scn.time_ns(float(t)), pos, scn.body_rotation(float(t)), vel))
    return out


def nav_events(
    scn: Scenario, *, offset: Callable[[float], np.ndarray] | None = None
) -> list[Event]:
    return [(s.t_ns, 0, s) for s in nav_samples(scn, offset)]


def strip_events(
    scn: Scenario, images: list[np.ndarray], skip: Iterable[tuple[int, int]] = ()
) -> list[Event]:
    """The strips of every scene, stamped ``time_ns(start_s + r0 * line_period)``; ``skip``:
    (scene index, first row) of strips left out."""
    skipped = set(skip)
    ev = []
    for i, sc in enumerate(scn.scenes):
        lp = next(v for v in scn.views if v.name == sc.view).camera.line_period
        for r0 in range(0, sc.lines, scn.strip_lines):
            if (i, r0) in skipped:
                continue
            st = scn.time_ns(sc.start_s + r0 * lp)
            ev.append(
                (st, 1, (sc.view, st, scn.scene_id(i), images[i][r0 : r0 + scn.strip_lines]))
            )
    return ev


def feed(pipe: Pipeline, events: Iterable[Event], *, flush: bool = True) -> Outputs:
    """Events in arrival order, then (``flush``) end of data, as the node on SIGINT and
    ``process``."""
    out = Outputs()
    for _, kind, item in sorted(events, key=lambda e: (e[0], e[1])):
        out.extend(pipe.add_navigation(item) if kind == 0 else pipe.add_strip(*item))
    if flush:
        out.extend(pipe.flush())
    return out


def small_scenario(name: str = "ikonos_agile", size: int = 384) -> Scenario:
    """A scenario's geometry with ``size`` x ``size`` px scenes (same middle lines), no GCP."""
    import dataclasses

    from parproj_ros.sim.scenarios import SCENARIOS

    scn = SCENARIOS[name]()
    cam = dataclasses.replace(scn.views[0].camera, detectors=size)
    view = dataclasses.replace(scn.views[0], camera=cam)
    dt = (scn.scenes[0].lines - size) / 2 * cam.line_period
    scenes = tuple(dataclasses.replace(s, lines=size, start_s=s.start_s + dt) for s in scn.scenes)
    return dataclasses.replace(scn, views=(view,), scenes=scenes, gcp=0, check=0)


def rendered(scn: Scenario) -> tuple[Any, list[np.ndarray]]:
    """The scenario's terrain and its scenes rendered over it (uint16) through the rigorous
    model."""
    from parproj_ros.sim.simulate import render_scene
    from parproj_ros.sim.terrain import procedural_terrain

    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    scenes = [
        render_scene(scn.model(i), terrain, 0, sc.lines, dtype=np.uint16, workers=2)
        for i, sc in enumerate(scn.scenes)
    ]
    return terrain, scenes
