"""Simulated acquisitions recorded into the bags of bags/: geometry, terrain, GCP and truth.

A scenario is a platform moving with constant velocity, one or two cameras on it, and a list of
scenes (which view, when it starts, how many lines, the platform attitude during it). The
images are rendered through the rigorous pushbroom model (geometry/pushbroom.py) over a terrain
(imaging/terrain.py), so every pixel's geometry is exact and the truth is known.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..core.config import PipelineConfig, ViewConfig
from ..core.results import GroundPoint
from ..geometry import ConstantMotion, LineCamera, PushbroomModel, rotation_from_angles

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SceneSpec:
    """One scene of a scenario.

    Attributes:
        view: which camera.
        start_s: time of the first line, seconds from the scenario's t = 0.
        lines: number of lines.
        attitude_rpy_deg: platform (body) roll, pitch, yaw during the scene, degrees.
    """

    view: str
    start_s: float
    lines: int
    attitude_rpy_deg: tuple[float, float, float]


@dataclass(frozen=True)
class Scenario:
    """A simulated acquisition.

    Attributes:
        name: bag name.
        description: one line for bags/README.md.
        views: cameras with their mounting in the body frame.
        position0: platform position at t = 0, object frame (local Cartesian), metres.
        velocity: platform velocity, object frame, m/s.
        scenes: scenes in time order; pairs are (scene 2k, scene 2k+1) in single-camera mode,
            or the k-th scene of each view with two views.
        relief_m: terrain height half range, metres.
        terrain_extent_m: side of the terrain square, metres.
        terrain_spacing_m: DEM grid spacing, metres.
        gcp: GCP per pair (observed in both scenes).
        check: check points per pair.
        truth: truth points per pair for the evaluation.
        strip_lines: lines per image message.
        nav_rate_hz: navigation rate.
        dtype: pixel type.
        t0_ns: absolute time of t = 0, nanoseconds.
        seed: seed of terrain and point draws.
        z_avg: average terrain height for the node, metres.
        gcp_noise_px: standard deviation of the GCP image measurements, pixels (truth points
            are always exact).
    """

    name: str
    description: str
    views: tuple[ViewConfig, ...]
    position0: tuple[float, float, float]
    velocity: tuple[float, float, float]
    scenes: tuple[SceneSpec, ...]
    relief_m: float
    terrain_extent_m: float
    terrain_spacing_m: float
    gcp: int = 12
    check: int = 6
    truth: int = 300
    strip_lines: int = 64
    nav_rate_hz: float = 20.0
    dtype: str = "uint16"
    t0_ns: int = 1_700_000_000 * 1_000_000_000
    seed: int = 7
    z_avg: float = 0.0
    gcp_noise_px: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    def scene_id(self, i: int) -> str:
        """Scene id (the strips' frame_id) of scene i."""
        return f"{self.scenes[i].view}_scene_{i:04d}"

    def model(self, i: int) -> PushbroomModel:
        """Rigorous model of scene i; its line 0 is at t = 0 of the model (scene start)."""
        sc = self.scenes[i]
        view = next(v for v in self.views if v.name == sc.view)
        body = rotation_from_angles(*np.radians(sc.attitude_rpy_deg))
        pos = np.array(self.position0) + sc.start_s * np.array(self.velocity)
        return PushbroomModel(
            view.camera, ConstantMotion(pos, np.array(self.velocity), body @ view.mounting)
        )

    def body_rotation(self, t_s: float) -> FloatArray:
        """Platform attitude at time t (s).

        That of the scene whose span, widened to halfway to its neighbours, contains t.
        """
        mids = [sc.start_s + sc.lines * self.views[0].camera.line_period / 2 for sc in self.scenes]
        i = int(np.argmin([abs(t_s - m) for m in mids]))
        return rotation_from_angles(*np.radians(self.scenes[i].attitude_rpy_deg))

    def pairs(self) -> list[tuple[int, int]]:
        """Scene index pairs (left, right)."""
        if len(self.views) == 1:
            return [(i, i + 1) for i in range(0, len(self.scenes) - 1, 2)]
        names = [v.name for v in self.views]
        per = {n: [i for i, s in enumerate(self.scenes) if s.view == n] for n in names}
        return list(zip(per[names[0]], per[names[1]], strict=False))

    def pipeline_config(self, **overrides: object) -> PipelineConfig:
        """The pipeline settings that process this scenario's bag."""
        kw: dict[str, object] = {
            "views": self.views,
            "z_avg": self.z_avg,
            "height_range": self.relief_m,
        }
        kw.update(overrides)
        return PipelineConfig(**kw)  # type: ignore[arg-type]

    def time_ns(self, t_s: float) -> int:
        """Absolute time (ns) of scenario time t (s)."""
        return self.t0_ns + round(t_s * 1e9)


def _sat_camera(detectors: int) -> LineCamera:
    return LineCamera(10.0, 12e-6, detectors, 1.0 / 6500.0)


def _agile(
    name: str, description: str, yaw_deg: float, seed: int, gcp: int, gcp_noise_px: float
) -> Scenario:
    cam = _sat_camera(768)
    h = 680_000.0
    y0 = h * np.tan(np.radians(5.0))
    pitch_fore, pitch_aft = -22.5, 17.0  # an asymmetric pair, as agile satellites fly them
    # Horizontal reach of the principal ray at roll 5 deg: h L / N = h tan(pitch) / cos(roll).
    reach_fore = h * np.tan(np.radians(-pitch_fore)) / np.cos(np.radians(5.0))
    reach_aft = h * np.tan(np.radians(pitch_aft)) / np.cos(np.radians(5.0))
    lines = 768
    half = lines / 2 / 6500.0
    x0 = -reach_fore - 10_000.0  # 10 km before the fore look's middle line
    t_fore = 10_000.0 / 7000.0 - half
    t_aft = (reach_fore + reach_aft + 10_000.0) / 7000.0 - half
    return Scenario(
        name=name,
        description=description,
        views=(ViewConfig("pan", cam, dtype="uint16"),),
        position0=(x0, y0, h),
        velocity=(7000.0, 0.0, 0.0),
        scenes=(
            SceneSpec("pan", t_fore, lines, (-5.0, pitch_fore, yaw_deg)),
            SceneSpec("pan", t_aft, lines, (-5.0, pitch_aft, yaw_deg)),
        ),
        relief_m=300.0,
        terrain_extent_m=4000.0,
        terrain_spacing_m=8.0,
        seed=seed,
        gcp=gcp,
        check=8 if gcp else 0,
        gcp_noise_px=gcp_noise_px,
    )


def ikonos() -> Scenario:
    """Paper 1's geometry as one agile IKONOS-like satellite (single camera, forward then back).

    Table 1's left scene (roll -5, pitch -22.5 deg, 680 km, 7 km/s) and, 73 s later on the same
    orbit, a backward look (pitch +17 deg) at the same ground; 768 detectors so that the bag
    stays small; GCP measured with 0.05 px noise.
    """
    return _agile(
        "ikonos_agile",
        "IKONOS-like agile satellite (paper 1 Table 1 left-scene "
        "geometry, 768 detectors), one camera: forward look (pitch -22.5 deg), then "
        "backward look (+17 deg) 73 s later; uint16 (11-bit range); 20 GCP + 8 check "
        "points measured with 0.05 px noise (Eq 8 with the roll)",
        0.0,
        11,
        20,
        0.05,
    )


def crab() -> Scenario:
    """The agile fore/aft pair flown with a 3 deg crab angle.

    The scan line is yawed against the velocity: Eqs 10-13 fail by tens of pixels and the
    virtual-GCP fit takes over.
    """
    return _agile(
        "crab_foreaft",
        "agile satellite fore/aft pair as ikonos_agile, with a 3 deg "
        "crab angle (scan line yawed against the velocity): Eqs 10-13 would err by "
        "pixels, the virtual-GCP fit is used; no GCP",
        3.0,
        13,
        0,
        0.0,
    )


def airborne() -> Scenario:
    """Airborne fore/aft line cameras (two views on one aircraft, -+14 deg pitch)."""
    h = 5000.0
    speed = 70.0
    gsd = 6.5e-6 * h / 0.3
    cam = LineCamera(0.3, 6.5e-6, 768, gsd / speed)
    tilt = 14.0
    fore = ViewConfig("left", cam, rotation_from_angles(0.0, np.radians(-tilt), 0.0), "uint8")
    aft = ViewConfig("right", cam, rotation_from_angles(0.0, np.radians(tilt), 0.0), "uint8")
    reach = h * np.tan(np.radians(tilt))
    lines = 768
    dur = lines * cam.line_period
    t_fore = 2.0
    t_aft = t_fore + 2 * reach / speed
    x0 = -reach - t_fore * speed - dur * speed / 2
    return Scenario(
        name="airborne_foreaft",
        description="airborne line camera, c = 0.3 m, 6.5 um, 768 detectors, 5000 m, 70 m/s, "
        "fore/aft cameras at -+14 deg pitch (two views), uint8; navigation only (no GCP)",
        views=(fore, aft),
        position0=(x0, 0.0, h),
        velocity=(speed, 0.0, 0.0),
        scenes=(
            SceneSpec("left", t_fore, lines, (0.0, 0.0, 0.0)),
            SceneSpec("right", t_aft, lines, (0.0, 0.0, 0.0)),
        ),
        relief_m=15.0,
        terrain_extent_m=400.0,
        terrain_spacing_m=1.0,
        dtype="uint8",
        nav_rate_hz=50.0,
        seed=12,
        gcp=0,
        check=0,
    )


SCENARIOS = {"ikonos_agile": ikonos, "airborne_foreaft": airborne, "crab_foreaft": crab}


def ground_points(
    scn: Scenario,
    pair: tuple[int, int],
    n: int,
    locate: Callable[[PushbroomModel, FloatArray, FloatArray], FloatArray],
    rng: np.random.Generator,
    *,
    prefix: str,
    check: bool = False,
    margin: float = 8.0,
) -> list[GroundPoint]:
    """N points on the terrain seen in both scenes of ``pair``, with exact observations.

    ``locate(model, line, sample)`` returns object points on the terrain.
    """
    left, right = scn.model(pair[0]), scn.model(pair[1])
    sl, sr = scn.scenes[pair[0]], scn.scenes[pair[1]]
    out: list[GroundPoint] = []
    tries = 0
    while len(out) < n and tries < 50:
        tries += 1
        k = max(4 * (n - len(out)), 16)
        line = rng.uniform(margin, sl.lines - 1 - margin, k)
        sample = rng.uniform(margin, left.camera.detectors - 1 - margin, k)
        xyz = locate(left, line, sample)
        lr = right.project(xyz)
        ok = (
            (lr[:, 0] >= margin)
            & (lr[:, 0] <= sr.lines - 1 - margin)
            & (lr[:, 1] >= margin)
            & (lr[:, 1] <= right.camera.detectors - 1 - margin)
        )
        for j in np.flatnonzero(ok):
            if len(out) >= n:
                break
            out.append(
                GroundPoint(
                    f"{prefix}{len(out):03d}",
                    xyz[j],
                    check,
                    {
                        scn.scene_id(pair[0]): (float(line[j]), float(sample[j])),
                        scn.scene_id(pair[1]): (float(lr[j, 0]), float(lr[j, 1])),
                    },
                )
            )
    return out
