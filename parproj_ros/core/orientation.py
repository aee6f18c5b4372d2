"""A complete scene's parallel projection parameters: paper 1 sections 3-4 (Eqs 9-13 and Eq 8).

From its GCP when at least ``min_gcp`` are observed in it (A1..A8 of Eq 3 estimated with the
roll psi of the PTP correction, Eq 8; or with the roll from navigation, or no PTP), else from
navigation (Eqs 9-13, with the crab-angle fallback to a fit on virtual points of the rigorous
model). A view's first scene that may have begun before navigation was received is not oriented.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..geometry import (
    GeometryError,
    ParallelProjection,
    PushbroomModel,
    SceneFrame,
    affine_to_nonlinear,
    estimate_affine,
    parameters_from_navigation,
)
from ..geometry.navigation import NavigationParameters
from ..geometry.pushbroom import LineCamera
from ..imaging.assembly import Scene
from .config import PipelineConfig, ViewConfig
from .gcp_store import GcpStore
from .results import Issue, Level, Method, SceneResult
from .trajectory import NavigationError, TrajectoryBuffer

FloatArray = NDArray[np.float64]


def start_seen(first_line_ns: int, nav_first_ns: int | None, margin_s: float) -> bool:
    """Whether navigation (from ``nav_first_ns``) arrived ``margin_s`` before ``first_line_ns``.

    Also True without any navigation: it cannot be told then. Times in nanoseconds.
    """
    if nav_first_ns is None:
        return True
    return first_line_ns - nav_first_ns >= margin_s * 1e9


def start_unseen(scene: Scene, nav_first_ns: int | None, margin_s: float) -> Issue | None:
    """An ERROR when ``scene`` may have begun before the pipeline was listening.

    Only a view's first scene can (``start_margin_s``). Its line numbers (to which GCP
    observations refer) and its place in the pairs would be guesses: it is not processed.
    """
    if scene.index > 0 or start_seen(scene.first_line_ns, nav_first_ns, margin_s):
        return None
    lead = (scene.first_line_ns - (nav_first_ns or 0)) / 1e9
    when = f"{lead:.3f} s before" if lead >= 0 else f"{-lead:.3f} s after"
    return Issue(
        Level.ERROR,
        f"{scene.view}/{scene.scene_id}",
        f"first scene received on view {scene.view} ({scene.lines} lines), and navigation "
        f"starts only {when} its first line (less than start_margin_s, {margin_s:g} s, "
        "before): the node may have started, or restarted, while this scene was under "
        "way, so its beginning, its line numbers (GCP observations) and its pair are "
        "unknown: scene skipped",
    )


def orient_scene(
    scene: Scene,
    view: ViewConfig,
    nav: TrajectoryBuffer,
    gcps: GcpStore,
    config: PipelineConfig,
) -> tuple[SceneResult | None, list[Issue]]:
    """Parameters of a complete scene (None: neither navigation nor GCP gave any), and issues.

    Navigation is fitted over the scene's lines (constant velocity and attitude); its scatter
    and attitude variation are reported. With ``min_gcp`` usable GCP observed in the scene the
    parameters come from them (:func:`scene_from_gcp`), else from navigation.
    """
    issues: list[Issue] = []
    where = f"{scene.view}/{scene.scene_id}"
    cam = view.camera
    nav_result = None
    model = None
    try:
        fit = nav.fit(scene.first_line_ns, scene.last_line_ns, view.mounting)
        model = PushbroomModel(cam, fit.motion)
        if fit.position_rms_m > config.navigation.position_tolerance_m:
            issues.append(
                Issue(
                    Level.WARN,
                    where,
                    (
                        f"navigation positions scatter by {fit.position_rms_m:.3g} m rms "
                        "about the constant-velocity line (> nav_position_tolerance_m, "
                        f"{config.navigation.position_tolerance_m:g} m): an "
                        "outlier or a manoeuvre; the parameters carry that error"
                    ),
                )
            )
        if fit.attitude_spread_rad > 1e-3:
            issues.append(
                Issue(
                    Level.WARN,
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
            z_avg=config.orientation.z_avg,
            scene_lines=scene.lines,
            height_range=config.orientation.height_range,
            crab_tolerance_px=config.orientation.crab_tolerance_px,
        )
    except (NavigationError, GeometryError) as err:
        issues.append(Issue(Level.WARN, where, f"no navigation-derived parameters: {err}"))
    issues += gcps.bad_observation_issues(scene)
    gxyz, gls, cxyz, cls = gcps.for_scene(scene)
    result: SceneResult | None = None
    min_gcp = config.orientation.min_gcp
    if len(gxyz) >= min_gcp:
        try:
            result = scene_from_gcp(
                scene,
                cam,
                nav_result,
                (gxyz, gls, cxyz, cls),
                roll=config.orientation.gcp_roll,
                model=None if nav_result is None else model,
            )
        except GeometryError as err:
            issues.append(
                Issue(
                    Level.WARN,
                    where,
                    f"GCP estimation failed ({err}); "
                    + ("using navigation" if nav_result else ""),
                )
            )
    elif len(gxyz) > 0:
        issues.append(
            Issue(
                Level.WARN,
                where,
                (f"only {len(gxyz)} GCP observed (need {min_gcp}): GCP not used"),
            )
        )
    if result is None and nav_result is not None and model is not None:
        result = SceneResult.from_navigation(scene, nav_result, model, cam)
        if nav_result.method != Method.NAVIGATION.value:
            issues.append(Issue(Level.WARN, where, nav_result.note))
    if result is None:
        issues.append(
            Issue(Level.ERROR, where, "no parameters (no usable navigation or GCP): scene skipped")
        )
    return result, issues


def scene_from_gcp(
    scene: Scene,
    cam: LineCamera,
    nav: NavigationParameters | None,
    points: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
    *,
    roll: str,
    model: PushbroomModel | None = None,
    reference: ParallelProjection | None = None,
) -> SceneResult:
    """A scene's parameters from its GCP: A1..A8 estimated (paper 1 Eq 8), then Eqs 4-6.

    Args:
        scene: the scene.
        cam: its camera.
        nav: its navigation-derived parameters, if any (scene frame, roll, mirror reference).
        points: (xyz (m), line/sample (px)) of the GCP, then of the check points.
        roll: ``gcp_roll``: "estimate" (Eq 8), "navigation" (psi from ``nav``; estimated
            without it) or "none" (no PTP correction).
        model: the rigorous model from navigation, kept in the result (with ``nav``).
        reference: parameters that pick the mirror solution of Eqs 4-6 (default: ``nav``'s).
    """
    gxyz, gls, cxyz, cls = points
    frame = (
        nav.frame
        if nav
        else SceneFrame((scene.lines - 1) / 2.0, cam.pixel_size, cam.pixel_size, cam.pp)
    )
    obs = frame.to_scene(gls[:, 0], gls[:, 1])
    roll_mode = roll
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
        None if nav is None else model,
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
