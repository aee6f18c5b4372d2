"""Tie points through RPC models: triangulation, and multi-view RPC bias compensation.

Observation model (Grodecki & Dial 2003, "Block adjustment of high-resolution satellite images
described by rational polynomials", PE&RS 69(1), the shift case): a tie point with ground
position X (lon, lat, h) is seen by view v at::

    (line, sample) = RPC_v(X) + b_v + noise

with b_v = (line bias, sample bias), pixels, one per view. Over a crop of a few thousand pixels
the error of a satellite RPC is dominated by such a constant image-space offset (the attitude
and ephemeris bias); the affine form of the paper adds terms that the crops this project
imports cannot separate from the constant at the 0.05 px level (not implemented).

The adjustment (:func:`adjust_biases`) solves for every b_v and every tie point's X together, by
Gauss-Newton on the reprojection residuals, the tie points eliminated by the Schur complement
(each point's 3 x 3 normal block is inverted alone), with robust rejection of blunders.

Gauge: tie points alone fix the biases only up to the image motion of a common ground
displacement d (3 dimensions: moving every tie point by d and every bias by -J_v d leaves every
residual unchanged, J_v = d(line, sample)/d(east, north, up) of view v at the scene centre). A
pair sees one more combination only (its y-parallax); three views fix the along-epipolar
relative biases, which a pair turns into a height offset of its DSM. The gauge chosen:

* ``"mean"`` (default): the corrections have no component along a common ground displacement
  (``G^T b = 0``, G = the 2V x 3 image motions of east, north and up): the smallest corrections
  (least squares in pixels) that make the views agree, so that the adjusted block sits where the
  RPCs put it on average;
* a view index r: ``b_r = 0`` and no component along a displacement along r's ray (which r does
  not see): r's RPC is kept and the others are brought onto it.

Units: pixels of each view (this project's convention: (0, 0) = centre of the first pixel);
ground in degrees (WGS84) and metres (ellipsoidal heights); internal ground steps in metres east,
north and up.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .model import RPCModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Metres per degree of latitude (mean; the Jacobians are numerical, this only scales steps).
M_PER_DEG = 111_320.0
#: Finite-difference step of the ground Jacobians, metres.
STEP_M = 1.0
#: Observations whose residual exceeds max(REJECT_SIGMA * sigma, REJECT_FLOOR_PX) are dropped.
REJECT_SIGMA = 4.0
#: Floor of the rejection threshold, pixels (SIFT positions are good to a few tenths).
REJECT_FLOOR_PX = 1.0
#: Fewest tie points seen in three or more views for an adjustment.
MIN_MULTI_TRACKS = 20
#: Fewest of those each view must be in.
MIN_VIEW_OBSERVATIONS = 10


def _metres(lat_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Metres per degree of longitude and of latitude at ``lat_deg`` (sphere, enough for steps)."""
    return M_PER_DEG * np.cos(np.radians(lat_deg)), np.full_like(lat_deg, M_PER_DEG)


def project_biased(
    rpc: RPCModel, geo: FloatArray, bias: Sequence[float] = (0.0, 0.0)
) -> FloatArray:
    """(n, 2) (line, sample) of geodetic points (n, 3) through ``rpc`` plus ``bias``, pixels."""
    line, sample = rpc.project(geo[:, 0], geo[:, 1], geo[:, 2], outside="nan")
    return np.stack([line + bias[0], sample + bias[1]], axis=-1)


def ground_jacobian(rpc: RPCModel, geo: FloatArray) -> FloatArray:
    """(n, 2, 3): d(line, sample) / d(east, north, up), pixels per metre.

    Forward differences of :data:`STEP_M` (their error, from the RPC's curvature, is below
    1e-5 px / m on the Marseille Pleiades models, where a metre is 2 px).
    """
    mx, my = _metres(geo[:, 1])
    out = np.empty((geo.shape[0], 2, 3))
    p0 = project_biased(rpc, geo)
    for k, scale in enumerate((mx, my, np.ones_like(mx))):
        d = np.zeros_like(geo)
        d[:, k] = STEP_M / scale
        out[:, :, k] = (project_biased(rpc, geo + d) - p0) / STEP_M
    return out


