"""iSAM2 settings: gtsam's ISAM2Params, and the pose graph's options from the config.

The choices and what each costs are documented at ``BaseStationConfig`` (common/config.py)
and in docs/architecture.md ("Back end"); the defaults of ``PoseGraph.__init__`` match the
config's defaults.
"""

from __future__ import annotations

from typing import TypedDict

import gtsam

from basestation.gps_factor import GpsWeighting
from common.config import BaseStationConfig
from common.errors import CollabSlamError

FACTORIZATIONS = ("CHOLESKY", "QR")


def make_isam2_params(
    *,
    factorization: str,
    relinearize_threshold: float,
    relinearize_skip: int,
    wildfire_threshold: float,
    cache_linearized_factors: bool,
    adaptive_reorder_threshold: float,
) -> gtsam.ISAM2Params:
    """ISAM2Params with Gauss-Newton steps and re-used factor slots. Thresholds in rad
    or m; ``adaptive_reorder_threshold`` 0: off."""
    if factorization not in FACTORIZATIONS:
        raise CollabSlamError(f"factorization must be CHOLESKY or QR, got {factorization!r}")
    params = gtsam.ISAM2Params()
    params.setFactorization(factorization)
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    gauss_newton = gtsam.ISAM2GaussNewtonParams()
    gauss_newton.setWildfireThreshold(wildfire_threshold)
    params.setOptimizationParams(gauss_newton)
    params.cacheLinearizedFactors = cache_linearized_factors
    # A removed factor's slot takes a later new factor: with the reduced pose graph moving
    # factors onto anchors, the slots otherwise grow by ~1.6 per keyframe for good (96,206
    # for 8,347 factors after 60,000 keyframes of the 10-robot soak). Safe for removal by
    # slot: every factor's slot is read from getNewFactorsIndices, and a live factor's
    # slot is never given to another.
    params.findUnusedFactorSlots = True
    if adaptive_reorder_threshold > 0:
        params.enableAdaptiveReorder = True
        params.adaptiveReorderThreshold = adaptive_reorder_threshold
    return params


class PoseGraphOptions(TypedDict):
    """Keyword arguments of ``PoseGraph.__init__`` taken from the config."""

    relinearize_threshold: float
    relinearize_skip: int
    prior_sigmas: tuple[float, float, float]  # m, m, rad
    track_changes: bool
    wildfire_threshold: float
    cache_linearized_factors: bool
    adaptive_reorder_threshold: float
    heads_last: bool
    gps_weighting: GpsWeighting
    max_pending_gps_fixes: int
    gps_batch_period_s: float
    factorization: str
    reduce_distance_m: float
    reduce_lag: int
    reduce_after_nodes: int
    tie_budget: float
    rebuild_nodes: int


def pose_graph_options(b: BaseStationConfig, track_changes: bool | None = None) -> PoseGraphOptions:
    """The base station's pose-graph options (``track_changes`` None: ``b.track_changes``)."""
    return PoseGraphOptions(
        relinearize_threshold=b.relinearize_threshold,
        relinearize_skip=b.relinearize_skip,
        prior_sigmas=(b.prior_sigma_xy_m, b.prior_sigma_xy_m, b.prior_sigma_yaw_rad),
        track_changes=b.track_changes if track_changes is None else track_changes,
        wildfire_threshold=b.wildfire_threshold,
        cache_linearized_factors=b.cache_linearized_factors,
        adaptive_reorder_threshold=b.adaptive_reorder_threshold,
        heads_last=b.heads_last,
        gps_weighting=GpsWeighting.from_config(b.gps),
        max_pending_gps_fixes=b.gps.max_pending_fixes,
        gps_batch_period_s=b.gps.batch_period_s,
        # QR with GPS's loose start priors (Cholesky calls them indeterminate)
        factorization="QR" if b.gps.enabled else b.isam2_factorization,
        reduce_distance_m=b.reduce_distance_m,
        reduce_lag=b.reduce_lag,
        reduce_after_nodes=b.reduce_after_nodes,
        tie_budget=b.reduce_tie_budget,
        rebuild_nodes=b.isam2_rebuild_nodes,
        tie_degree=b.reduce_tie_degree,
    )
