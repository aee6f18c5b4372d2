"""The navigation feed of the pipeline: samples for paper 1 section 3 (Eqs 9-13), kept and pruned.

Navigation arrives on its own topic, in no fixed order with the strips: a sample far ahead of
the newest one is held until the next confirms the jump, one far behind is dropped; samples are
kept only as long as a scene may still need them; complete scenes that navigation does not cover
yet wait in the ledger (:attr:`~parproj_ros.core.ledger.PairLedger.waiting`). Times are
nanoseconds.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from ..imaging.assembly import SceneAssembler
from .config import NavigationSettings
from .ledger import PairLedger
from .results import Issue, Level
from .trajectory import NavSample, TrajectoryBuffer


class NavigationFeed:
    """Navigation samples accepted (:attr:`buffer`); scenes waiting for them are the ledger's."""

    def __init__(self, settings: NavigationSettings, ledger: PairLedger) -> None:
        self.settings = settings
        self.ledger = ledger
        self.buffer = TrajectoryBuffer()
        #: A sample more than ``nav_jump_s`` ahead of the newest one, until the next one comes.
        self.pending: NavSample | None = None
        #: Earliest navigation stamp accepted (ns), None before any.
        self.first_ns: int | None = None

    def add(self, sample: NavSample) -> tuple[bool, list[Issue]]:
        """Take one sample: (whether it was accepted now, issues).

        A sample more than ``nav_jump_s`` ahead of the newest one is held until the next sample
        confirms the jump (a clock jump or a stray stamp is then dropped and reported); one more
        than ``nav_jump_s`` behind is dropped and reported.
        """
        issues = []
        jump = self.settings.jump_s * 1e9
        last = self.buffer.last_ns
        if self.pending is not None:
            pending, self.pending = self.pending, None
            if abs(sample.t_ns - pending.t_ns) <= jump:
                self._add(pending)  # the jump is confirmed by this sample
            else:
                issues.append(
                    Issue(
                        Level.WARN,
                        "navigation",
                        (
                            f"a sample stamped {(pending.t_ns - (last or 0)) / 1e9:+.3f} s "
                            "from the newest one (more than nav_jump_s, "
                            f"{self.settings.jump_s:g} s) was not followed by others: dropped"
                        ),
                    )
                )
        elif last is not None and sample.t_ns > last + jump:
            self.pending = sample
            return False, issues
        if last is not None and sample.t_ns < last - jump:
            issues.append(
                Issue(
                    Level.WARN,
                    "navigation",
                    (
                        f"sample stamped {(sample.t_ns - last) / 1e9:+.3f} s from the newest one "
                        f"(stamps going backwards by more than nav_jump_s, "
                        f"{self.settings.jump_s:g} s; too late for any scene still open): dropped"
                    ),
                )
            )
            return False, issues
        self._add(sample)
        return True, issues

    def _add(self, sample: NavSample) -> None:
        self.buffer.add(sample)
        if self.first_ns is None or sample.t_ns < self.first_ns:
            self.first_ns = sample.t_ns

    def needed_from(
        self, assemblers: Mapping[str, SceneAssembler], streamed: Iterable[int]
    ) -> int | None:
        """Earliest line time (ns) for which a scene may still need navigation (None: unknown).

        The first lines of the open scenes, of the scenes waiting for navigation and of the
        streamed pairs' scenes (``streamed``); for a view with no open scene, the end of its
        data (its next scene cannot start earlier). Unknown while a view has received no strip.
        """
        times = [s.first_line_ns for s in self.ledger.waiting]
        times += list(streamed)
        for asm in assemblers.values():
            opened = asm.open_scene()
            if opened is not None:
                times.append(opened.first_line_ns)
            elif asm.latest_ns is not None:
                times.append(asm.latest_ns)
            else:
                return None
        return min(times)

    def prune(self, assemblers: Mapping[str, SceneAssembler], streamed: Iterable[int]) -> None:
        """Forget navigation no scene can need any more (``nav_history_s`` before it is kept)."""
        needed = self.needed_from(assemblers, streamed)
        last = self.buffer.last_ns
        if needed is not None and last is not None:
            self.buffer.prune_before(min(needed, last) - round(self.settings.history_s * 1e9))
