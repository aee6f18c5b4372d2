"""Step 6, publish: the :class:`~parproj_ros.core.results.PairResult` of a normalized pair.

One function for the pairs normalized whole and the streamed ones: the pair's y-parallax
(its GCP and check points, else virtual points of its models), its height mapping
(``Z = a d + b``, paper 2), its terrain; then the ledger records the pair made and its scenes'
GCP are forgotten (those a selected pair still needs are kept).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .config import PipelineConfig
from .gcp_store import GcpStore
from .ledger import PairLedger
from .normalization import pair_terrain, y_parallax
from .results import PairGeometry, PairResult, SceneResult
from .terrain import Terrain


def finish_pair(
    left: SceneResult,
    right: SceneResult,
    geo: PairGeometry,
    images: tuple[NDArray[np.generic] | None, NDArray[np.generic] | None],
    stamp_ns: int,
    *,
    config: PipelineConfig,
    gcps: GcpStore,
    ledger: PairLedger,
    terrain: Terrain | None = None,
) -> PairResult:
    """The result of a normalized pair (``images``: None for a streamed pair), stamped ns.

    ``terrain``: the pair's terrain when measured; else that of its GCP or the prior
    (:func:`~parproj_ros.core.normalization.pair_terrain`), taken before the GCP are forgotten.
    """
    ypar, source = y_parallax(left, right, geo.left_geom, geo.right_geom, gcps, config.orientation)
    k = geo.normalization.parallax_per_height
    if terrain is None:
        terrain = pair_terrain(left, right, config.orientation, gcps)
    ids = (left.scene.scene_id, right.scene.scene_id)
    gcps.forget(ids, keep=ledger.selected_scene_ids())
    ledger.pair_made(left.scene.index)
    return PairResult(
        geo.pair_id,
        stamp_ns,
        left,
        right,
        geo.normalization,
        geo.left_grid,
        geo.right_grid,
        images[0],
        images[1],
        geo.left_grid.pixel / k,
        (geo.left_grid.x_origin - geo.right_grid.x_origin - geo.normalization.parallax_offset) / k,
        ypar,
        source,
        terrain,
    )
