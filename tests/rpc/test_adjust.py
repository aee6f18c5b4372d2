"""Multi-view RPC bias adjustment and RPC triangulation (parproj_ros/rpc/adjust.py).

The RPCs are the three real Pleiades models of the Marseille triplet (../shared/data/
marseille_triplet, read from each image's GeoTIFF tag); the tie points are exact projections of
random ground points (heights over the area's 50..340 m) with known image biases, Gaussian noise
of ``NOISE`` px per coordinate and blunders injected.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from testkit.paths import ROOT

from parproj_ros.io.scene_import import find_rpc
from parproj_ros.rpc import RPCModel
from parproj_ros.rpc.adjust import (
    adjust_biases,
    apply_biases,
    ground_jacobian,
    pair_heights,
    project_biased,
    triangulate,
)

MARSEILLE = ROOT.parent / "shared" / "data" / "marseille_triplet"
#: Image noise of the synthetic tie points, px per coordinate (SIFT-like).
NOISE = 0.2
#: Tie points.
N = 600
#: Injected biases (line, sample) px per view.
BIASES = np.array([[0.8, -1.3], [-0.4, 0.9], [1.5, 0.2]])


@pytest.fixture(scope="module")
def rpcs() -> list[RPCModel]:
    return [find_rpc(MARSEILLE / f"img_0{i}.tif")[0] for i in (1, 2, 3)]


def _ground(rpc: RPCModel, n: int, seed: int) -> np.ndarray:
    """n ground points under the first image (1024 px square), heights 50..340 m."""
    rng = np.random.default_rng(seed)
    line, sample = rng.uniform(0, 1023, n), rng.uniform(0, 1023, n)
    h = rng.uniform(50.0, 340.0, n)
    lon, lat = rpc.localize(line, sample, h)
    return np.stack([lon, lat, h], axis=-1)


def _observations(
    rpcs: list[RPCModel], geo: np.ndarray, biases: np.ndarray, seed: int
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    obs = np.stack([project_biased(r, geo, b) for r, b in zip(rpcs, biases, strict=True)], 1)
    return obs + rng.normal(0.0, NOISE, obs.shape)


def _gauge_basis(rpcs: list[RPCModel], geo: np.ndarray) -> np.ndarray:
    """(2V, 3): image motion of each view for a 1 m ground step east, north, up."""
    centre = np.median(geo, axis=0)[None, :]
    return np.concatenate([ground_jacobian(r, centre)[0] for r in rpcs])


def test_pair_heights_exact(rpcs: list[RPCModel]) -> None:
    """Exact correspondences: the height back to 1 mm, nothing across the epipolar curve."""
    geo = _ground(rpcs[0], 200, 1)
    pl, pr = project_biased(rpcs[0], geo), project_biased(rpcs[2], geo)
    h, across, v = pair_heights(rpcs[0], rpcs[2], pl, pr, (300.0, 800.0))
    assert np.max(np.abs(h - geo[:, 2])) < 1e-3
    assert np.max(np.abs(across)) < 1e-4
    # pair 1-3: about 2.2 m of height per pixel of disparity (data README)
    assert 1.9 < float(np.median(1.0 / np.hypot(v[:, 0], v[:, 1]))) < 2.5
    # a right point moved 1 px across the curve reads as 1 px of y-parallax, same height
    normal = np.stack([-v[:, 1], v[:, 0]], axis=-1) / np.hypot(v[:, 0], v[:, 1])[:, None]
    h2, across2, _ = pair_heights(rpcs[0], rpcs[2], pl, pr + normal, (300.0, 800.0))
    assert np.allclose(np.abs(across2), 1.0, atol=1e-3)
    assert np.max(np.abs(h2 - geo[:, 2])) < 0.01


def test_triangulate_three_views(rpcs: list[RPCModel]) -> None:
    """Least-squares ground of exact observations: back to 1 mm, residuals ~ 0."""
    geo = _ground(rpcs[0], 100, 2)
    obs = np.stack([project_biased(r, geo) for r in rpcs], 1)
    obs[:30, 1] = np.nan  # seen in two views only
    est, res = triangulate(rpcs, obs)
    mx = 111_320.0 * np.cos(np.radians(geo[:, 1]))
    assert np.max(np.abs(est[:, 0] - geo[:, 0]) * mx) < 1e-3
    assert np.max(np.abs(est[:, 2] - geo[:, 2])) < 1e-3
    assert np.nanmax(np.abs(res)) < 1e-4
    assert np.all(np.isnan(res[:30, 1]))


def test_biases_recovered_with_a_fixed_view(rpcs: list[RPCModel]) -> None:
    """Gauge 'view 0': b_0 = 0, and b - b_true is a common ground displacement's image motion.

    Tolerance: a bias is a mean over ~600 observations of noise 0.2 px: its standard error is
    about 0.2 / sqrt(600) x (a factor < 3 for the tie points' own unknowns) < 0.025 px; 0.06 px.
    """
    geo = _ground(rpcs[0], N, 3)
    obs = _observations(rpcs, geo, BIASES, 4)
    obs[:100, 2] = np.nan  # some points in two views only
    obs[200:230, 1, 1] += 25.0  # blunders in view 1
    res = adjust_biases(rpcs, obs, gauge=0)
    assert np.allclose(res.biases[0], 0.0, atol=1e-9)
    g = _gauge_basis(rpcs, geo)
    d = (res.biases - BIASES).ravel()
    # remove the best common ground displacement: what is left is the estimation error
    left = d - g @ np.linalg.lstsq(g, d, rcond=None)[0]
    assert np.max(np.abs(left)) < 0.06
    assert not res.inliers[200:230, 1].any()  # the blunders are out
    assert res.inliers[230:, 1].mean() > 0.98
    # residuals: before, the biases' inconsistent part (0.6-1.4 px here); after, the noise
    # (RMS of a 2-D residual of two coordinates of 0.2 px, less the share the tie points
    # absorb: 0.2..0.29 px)
    assert np.all(res.rms_before > 2.0 * res.rms_after)
    assert np.all((res.rms_after > 0.15) & (res.rms_after < 0.3))
    assert res.multi_tracks == pytest.approx(N - 100, abs=35)


def test_mean_gauge_is_the_smallest_correction(rpcs: list[RPCModel]) -> None:
    """Gauge 'mean': the biases are the true ones less their common-displacement part."""
    geo = _ground(rpcs[0], N, 5)
    res = adjust_biases(rpcs, _observations(rpcs, geo, BIASES, 6))
    g = _gauge_basis(rpcs, geo)
    expected = BIASES.ravel() - g @ np.linalg.lstsq(g, BIASES.ravel(), rcond=None)[0]
    assert np.max(np.abs(res.biases.ravel() - expected)) < 0.06
    # no component along a common displacement (the constraint, to rounding)
    assert np.max(np.abs(g.T @ res.biases.ravel())) < 1e-6


def test_adjusted_pairs_share_one_object_space(rpcs: list[RPCModel]) -> None:
    """The point of it: after the correction, every pair triangulates the same heights.

    Before, each pair's heights are offset by its relative bias along the epipolar direction
    (metres = pixels x metres per pixel of disparity: 4.4 m in pairs 1-2 and 2-3, 2.2 m in
    1-3); after, the pairs agree to the noise of a median over 600 points (< 0.1 m).
    """
    geo = _ground(rpcs[0], N, 7)
    obs = _observations(rpcs, geo, BIASES, 8)
    res = adjust_biases(rpcs, obs)

    def offsets(models: list[RPCModel]) -> list[float]:
        hs = {}
        for i, j in itertools.combinations(range(3), 2):
            hs[i, j] = pair_heights(models[i], models[j], obs[:, i], obs[:, j], (300, 800))[0]
        return [float(np.median(hs[k] - hs[0, 1])) for k in ((0, 2), (1, 2))]

    before = offsets(rpcs)
    after = offsets(apply_biases(rpcs, res.biases))
    assert max(abs(x) for x in before) > 2.0
    assert max(abs(x) for x in after) < 0.1


def test_two_views_cannot_fix_the_relative_bias(rpcs: list[RPCModel]) -> None:
    geo = _ground(rpcs[0], 100, 9)
    obs = _observations(rpcs[:2], geo, BIASES[:2], 10)
    with pytest.raises(ValueError, match="only 0 tie points are seen in three or more views"):
        adjust_biases(rpcs[:2], obs)
    with pytest.raises(ValueError, match=r"obs must be \(n, 3, 2\)"):
        adjust_biases(rpcs, obs)


def test_a_view_in_too_few_tie_points_is_named(rpcs: list[RPCModel]) -> None:
    """A fourth view (another acquisition of img_02's geometry) in only 5 of the tie points:
    its bias is not determined, and the message names it."""
    four = [*rpcs, rpcs[1]]
    geo = _ground(rpcs[0], 200, 11)
    obs = _observations(four, geo, np.vstack([BIASES, [[0.3, 0.3]]]), 12)
    obs[5:, 3] = np.nan
    with pytest.raises(ValueError, match="view img_04 is in only 5 tie points seen in three"):
        adjust_biases(four, obs, names=["img_01", "img_02", "img_03", "img_04"])
