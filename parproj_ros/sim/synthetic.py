"""A synthetic fore/aft satellite and its strip acquisition (the benchmark's scene).

IKONOS-like camera and orbit (c = 10 m, 12 um pixels, 6500 lines/s, uint16): a satellite at
680 km, roll -5 deg, flying along X at the speed that makes 6500 lines/s give square pixels
(5304 m/s; IKONOS slows its scan by pitching back to get them), with fore and aft cameras pitched
-+theta. theta is chosen so that the aft camera images the fore camera's ground one scene later:
scene k of the aft view is exposed while scene k+1 of the fore view is, interleaved strip by strip
as a real fore/aft sensor delivers them, and pair k completes with the aft scene k. Every scene has
the same random 11-bit content (one block per strip position), so the pair is photometrically
consistent; rendering through a terrain is too slow at this size.

The benchmark (``tools/bench``) sends this acquisition through the node; the streaming tests feed
it to a Pipeline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core import contract
from ..core.pipeline import ViewConfig
from ..core.trajectory import NavSample
from ..geometry import ConstantMotion, LineCamera, PushbroomModel, rotation_from_angles

FloatArray = NDArray[np.float64]

#: IKONOS-like camera and orbit (paper 1 Table 1): principal distance and pixel size, metres.
PRINCIPAL_DISTANCE_M = 10.0
PIXEL_SIZE_M = 12e-6
LINE_RATE_HZ = 6500.0
ALTITUDE_M = 680_000.0
ROLL_DEG = -5.0
#: Ground speed (m/s) at which LINE_RATE_HZ gives square ground pixels at nadir.
SPEED_M_S = PIXEL_SIZE_M * ALTITUDE_M / PRINCIPAL_DISTANCE_M * LINE_RATE_HZ
#: Absolute time of sensor time 0, nanoseconds.
T0_NS = 1_700_000_000 * 1_000_000_000
VIEWS = ("left", "right")


@dataclass(frozen=True)
class Platform:
    """The fore/aft satellite of the benchmark.

    Attributes:
        views: left (fore, pitched -theta) and right (aft, +theta) cameras.
        lines: lines per scene.
        scene_s: duration of one scene, seconds.
        lag_scenes: the aft camera images the fore camera's ground this many scenes later.
        theta: camera pitch, radians.
        body: platform attitude (roll), 3x3.
    """

    views: tuple[ViewConfig, ViewConfig]
    lines: int
    scene_s: float
    lag_scenes: int
    theta: float
    body: FloatArray

    @property
    def camera(self) -> LineCamera:
        """The (shared) camera of both views."""
        return self.views[0].camera

    def scene_start_s(self, view: int, k: int) -> float:
        """Sensor time (s) of line 0 of scene k of a view (0 fore, 1 aft)."""
        return (k + (self.lag_scenes if view else 0)) * self.scene_s

    def position(self, t_s: float) -> FloatArray:
        """Platform position (m, object frame) at sensor time t_s (s)."""
        return np.array([SPEED_M_S * t_s, 0.0, ALTITUDE_M])

    @property
    def velocity(self) -> FloatArray:
        """Platform velocity, m/s."""
        return np.array([SPEED_M_S, 0.0, 0.0])

    def model(self, view: int, k: int) -> PushbroomModel:
        """Rigorous model of scene k of a view; line 0 at the model's t = 0."""
        v = self.views[view]
        t0 = self.scene_start_s(view, k)
        return PushbroomModel(
            v.camera, ConstantMotion(self.position(t0), self.velocity, self.body @ v.mounting)
        )


def make_platform(lines: int, detectors: int, *, lag_scenes: int = 1) -> Platform:
    """The benchmark platform for scenes of ``lines`` x ``detectors`` (see the module doc)."""
    cam = LineCamera(PRINCIPAL_DISTANCE_M, PIXEL_SIZE_M, detectors, 1.0 / LINE_RATE_HZ)
    scene_s = lines * cam.line_period
    roll = math.radians(ROLL_DEG)
    # Horizontal reach of a ray pitched by theta at roll psi: h tan(theta) / cos(psi); fore and
    # aft rays meet the same ground lag_scenes * scene_s apart.
    theta = math.atan(lag_scenes * SPEED_M_S * scene_s * math.cos(roll) / (2 * ALTITUDE_M))
    views = (
        ViewConfig("left", cam, rotation_from_angles(0.0, -theta, 0.0)),
        ViewConfig("right", cam, rotation_from_angles(0.0, theta, 0.0)),
    )
    return Platform(views, lines, scene_s, lag_scenes, theta, rotation_from_angles(roll, 0.0, 0.0))


def stereo_platform(lines: int, detectors: int, *, min_base_to_height: float = 0.005) -> Platform:
    """:func:`make_platform` with a base-to-height ratio of at least ``min_base_to_height``.

    The aft view sees the fore view's ground as many scenes later as that needs (short
    scenes: more than one).
    """
    plat = make_platform(lines, detectors)
    lag = max(1, math.ceil(min_base_to_height / (2 * math.tan(plat.theta))))
    return plat if lag == 1 else make_platform(lines, detectors, lag_scenes=lag)