def pair_heights(
    left: RPCModel, right: RPCModel, pl: FloatArray, pr: FloatArray, h_span: tuple[float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Two-view triangulation: the height at which the left ray meets the right point.

    For each match (left (line, sample) ``pl``, right ``pr``, (n, 2) pixels), the height h at
    which localizing the left point and projecting it into the right image lands closest to the
    right point (the curve is a straight line to far below a pixel over the span; refined once
    about the solution).

    Args:
        left: the left view's RPC.
        right: the right view's RPC.
        pl: (n, 2) left (line, sample), pixels.
        pr: (n, 2) right (line, sample), pixels.
        h_span: two heights the search is set up on, metres (e.g. the RPC's height span).

    Returns:
        h (n,) metres; the signed distance of the right point across the epipolar curve (the
        y-parallax, pixels, positive to the left of the curve's direction of increasing h);
        and the right image motion per metre of height (n, 2) pixels / m. NaN where a
        localization fails.

    """
    h1, h2 = float(h_span[0]), float(h_span[1])

    def curve(h: FloatArray) -> FloatArray:
        lon, lat = left.localize(pl[:, 0], pl[:, 1], h, outside="nan")
        return np.stack(right.project(lon, lat, h, outside="nan"), axis=-1)

    n = pl.shape[0]
    ha, hb = np.full(n, h1), np.full(n, h2)
    for _ in range(2):
        qa, qb = curve(ha), curve(hb)
        v = (qb - qa) / (hb - ha)[:, None]
        vv = np.einsum("ij,ij->i", v, v)
        with np.errstate(invalid="ignore", divide="ignore"):
            h = ha + np.einsum("ij,ij->i", pr - qa, v) / vv
        # refine on a short secant about the solution (curvature of the epipolar curve)
        ha, hb = h - 5.0, h + 5.0
    q = curve(h)
    d = pr - q
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / np.sqrt(vv)[:, None]
    across = u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0]
    return h, across, v


def triangulate(
    rpcs: Sequence[RPCModel],
    obs: FloatArray,
    biases: FloatArray | None = None,
    *,
    h0: float | None = None,
    iterations: int = 8,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares ground positions of tie points seen in two or more views.

    Args:
        rpcs: one RPC per view.
        obs: (n, V, 2) (line, sample) pixels per tie point and view; NaN where not seen.
        biases: (V, 2) image biases (line, sample) pixels, added to each RPC's projection.
        h0: starting height, metres (default the first view's ``height_off``).
        iterations: Gauss-Newton iterations (the model is nearly linear: 3-4 suffice).

    Returns:
        geo (n, 3) lon deg, lat deg, h m (NaN for a point seen in fewer than two views or
        that fails); residuals (n, V, 2) observed - modelled, pixels (NaN where not seen).

    """
    n, nv = obs.shape[0], len(rpcs)
    b = np.zeros((nv, 2)) if biases is None else np.asarray(biases, dtype=np.float64)
    seen = np.all(np.isfinite(obs), axis=2)
    geo = np.full((n, 3), np.nan)
    start = np.full(n, rpcs[0].height_off if h0 is None else h0)
    first = np.argmax(seen, axis=1)
    for v, rpc in enumerate(rpcs):
        k = first == v
        if np.any(k):
            lon, lat = rpc.localize(
                obs[k, v, 0] - b[v, 0], obs[k, v, 1] - b[v, 1], start[k], outside="nan"
            )
            geo[k] = np.stack([lon, lat, start[k]], axis=-1)
    ok = seen.sum(axis=1) >= 2
    geo[~ok] = np.nan
    jac = np.zeros((n, nv, 2, 3))
    for k in range(iterations):
        # chord method: the Jacobians of the first two iterates serve all later ones (an RPC
        # is nearly linear over the metres a tie point moves after the first step)
        res, new_jac = _residuals(rpcs, obs, b, geo, seen, jacobian=k < 2)
        if k < 2:
            jac = new_jac
        nxx = np.einsum("nvki,nvkj->nij", jac, jac)
        gx = np.einsum("nvki,nvk->ni", jac, np.where(np.any(jac, axis=3), res, 0.0))
        step = _solve3(nxx, gx)
        mx, my = _metres(geo[:, 1])
        geo = geo + np.stack([step[:, 0] / mx, step[:, 1] / my, step[:, 2]], axis=-1)
        if not np.nanmax(np.abs(step), initial=0.0) > 1e-3:
            break
    res, _ = _residuals(rpcs, obs, b, geo, seen, jacobian=False)
    res[~seen] = np.nan
    return geo, res


def _solve3(a: FloatArray, g: FloatArray) -> FloatArray:
    """Solve n 3 x 3 systems a x = g (NaN where singular or not finite)."""
    out = np.full(g.shape, np.nan)
    good = np.all(np.isfinite(a), axis=(1, 2)) & np.all(np.isfinite(g), axis=1)
    good &= np.abs(np.linalg.det(np.where(good[:, None, None], a, np.eye(3)))) > 1e-18
    if np.any(good):
        out[good] = np.linalg.solve(a[good], g[good][..., None])[..., 0]
    return out


def _residuals(
    rpcs: Sequence[RPCModel],
    obs: FloatArray,
    b: FloatArray,
    geo: FloatArray,
    seen: BoolArray,
    *,
    jacobian: bool = True,
) -> tuple[FloatArray, FloatArray]:
    """Residuals (n, V, 2) and ground Jacobians (n, V, 2, 3); zero where not seen."""
    n, nv = obs.shape[0], len(rpcs)
    res = np.zeros((n, nv, 2))
    jac = np.zeros((n, nv, 2, 3))
    for v, rpc in enumerate(rpcs):
        k = seen[:, v] & np.all(np.isfinite(geo), axis=1)
        if not np.any(k):
            continue
        res[k, v] = obs[k, v] - project_biased(rpc, geo[k], b[v])
        if jacobian:
            jac[k, v] = ground_jacobian(rpc, geo[k])
    bad = ~np.isfinite(res) | ~np.isfinite(jac).all(axis=3)
    res[bad] = 0.0
    jac[np.broadcast_to(bad[..., None], jac.shape)] = 0.0
    return res, jac


@dataclass
class BiasAdjustment:
    """The result of :func:`adjust_biases`.

    Attributes:
        biases: (V, 2) line, sample bias per view, pixels: the corrected model of view v is
            ``RPC_v(X) + biases[v]`` (:func:`apply_biases`).
        rms_before: (V,) RMS reprojection residual per view, sqrt(mean(dl^2 + ds^2)) pixels,
            with the RPCs as given and each tie point triangulated; inliers only.
        rms_after: (V,) the same with the biases.
        observations: (V,) inlier observations per view.
        tracks: tie points used (inliers, seen in two or more views).
        multi_tracks: of those, seen in three or more views.
        ground: (n, 3) adjusted lon, lat, h of every input tie point (NaN: rejected).
        inliers: (n, V) observations kept.
        gauge: the gauge (``"mean"`` or the fixed view's index).
        iterations: Gauss-Newton iterations done.
        shift_m: mean displacement of the tie points' ground (east, north, up) metres from the
            unadjusted triangulation to the adjusted one.

    """

    biases: FloatArray
    rms_before: FloatArray
    rms_after: FloatArray
    observations: NDArray[np.int64]
    tracks: int
    multi_tracks: int
    ground: FloatArray
    inliers: BoolArray
    gauge: str | int
    iterations: int
    shift_m: FloatArray = field(default_factory=lambda: np.zeros(3))


def _rms(res: FloatArray, mask: BoolArray) -> FloatArray:
    """(V,) RMS of |residual| per view over ``mask`` (n, V), pixels (NaN for no observation)."""
    sq = np.where(mask, np.sum(np.nan_to_num(res) ** 2, axis=2), 0.0)
    cnt = mask.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.sqrt(sq.sum(axis=0) / cnt), dtype=np.float64)


def _gauge_matrix(rpcs: Sequence[RPCModel], centre: FloatArray, gauge: str | int) -> FloatArray:
    """Rows c with c . b = 0 (b = the (2V,) stacked biases) that fix the datum (module doc)."""
    nv = len(rpcs)
    jac = np.stack([ground_jacobian(r, centre[None, :])[0] for r in rpcs])  # (V, 2, 3)
    motions = jac.reshape(2 * nv, 3)  # column k: image motion of a 1 m step along axis k
    if gauge == "mean":
        return np.asarray(motions.T, dtype=np.float64)
    r = int(gauge)
    if not 0 <= r < nv:
        raise ValueError(f"gauge: view {r} of {nv}")
    # the direction view r does not see: the null vector of its 2 x 3 Jacobian (its ray)
    _, _, vt = np.linalg.svd(jac[r])
    ray = vt[-1]
    rows = np.zeros((3, 2 * nv))
    rows[0, 2 * r] = rows[1, 2 * r + 1] = 1.0
    rows[2] = motions @ ray
    return rows


def adjust_biases(
    rpcs: Sequence[RPCModel],
    obs: FloatArray,
    *,
    gauge: str | int = "mean",
    iterations: int = 10,
    reject_sigma: float = REJECT_SIGMA,
    reject_floor_px: float = REJECT_FLOOR_PX,
    min_multi_tracks: int = MIN_MULTI_TRACKS,
    names: Sequence[str] | None = None,
) -> BiasAdjustment:
    """Per-view image biases from tie points (module docstring), with robust rejection.

    Args:
        rpcs: one RPC per view (V >= 2).
        obs: (n, V, 2) (line, sample) pixels per tie point and view, NaN where not seen.
        gauge: ``"mean"`` or the index of the view kept fixed (module docstring).
        iterations: most Gauss-Newton iterations (each after a rejection pass).
        reject_sigma: observations beyond this many robust sigmas (1.4826 MAD of the residual
            norms) are dropped, with a floor of ``reject_floor_px``.
        reject_floor_px: floor of the rejection threshold, pixels.
        min_multi_tracks: fewest inlier tie points seen in three or more views.
        names: the views' names for the messages (default: their indices).

    Returns:
        The adjustment (:class:`BiasAdjustment`).

    Raises:
        ValueError: fewer than two views, a malformed ``obs``, fewer than
            ``min_multi_tracks`` tie points in three or more views, or a view in fewer than
            :data:`MIN_VIEW_OBSERVATIONS` of them (the message says which and how many).

    """
    nv = len(rpcs)
    obs = np.asarray(obs, dtype=np.float64)
    if nv < 2 or obs.ndim != 3 or obs.shape[1:] != (nv, 2):
        raise ValueError(f"obs must be (n, {nv}, 2) for {nv} >= 2 views, got {obs.shape}")
    inl = np.all(np.isfinite(obs), axis=2)
    b = np.zeros((nv, 2))
    geo0, res0 = triangulate(rpcs, np.where(inl[..., None], obs, np.nan))
    # robust rejection with the RPCs as given (a bias is common to all of a view's points)
    for _ in range(3):
        inl = _reject(res0, inl, reject_sigma, reject_floor_px)
        geo0, res0 = triangulate(rpcs, np.where(inl[..., None], obs, np.nan))
    count = inl.sum(axis=1)
    if int(np.sum(count >= 3)) < min_multi_tracks:
        raise ValueError(
            f"only {int(np.sum(count >= 3))} tie points are seen in three or more views (at "
            f"least {min_multi_tracks} needed to fix the views' relative biases)"
        )
    per_view = (inl & (count >= 3)[:, None]).sum(axis=0)
    if int(per_view.min()) < MIN_VIEW_OBSERVATIONS:
        v = int(np.argmin(per_view))
        raise ValueError(
            f"view {names[v] if names else v} is in only {int(per_view[v])} tie points seen in "
            f"three or more views (at least {MIN_VIEW_OBSERVATIONS} needed to fix its bias)"
        )
    centre = np.nanmedian(geo0[count >= 2], axis=0)
    c = _gauge_matrix(rpcs, centre, gauge)
    geo = geo0.copy()
    done = 0
    for _ in range(iterations):
        done += 1
        use = inl & (inl.sum(axis=1) >= 2)[:, None]
        step_b, geo = _gauss_newton_step(rpcs, obs, b, geo, use, c)
        b = b + step_b
        geo, res = triangulate(rpcs, np.where(use[..., None], obs, np.nan), b)
        inl_new = _reject(res, inl, reject_sigma, reject_floor_px)
        if np.max(np.abs(step_b)) < 1e-4 and np.array_equal(inl_new, inl):
            break
        inl = inl_new
    use = inl & (inl.sum(axis=1) >= 2)[:, None]
    geo, res = triangulate(rpcs, np.where(use[..., None], obs, np.nan), b)
    _, res_b = triangulate(rpcs, np.where(use[..., None], obs, np.nan))
    tracks = use.any(axis=1)
    geo[~tracks] = np.nan
    both = tracks & np.all(np.isfinite(geo), axis=1) & np.all(np.isfinite(geo0), axis=1)
    mx, my = _metres(geo[both, 1])
    d = geo[both] - geo0[both]
    shift = (
        np.array([np.mean(d[:, 0] * mx), np.mean(d[:, 1] * my), np.mean(d[:, 2])])
        if np.any(both)
        else np.zeros(3)
    )
    return BiasAdjustment(
        biases=b,
        rms_before=_rms(res_b, use),
        rms_after=_rms(res, use),
        observations=use.sum(axis=0).astype(np.int64),
        tracks=int(tracks.sum()),
        multi_tracks=int(np.sum(use.sum(axis=1) >= 3)),
        ground=geo,
        inliers=use,
        gauge=gauge,
        iterations=done,
        shift_m=shift,
    )


def _reject(res: FloatArray, inl: BoolArray, k: float, floor: float) -> BoolArray:
    """Observations whose residual norm is within max(k robust sigma, floor) pixels."""
    norm = np.hypot(res[..., 0], res[..., 1])
    v = norm[inl & np.isfinite(norm)]
    if v.size == 0:
        return inl
    sigma = 1.4826 * float(np.median(v))
    with np.errstate(invalid="ignore"):
        keep = inl & (norm <= max(k * sigma, floor))
    # a point left in one view tells nothing
    keep &= (keep.sum(axis=1) >= 2)[:, None]
    return np.asarray(keep)


def _gauss_newton_step(
    rpcs: Sequence[RPCModel],
    obs: FloatArray,
    b: FloatArray,
    geo: FloatArray,
    use: BoolArray,
    c: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """One joint step (biases and ground), tie points eliminated (reduced camera system).

    The bias step solves ``S db = r`` subject to ``c (b + db) = 0`` (Lagrange multipliers).
    Returns (db (V, 2), updated geo).
    """
    nv = len(rpcs)
    res, jac = _residuals(rpcs, obs, b, geo, use)
    res = np.where(use[..., None], res, 0.0)
    jac = np.where(use[..., None, None], jac, 0.0)
    nxx = np.einsum("nvki,nvkj->nij", jac, jac)
    gx = np.einsum("nvki,nvk->ni", jac, res)
    good = np.all(np.isfinite(geo), axis=1) & (use.sum(axis=1) >= 2)
    nxx_inv = np.zeros_like(nxx)
    nxx_inv[good] = np.linalg.inv(nxx[good])
    # bias block: each observation of view v adds I2 to (v, v); coupling N_bX[v] = J_nv
    s = np.zeros((2 * nv, 2 * nv))
    rb = np.zeros(2 * nv)
    for v in range(nv):
        s[2 * v : 2 * v + 2, 2 * v : 2 * v + 2] += np.eye(2) * use[good, v].sum()
        rb[2 * v : 2 * v + 2] += res[good, v].sum(axis=0)
    jg, ig, gg = jac[good], nxx_inv[good], gx[good]
    # sum_n N_bX N_XX^-1 N_Xb over the views' 2-row blocks
    t = np.einsum("nvki,nij->nvkj", jg, ig)  # (n, V, 2, 3)
    s -= np.einsum("nvki,nwli->vkwl", t, jg).reshape(2 * nv, 2 * nv)
    rb -= np.einsum("nvki,ni->vk", t, gg).reshape(2 * nv)
    m = c.shape[0]
    kkt = np.zeros((2 * nv + m, 2 * nv + m))
    kkt[: 2 * nv, : 2 * nv] = s
    kkt[: 2 * nv, 2 * nv :] = c.T
    kkt[2 * nv :, : 2 * nv] = c
    rhs = np.concatenate([rb, -c @ b.ravel()])
    sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
    db = sol[: 2 * nv].reshape(nv, 2)
    # back-substitution: dX = N_XX^-1 (g_X - N_Xb db)
    coupling = np.einsum("nvki,vk->ni", jac, db)
    dx = np.einsum("nij,nj->ni", nxx_inv, gx - coupling)
    mx, my = _metres(geo[:, 1])
    new = geo + np.stack([dx[:, 0] / mx, dx[:, 1] / my, dx[:, 2]], axis=-1)
    new[~good] = geo[~good]
    return db, new


def apply_biases(rpcs: Sequence[RPCModel], biases: FloatArray) -> list[RPCModel]:
    """Each RPC with its bias folded in: ``RPC_v(X) + biases[v]`` (line, sample pixels)."""
    return [r.shifted(float(b[0]), float(b[1])) for r, b in zip(rpcs, biases, strict=True)]


def robust_range(
    heights: FloatArray, *, low: float = 1.0, high: float = 99.0
) -> tuple[float, float]:
    """(low, high) percentiles of the finite heights, metres (NaN, NaN when there are none)."""
    h = heights[np.isfinite(heights)]
    if h.size == 0:
        return math.nan, math.nan
    lo, hi = np.percentile(h, [low, high])
    return float(lo), float(hi)


__all__ = [
    "BiasAdjustment",
    "adjust_biases",
    "apply_biases",
    "ground_jacobian",
    "pair_heights",
    "project_biased",
    "robust_range",
    "triangulate",
]
