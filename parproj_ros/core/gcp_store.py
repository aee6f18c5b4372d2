"""GCP memory of the pipeline: the ground control and check points of paper 1 section 4 (Eq 8).

Points arrive on their own topic, each with its image observations by scene id; they are kept
until the scenes they are observed in are paired (scene ids never repeat), so that GCP sets sent
with every acquisition do not pile up. Coordinates are object space (local Cartesian, Z up,
metres); observations are (line, sample) pixels of the scene.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ..imaging.assembly import Scene
from .results import GroundPoint, Issue, Level, Outputs

FloatArray = NDArray[np.float64]


class GcpStore:
    """The GCP and check points known, by id (:attr:`points`, in arrival order)."""

    def __init__(self) -> None:
        self.points: dict[str, GroundPoint] = {}

    def add(self, points: Sequence[GroundPoint], done: Mapping[str, tuple[str, str]]) -> Outputs:
        """Add or replace ground control points (by id).

        ``done``: the scenes already done with, scene id -> (view, method or "skipped").
        Observations in them are dropped and reported, one warning per scene: they come too
        late to be used.
        """
        out = Outputs()
        late: dict[str, int] = {}
        for p in points:
            xyz = np.asarray(p.xyz, dtype=float)
            if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
                out.issues.append(
                    Issue(Level.WARN, f"gcp {p.id}", "non-finite coordinates: ignored")
                )
                continue
            seen = [s for s in p.observations if s in done]
            if seen:
                for s in seen:
                    late[s] = late.get(s, 0) + 1
                p = replace(
                    p, observations={s: o for s, o in p.observations.items() if s not in seen}
                )
                if not p.observations:
                    continue
            self.points[p.id] = p
        for sid, n in late.items():
            view, method = done[sid]
            out.issues.append(
                Issue(
                    Level.WARN,
                    f"{view}/{sid}",
                    f"{n} GCP and check points observed in this scene arrived after it was "
                    + ("skipped" if method == "skipped" else f"processed ({method})")
                    + ": not used",
                )
            )
        return out

    def forget(self, scene_ids: tuple[str, ...], keep: Collection[str] = ()) -> None:
        """Drop the observations in the scenes of a finished pair (scene ids never repeat).

        A point left with no observation is dropped. Scenes in ``keep`` (that a selected pair
        still needs) keep theirs.
        """
        scene_ids = tuple(s for s in scene_ids if s not in keep)
        for pid, p in list(self.points.items()):
            if not any(s in p.observations for s in scene_ids):
                continue
            obs = {s: o for s, o in p.observations.items() if s not in scene_ids}
            if obs:
                self.points[pid] = replace(p, observations=obs)
            else:
                del self.points[pid]

    def count(self, scene_id: str) -> int:
        """Number of GCP (check points not counted) observed in a scene."""
        return sum(1 for p in self.points.values() if scene_id in p.observations and not p.check)

    def bad_observations(self, scene: Scene) -> list[str]:
        """Ids of GCP whose observation in this scene is non-finite or far outside it."""
        bad = []
        margin = 0.5 * max(scene.lines, scene.detectors)
        for p in self.points.values():
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

    def bad_observation_issues(self, scene: Scene) -> list[Issue]:
        """A WARN per observation in ``scene`` left out (:meth:`bad_observations`)."""
        issues = []
        for pid in self.bad_observations(scene):
            obs = self.points[pid].observations[scene.scene_id]
            issues.append(
                Issue(
                    Level.WARN,
                    f"gcp {pid}",
                    (
                        f"observation in {scene.scene_id} at line {obs[0]}, sample {obs[1]} "
                        "is not in "
                        f"the scene ({scene.lines} x {scene.detectors}): ignored"
                    ),
                )
            )
        return issues

    def observed(self, scene: Scene, check: bool) -> tuple[list[str], FloatArray, FloatArray]:
        """(ids, xyz (m), line/sample (px)) of the GCP (or check points) observed in ``scene``.

        Observations that are non-finite or far outside the scene are left out
        (:meth:`bad_observations`).
        """
        bad = set(self.bad_observations(scene))
        ids = [
            p.id
            for p in self.points.values()
            if p.check == check and scene.scene_id in p.observations and p.id not in bad
        ]
        xyz = np.array([self.points[i].xyz for i in ids]).reshape(-1, 3)
        ls = np.array([self.points[i].observations[scene.scene_id] for i in ids]).reshape(-1, 2)
        return ids, xyz, ls

    def for_scene(self, scene: Scene) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(xyz, line/sample) of the GCP, then of the check points, observed in this scene."""
        _, gxyz, gls = self.observed(scene, check=False)
        _, cxyz, cls = self.observed(scene, check=True)
        return gxyz, gls, cxyz, cls

    def heights(self, scene_ids: tuple[str, ...]) -> FloatArray:
        """Heights Z (m) of the points observed in any of ``scene_ids``."""
        return np.array(
            [p.xyz[2] for p in self.points.values() if any(s in p.observations for s in scene_ids)]
        )

    def common(
        self, left_id: str, right_id: str
    ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
        """(line, sample) observations in the left and in the right scene of the points in both."""
        ls_l, ls_r = [], []
        for p in self.points.values():
            a = p.observations.get(left_id)
            b = p.observations.get(right_id)
            if a is not None and b is not None:
                ls_l.append(a)
                ls_r.append(b)
        return ls_l, ls_r
