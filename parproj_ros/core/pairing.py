"""Which scenes make a stereo pair (paper 2 section 2: two scenes of one ground, two looks).

Two views: the k-th scenes of the two views pair up. One view (single-camera mode, e.g. an agile
satellite looking forward then back): acquisitions 2k and 2k+1 pair up, or the pairs selected by
scene ids (:meth:`Pairing.set_pairs`, the node's ``pairs`` topic). Oriented scenes wait for their
partner in the ledger (:attr:`PairLedger.ready`), which also remembers the scenes done with so
that late inputs naming them are reported; this module is the policy, the ledger its state.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from ..imaging.assembly import Scene
from .config import PipelineConfig
from .gcp_store import GcpStore
from .ledger import PairLedger
from .results import Issue, Level, Outputs, SceneResult

#: Makes (normalizes, refines, publishes) one pair of oriented scenes (left, right).
MakePair = Callable[[SceneResult, SceneResult], Outputs]


class Pairing:
    """Which oriented scenes pair up: the policy; its state is the ledger's."""

    def __init__(self, config: PipelineConfig, ledger: PairLedger) -> None:
        self.config = config
        self.ledger = ledger

    def done_with(self, scene: Scene, method: str) -> None:
        """Remember that a scene is done with (``method``, or "skipped")."""
        self.ledger.done_with(scene, method)

    def _done_how(self, scene_id: str) -> str:
        method = self.ledger.done[scene_id][1]
        return "skipped" if method == "skipped" else f"processed ({method})"

    def add(self, result: SceneResult) -> list[Issue]:
        """An oriented scene waits for its partner; the issues (none, or one WARN).

        Single camera: only an acquisition's first part waits; the others are not paired.
        """
        scene = result.scene
        if not self.config.single_camera:
            self.ledger.ready[scene.view][scene.index] = result
        elif scene.part == 0:
            # Single camera: pairs are acquisitions 2k and 2k+1 (a look forward, then back),
            # whatever parts a gap or scene_lines cut them into; each is paired by its first
            # part, so that one split does not shift every later pair.
            self.ledger.ready[scene.view][scene.acquisition] = result
        else:
            return [
                Issue(
                    Level.WARN,
                    f"{scene.view}/{scene.scene_id}",
                    f"part {scene.part} of an acquisition that was split: its parameters are "
                    "published, but single-camera pairs are made of the first parts of two "
                    "acquisitions: not paired",
                )
            ]
        return []

    def selected_scene_ids(self) -> set[str]:
        """Scene ids that a selected pair not made yet still needs."""
        return self.ledger.selected_scene_ids()

    def make_pairs(self, make: MakePair, gcps: GcpStore) -> Outputs:
        """Make (``make``) every pair whose two scenes are ready."""
        out = Outputs()
        names = [v.name for v in self.config.views]
        if self.config.single_camera and self.ledger.selection is not None:
            out.extend(self.make_selected(make, gcps))
        elif self.config.single_camera:
            ready = self.ledger.ready[names[0]]
            for i in sorted(ready):
                if i % 2 == 0 and i + 1 in ready:
                    left, right = ready.pop(i), ready.pop(i + 1)
                    self.ledger.mark_made(left.scene.scene_id, right.scene.scene_id)
                    out.extend(make(left, right))
        else:
            left_ready, right_ready = self.ledger.ready[names[0]], self.ledger.ready[names[1]]
            for i in sorted(set(left_ready) & set(right_ready)):
                out.extend(make(left_ready.pop(i), right_ready.pop(i)))
        return out

    def set_pairs(
        self, pairs: Sequence[tuple[str, str]], make: MakePair, gcps: GcpStore
    ) -> Outputs:
        """Select which acquisitions pair up (single-camera mode; the node's ``pairs`` topic).

        ``pairs`` are (left scene id, right scene id): acquisitions (strip frame_ids, their
        first parts). A scene may be in several pairs: it is kept until every selected pair
        that needs it is made, then released. The selection replaces any earlier one for the
        pairs not made yet; scenes held that it no longer needs are released (WARN). Bad
        entries are reported and left out, the others kept: an empty id, a scene paired with
        itself, a pair listed twice (in either order), a scene already done with and released
        (processed under an earlier rule, or skipped). Scene ids that never arrive are
        reported when the data end (:meth:`unmade`). Two-view mode ignores the selection.
        """
        out = Outputs()
        if not self.config.single_camera:
            out.issues.append(
                Issue(
                    Level.WARN,
                    "pairs",
                    "pair selection ignored: with two views the k-th scenes of the views pair "
                    "up (it is for single-camera mode)",
                )
            )
            return out
        held = {r.scene.scene_id for r in self.ledger.ready[self.config.views[0].name].values()}
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
            elif key in self.ledger.made:
                seen.add(key)
                out.issues.append(Issue(Level.OK, f"pair {name}", "already made: not made again"))
                continue
            else:
                gone = [s for s in (left, right) if s in self.ledger.done and s not in held]
                if gone:
                    why = "scene " + ", ".join(
                        f"{s} was already {self._done_how(s)} and released" for s in gone
                    )
            if why:
                out.issues.append(Issue(Level.ERROR, f"pair {name}", f"{why}: pair left out"))
                continue
            seen.add(key)
            chosen.append((left, right))
        self.ledger.selection = chosen
        out.issues.append(
            Issue(
                Level.OK if chosen else Level.WARN,
                "pairs",
                f"pair selection: {len(chosen)} pairs to make"
                + (": " + ", ".join(f"{a}:{b}" for a, b in chosen[:20]) if chosen else "")
                + (" ..." if len(chosen) > 20 else ""),
            )
        )
        out.extend(self.make_selected(make, gcps))
        return out

    def make_selected(self, make: MakePair, gcps: GcpStore, warn_unpaired: bool = True) -> Outputs:
        """Make the selected pairs whose scenes are both ready; release scenes no pair needs.

        A released scene's GCP observations are forgotten (``gcps``). ``warn_unpaired``: a WARN
        for each released scene that no pair used.
        """
        out = Outputs()
        ready = self.ledger.ready[self.config.views[0].name]
        by_id = {r.scene.scene_id: r for r in ready.values()}
        remaining: list[tuple[str, str]] = []
        for left, right in self.ledger.selection or ():
            if left in by_id and right in by_id:
                self.ledger.mark_made(left, right)
                out.extend(make(by_id[left], by_id[right]))
                continue
            gone = [s for s in (left, right) if s in self.ledger.done and s not in by_id]
            if gone:
                out.issues.append(
                    Issue(
                        Level.ERROR,
                        f"pair {left}:{right}",
                        "scene "
                        + ", ".join(f"{s} was {self._done_how(s)}" for s in gone)
                        + ": pair not made",
                    )
                )
                continue
            remaining.append((left, right))
        self.ledger.selection = remaining
        needed = self.selected_scene_ids()
        for acq, res in list(ready.items()):
            sid = res.scene.scene_id
            if sid in needed:
                continue
            del ready[acq]  # every pair that needed it is made: its pixels are released
            if warn_unpaired and not any(sid in pair for pair in self.ledger.made):
                out.issues.append(
                    Issue(
                        Level.WARN,
                        f"{res.scene.view}/{sid}",
                        "in no selected pair (pairs topic): parameters published, not paired",
                    )
                )
            gcps.forget((sid,), keep=self.selected_scene_ids())
        return out

    def unmade(self, make: MakePair, gcps: GcpStore) -> Outputs:
        """End of data: an ERROR per selected pair not made (a scene never arrived)."""
        out = Outputs()
        ready = self.ledger.ready[self.config.views[0].name] if self.config.single_camera else {}
        have = {r.scene.scene_id for r in ready.values()}
        for left, right in self.ledger.selection or ():
            missing = [s for s in (left, right) if s not in have]
            out.issues.append(
                Issue(
                    Level.ERROR,
                    f"pair {left}:{right}",
                    "scene "
                    + ", ".join(missing)
                    + " never received (unknown scene id?): selected pair not made",
                )
            )
        if self.ledger.selection:
            self.ledger.selection = []
            out.extend(self.make_selected(make, gcps, warn_unpaired=False))  # release them
        return out
