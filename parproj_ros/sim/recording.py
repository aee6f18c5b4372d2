"""Recording simulated scenarios into input bags.

The bags hold the input topics of the interface contract (:mod:`parproj_ros.core.contract`;
:mod:`parproj_ros.ros.inputs` reads them back).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..core import contract
from ..core.results import GroundPoint
from ..core.trajectory import NavSample
from ..geometry import LineCamera
from ..ros.bag import BagWriter
from ..ros.conversions import (
    array_to_image,
    gcp_to_msg,
    sample_to_odometry,
    scanner_info_msg,
)
from .scenarios import Scenario, ground_points

#: The object frame of simulated bags (a local Cartesian frame, metres, Z up).
FRAME_ID = contract.DEFAULT_FRAME


def _progress(total: int, desc: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, unit="line", leave=False)


def record_scenario(
    scn: Scenario,
    path: Path,
    *,
    progress: bool = True,
    noise_px: float | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render ``scn`` and write its bag folder at ``path``; return a summary for bags/README.

    ``noise_px`` (default: the scenario's) is the standard deviation of the Gaussian noise added
    to the GCP and check-point image measurements; truth points stay exact.
    """
    from nav_msgs.msg import Odometry
    from parproj_msgs.msg import GroundControlPoints
    from sensor_msgs.msg import Image

    from .simulate import locate_on_terrain, render_scene
    from .terrain import procedural_terrain

    terrain = procedural_terrain(
        scn.terrain_extent_m, scn.terrain_spacing_m, scn.relief_m, seed=scn.seed
    )
    rng = np.random.default_rng(scn.seed)

    def locate(model: Any, line: Any, sample: Any) -> Any:
        return locate_on_terrain(model, terrain, line, sample)

    gcp: list[GroundPoint] = []
    truth: list[GroundPoint] = []
    for k, pair in enumerate(scn.pairs()):
        gcp += ground_points(scn, pair, scn.gcp, locate, rng, prefix=f"p{k}_gcp")
        gcp += ground_points(scn, pair, scn.check, locate, rng, prefix=f"p{k}_chk", check=True)
        truth += ground_points(scn, pair, scn.truth, locate, rng, prefix=f"p{k}_t", check=True)
    noise_px = scn.gcp_noise_px if noise_px is None else noise_px
    if noise_px > 0:
        for p in gcp:
            for sid, (line, sample) in list(p.observations.items()):
                p.observations[sid] = (
                    line + rng.normal(0, noise_px),
                    sample + rng.normal(0, noise_px),
                )
    first = min(sc.start_s for sc in scn.scenes) - 1.0
    last = max(sc.start_s + sc.lines * _cam(scn, sc.view).line_period for sc in scn.scenes) + 1.0
    dtype = np.dtype(scn.dtype)
    with BagWriter(path, compression="zstd") as bw:
        bw.add_topics(contract.input_topics(v.name for v in scn.views))
        t_first = scn.time_ns(first)
        for v in scn.views:
            info = scanner_info_msg(v, stamp_ns=t_first)
            bw.write(contract.scanner_info_topic(v.name), info, t_first)
        bw.write(
            contract.GCP,
            gcp_to_msg(gcp, GroundControlPoints(), frame_id=FRAME_ID, stamp_ns=t_first),
            t_first,
        )
        bw.write(
            contract.TRUTH_POINTS,
            gcp_to_msg(truth, GroundControlPoints(), frame_id=FRAME_ID, stamp_ns=t_first),
            t_first,
        )
        # Navigation and strips, interleaved in time order.
        nav_t = np.arange(first, last, 1.0 / scn.nav_rate_hz)
        events: list[tuple[int, int, Any]] = []
        vel = np.array(scn.velocity)
        for t in nav_t:
            pos = np.array(scn.position0) + t * vel
            s = NavSample(scn.time_ns(float(t)), pos, scn.body_rotation(float(t)), vel)
            events.append(
                (
                    s.t_ns,
                    0,
                    (
                        contract.NAVIGATION,
                        sample_to_odometry(
                            s, Odometry(), frame_id=FRAME_ID, child_frame_id=contract.BODY_FRAME
                        ),
                    ),
                )
            )
        total = sum(sc.lines for sc in scn.scenes)
        with _progress(total, f"render {scn.name}", progress) as bar:
            for i, sc in enumerate(scn.scenes):
                model = scn.model(i)
                img = render_scene(model, terrain, 0, sc.lines, dtype=dtype)
                bar.update(sc.lines)
                lp = model.camera.line_period
                for r0 in range(0, sc.lines, scn.strip_lines):
                    stamp = scn.time_ns(sc.start_s + r0 * lp)
                    msg = array_to_image(
                        img[r0 : r0 + scn.strip_lines],
                        Image(),
                        frame_id=scn.scene_id(i),
                        stamp_ns=stamp,
                    )
                    events.append((stamp, 1, (contract.strip_topic(sc.view), msg)))
        events.sort(key=lambda e: (e[0], e[1]))
        for stamp, _, (topic, msg) in events:
            bw.write(topic, msg, stamp)
    size = sum(f.stat().st_size for f in Path(path).iterdir())
    log(
        f"wrote {path} ({size / 1e6:.2f} MB): {len(scn.scenes)} scenes, {len(gcp)} GCP/check, "
        f"{len(truth)} truth points"
    )
    return {"name": scn.name, "size_mb": size / 1e6, "gcp": len(gcp), "truth": len(truth)}


def _cam(scn: Scenario, view: str) -> LineCamera:
    return next(v for v in scn.views if v.name == view).camera
