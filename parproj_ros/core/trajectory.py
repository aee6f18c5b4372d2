"""Navigation samples -> the constant-velocity, constant-attitude motion of one scene.

Samples come from nav_msgs/Odometry: position of the platform in the object frame (local
Cartesian, metres), orientation of the platform (body) frame in the object frame, and the linear
velocity in the body (child) frame as ROS defines it. The scanner rotation is
``R_s = R_body @ R_mount`` with ``R_mount`` the sensor frame in the body frame.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..geometry.errors import GeometryError
from ..geometry.pushbroom import ConstantMotion
from ..geometry.rotation import quaternion_to_rotation

FloatArray = NDArray[np.float64]


class NavigationError(ValueError):
    """Navigation does not cover a scene, or is inconsistent; says which and by how much."""


@dataclass(frozen=True)
class NavSample:
    """One navigation sample.

    Attributes:
        t_ns: time, nanoseconds.
        position: platform position, object frame, metres, (3,).
        rotation: body -> object rotation, (3, 3).
        velocity: velocity in the object frame, m/s, (3,) (already rotated from the body frame).
    """

    t_ns: int
    position: FloatArray
    rotation: FloatArray
    velocity: FloatArray


def make_sample(
    t_ns: int,
    position: NDArray[np.float64],
    quaternion: NDArray[np.float64],
    velocity_body: NDArray[np.float64],
) -> NavSample:
    """Validate raw Odometry values and build a sample.

    Raises:
        NavigationError: NaN/Inf anywhere or a zero-norm quaternion.
    """
    p = np.asarray(position, dtype=float)
    v = np.asarray(velocity_body, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise NavigationError(f"position is not 3 finite numbers: {p}")
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise NavigationError(f"velocity is not 3 finite numbers: {v}")
    try:
        r = quaternion_to_rotation(quaternion)
    except GeometryError as err:
        raise NavigationError(str(err)) from err
    return NavSample(int(t_ns), p, r, r @ v)


@dataclass(frozen=True)
class MotionFit:
    """Constant motion fitted to the samples of one time span, with its quality.

    Attributes:
        motion: constant motion (scanner rotation = body rotation @ mounting), t0 in seconds.
        samples: number of samples used.
        position_rms_m: RMS of positions about the straight line, metres.
        attitude_spread_rad: largest angle between a sample's attitude and the mean, radians.
        velocity_mismatch: |v_fit - v_reported| / |v_fit| (reported = Odometry twist), or NaN.
    """

    motion: ConstantMotion
    samples: int
    position_rms_m: float
    attitude_spread_rad: float
    velocity_mismatch: float
    t0_ns: int = 0

    def _replace_t0(self, t0_ns: int) -> MotionFit:
        """The same motion with its time origin (t = 0 s) moved to ``t0_ns``."""
        dt = (t0_ns - self.t0_ns) / 1e9
        m = self.motion
        moved = ConstantMotion(m.position + dt * m.velocity, m.velocity, m.rotation, t0=0.0)
        return MotionFit(
            moved,
            self.samples,
            self.position_rms_m,
            self.attitude_spread_rad,
            self.velocity_mismatch,
            t0_ns,
        )


class TrajectoryBuffer:
    """Time-ordered navigation samples with bounded memory.

    Args:
        max_samples: oldest samples are dropped beyond this many.
        max_gap_s: a gap between samples larger than this inside a scene's span is an error.
    """

    def __init__(self, *, max_samples: int = 200_000, max_gap_s: float = 1.0) -> None:
        self.max_samples = max_samples
        self.max_gap_s = max_gap_s
        self._t: list[int] = []
        self._s: list[NavSample] = []

    def __len__(self) -> int:
        return len(self._t)

    def add(self, sample: NavSample) -> None:
        """Insert a sample in time order (a sample with an existing time replaces it)."""
        i = bisect.bisect_left(self._t, sample.t_ns)
        if i < len(self._t) and self._t[i] == sample.t_ns:
            self._s[i] = sample
            return
        self._t.insert(i, sample.t_ns)
        self._s.insert(i, sample)
        if len(self._t) > self.max_samples:
            del self._t[0]
            del self._s[0]

    def prune_before(self, t_ns: int) -> None:
        """Forget samples older than t_ns (keeping one before it)."""
        i = max(0, bisect.bisect_left(self._t, t_ns) - 1)
        del self._t[:i]
        del self._s[:i]

    @property
    def last_ns(self) -> int | None:
        """Time of the newest sample, or None."""
        return self._t[-1] if self._t else None

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        """Whether samples bracket t0 and t1 (ns), each within ``max_gap_s`` of it.

        A single stray sample far in the future does not make a span "covered".
        """
        if not self._t:
            return False
        gap = self.max_gap_s * 1e9
        i0 = bisect.bisect_right(self._t, t0_ns) - 1
        i1 = bisect.bisect_left(self._t, t1_ns)
        return (
            i0 >= 0
            and t0_ns - self._t[i0] <= gap
            and i1 < len(self._t)
            and self._t[i1] - t1_ns <= gap
        )

    def fit_recent(
        self,
        t0_ns: int,
        mounting: FloatArray,
        *,
        window_s: float = 2.0,
        until_ns: int | None = None,
    ) -> MotionFit:
        """Fit the motion on the latest ``window_s`` of navigation, with its origin at ``t0_ns``.

        For extrapolation over a scene that has just started at ``t0_ns`` (streaming).
        ``until_ns``: only the samples up to that time count (a decision taken after more
        navigation arrived, made as it would have been then).

        Raises:
            NavigationError: fewer than 2 samples in the window, or the newest sample is more
                than ``max_gap_s`` before ``t0_ns``.
        """
        n = len(self._t) if until_ns is None else bisect.bisect_right(self._t, until_ns)
        if n < 2:
            raise NavigationError("fewer than 2 navigation samples received")
        last = self._t[n - 1]
        if last < t0_ns - self.max_gap_s * 1e9:
            raise NavigationError(
                f"newest navigation is {(t0_ns - last) / 1e9:.3f} s older than the scene start"
            )
        start = max(self._t[0], last - round(window_s * 1e9))
        return self.fit(start, last, mounting)._replace_t0(t0_ns)

    def fit(self, t0_ns: int, t1_ns: int, mounting: FloatArray) -> MotionFit:
        """Fit the constant motion of the span [t0, t1] (ns); ``t0`` becomes the motion's t0.

        Raises:
            NavigationError: the span is not covered (navigation starts late, ends early or has
                a gap longer than ``max_gap_s``) or there are fewer than 2 samples.
        """
        if not self._t:
            raise NavigationError("no navigation received")
        if self._t[0] > t0_ns:
            raise NavigationError(
                f"navigation starts {(self._t[0] - t0_ns) / 1e9:.3f} s after the first line"
            )
        if self._t[-1] < t1_ns:
            raise NavigationError(
                f"navigation ends {(t1_ns - self._t[-1]) / 1e9:.3f} s before the scene's last line"
            )
        i0 = max(0, bisect.bisect_right(self._t, t0_ns) - 1)
        i1 = min(len(self._t), bisect.bisect_left(self._t, t1_ns) + 1)
        ts = np.array(self._t[i0:i1], dtype=np.int64)
        if len(ts) < 2:
            raise NavigationError("fewer than 2 navigation samples span the scene")
        gaps = np.diff(ts) / 1e9
        if gaps.max() > self.max_gap_s:
            k = int(np.argmax(gaps))
            raise NavigationError(
                f"navigation gap of {gaps[k]:.3f} s (> {self.max_gap_s} s) at "
                f"{(ts[k] - t0_ns) / 1e9:.3f} s into the scene"
            )
        samples = self._s[i0:i1]
        tt = (ts - t0_ns) / 1e9
        pos = np.array([s.position for s in samples])
        design = np.column_stack([np.ones_like(tt), tt])
        with np.errstate(all="ignore"):
            coef, *_ = np.linalg.lstsq(design, pos, rcond=None)
            resid = pos - design @ coef
            v_rep = np.mean([s.velocity for s in samples], axis=0)
        if not (
            np.all(np.isfinite(coef)) and np.all(np.isfinite(resid)) and np.all(np.isfinite(v_rep))
        ):
            raise NavigationError("navigation values too large to fit a motion (overflow)")
        # Attitude: chordal L2 mean of the rotations, projected back onto SO(3).
        rs = np.array([s.rotation for s in samples])
        u, _, vt = np.linalg.svd(rs.mean(axis=0))
        r_mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        spread = max(
            float(np.arccos(np.clip((np.trace(r_mean.T @ r) - 1) / 2, -1.0, 1.0))) for r in rs
        )
        v_fit = coef[1]
        with np.errstate(all="ignore"):  # absurd (finite) velocities overflow the norm: NaN
            mismatch = float(
                np.linalg.norm(v_fit - v_rep) / max(float(np.linalg.norm(v_fit)), 1e-12)
            )
        motion = ConstantMotion(coef[0], v_fit, r_mean @ mounting, t0=0.0)
        return MotionFit(
            motion, len(samples), float(np.sqrt(np.mean(resid**2))), spread, mismatch, t0_ns
        )