def texture_blocks(count: int, rows: int, detectors: int, seed: int) -> list[NDArray[np.uint16]]:
    """``count`` random 11-bit uint16 blocks of rows x detectors (the synthetic scene texture)."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 2048, (rows, detectors), dtype=np.uint16) for _ in range(count)]


@dataclass(frozen=True)
class Event:
    """One message of the synthetic acquisition, in delivery order.

    Attributes:
        due_s: sensor time at which it is delivered (a strip: after its last line), seconds.
        kind: "nav" or "strip".
        t_s: navigation time, or sensor time of the strip's first line, seconds.
        view: 0 (left, fore) or 1 (right, aft).
        scene: scene index within the view.
        row0: first line of the strip in its scene.
        rows: lines in the strip.
        slot: scene-time slot of the strip (flow control); -1 for navigation.
        last_of_pair: the last strip of pair ``scene`` (the aft scene's last strip).
    """

    due_s: float
    kind: str
    t_s: float
    view: int = 0
    scene: int = 0
    row0: int = 0
    rows: int = 0
    slot: int = -1
    last_of_pair: bool = False

    @property
    def stamp_ns(self) -> int:
        """Header stamp: time of the first line (strip) or of the sample (navigation), ns."""
        return T0_NS + round(self.t_s * 1e9)

    @property
    def scene_id(self) -> str:
        """The strip's frame_id."""
        return f"{VIEWS[self.view]}_{self.scene:04d}"


def acquisition(plat: Platform, pairs: int, strip_lines: int, nav_rate_hz: float) -> list[Event]:
    """Navigation and strips of ``pairs`` fore/aft pairs, sorted by delivery time.

    The fore view also delivers the scenes it images while the aft view images the last pairs
    (a continuous acquisition; they pair with nothing here). Navigation runs from 1 s before
    the first line to 0.5 s after the last (samples before sensor time 0 are delivered at 0);
    strips are delivered when their last line is exposed.
    """
    lp = plat.camera.line_period
    span = (pairs + plat.lag_scenes) * plat.scene_s
    events = [
        Event(max(t, 0.0), "nav", float(t)) for t in np.arange(-1.0, span + 0.5, 1.0 / nav_rate_hz)
    ]
    for view in (0, 1):
        # The fore camera keeps imaging while the aft one images the last pair's ground.
        for k in range(pairs + (0 if view else plat.lag_scenes)):
            start = plat.scene_start_s(view, k)
            slot = k + (plat.lag_scenes if view else 0)
            for r0 in range(0, plat.lines, strip_lines):
                n = min(strip_lines, plat.lines - r0)
                events.append(
                    Event(
                        start + (r0 + n) * lp,
                        "strip",
                        start + r0 * lp,
                        view,
                        k,
                        r0,
                        n,
                        slot,
                        view == 1 and r0 + n == plat.lines,
                    )
                )
    events.sort(key=lambda e: (e.due_s, e.kind != "nav", e.view))
    return events


class StripMessages:
    """Prebuilt sensor_msgs/Image strips (data set once; header set per publication).

    Every scene of both views has the same content: one random 11-bit block per strip
    position, so a scene has no repeated block and the fore and aft scenes of a pair, which
    see the same flat ground, form a consistent stereo pair (image matching finds tie points).
    """

    def __init__(self, plat: Platform, strip_lines: int) -> None:
        from sensor_msgs.msg import Image

        from ..ros.conversions import array_to_image

        dets = plat.camera.detectors
        self.strip_lines = strip_lines
        self.msgs: list[Any] = []
        for r0 in range(0, plat.lines, strip_lines):
            n = min(strip_lines, plat.lines - r0)
            (block,) = texture_blocks(1, n, dets, seed=10 + r0)
            img = Image(check_fields=False)
            self.msgs.append(array_to_image(block, img, frame_id="", stamp_ns=T0_NS))

    def get(self, ev: Event) -> Any:
        """The message of a strip event, its header filled in."""
        from ..ros.conversions import ns_to_stamp

        msg = self.msgs[ev.row0 // self.strip_lines]
        ns_to_stamp(ev.stamp_ns, msg.header.stamp)
        msg.header.frame_id = ev.scene_id
        return msg


def nav_message(plat: Platform, t_s: float) -> Any:
    """nav_msgs/Odometry of the platform at sensor time t_s (s)."""
    from nav_msgs.msg import Odometry

    from ..ros.conversions import sample_to_odometry

    s = NavSample(T0_NS + round(t_s * 1e9), plat.position(t_s), plat.body, plat.velocity)
    return sample_to_odometry(
        s, Odometry(), frame_id=contract.DEFAULT_FRAME, child_frame_id=contract.BODY_FRAME
    )
