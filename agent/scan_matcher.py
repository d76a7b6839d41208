"""2-D scan-to-submap matching: correlative search, then least-squares refinement.

The agent's local SLAM front end, as Cartographer's
`LocalTrajectoryBuilder2D::ScanMatch` does it. All poses are T_submap_sensor
[x, y, yaw] (m, rad); points are (N, 2) in the sensor frame (m).

1. `adaptive_voxel_filter` thins a scan to a few hundred points.
2. `RealTimeCorrelativeMatcher` finds the best pose on the lattice (grid cells x
   angular steps) inside a window around the prediction. The result equals an
   exhaustive search, found by branch and bound over max-pooled grids (Olson 2009;
   Cartographer's `FastCorrelativeScanMatcher2D`). Score = mean cell probability of
   the points times Cartographer's real-time penalty exp(-(w_t |dt| + w_r |dyaw|)^2),
   so ties (a corridor) go to the candidate nearest the prediction.
3. `CeresLikeRefiner` moves the pose off the lattice: Levenberg-Marquardt with
   analytic Jacobians (numba) on the Catmull-Rom bicubic interpolation of the grid,
   cost = sum_i (w_occ / sqrt(N) * (1 - P(T p_i)))^2 + |w_t (t - t_prior)|^2
   + (w_r wrap(yaw - yaw_prior))^2 (Cartographer's `CeresScanMatcher2D`). As in
   Cartographer, `match` uses the predicted translation and the correlative yaw as
   the prior.

Unknown cells read as `unknown_probability`, 0.5 by default (Hector SLAM's choice).
Cartographer reads them as the grid's min probability (0.1). In a young submap that
makes free cells (0.49 after one scan) almost as good as walls (0.55) and much
better than the unknown space behind walls: in tests with a one-scan submap the
correlative result was off by up to 16 cm, against 3.5 cm with 0.5.

Covariance of a match (3x3, [x, y, yaw], submap frame): Olson's, from the
correlative likelihood exp(sum_i log P_i) over the search window, through the best
lattice pose (`RealTimeCorrelativeMatcher.covariance`). It is not taken from the
Gauss-Newton Hessian. The rasterized walls of a grid are stair-stepped, which gives
the cost strong local curvature along a featureless corridor: there the Hessian
covariance came out nearly isotropic (ratio 1-3), while the actual errors were
15-45 cm along the corridor and under 5 mm across it. The lattice likelihood is flat
along the corridor, so the covariance spreads over the window there.
`RefineResult.information` still carries J^T J for callers who want it.

`ScanMatcher` uses that covariance to keep the prediction in directions the scan
does not constrain (solution remapping, see its doc). Without remapping, the stair
texture would move the pose along a corridor by up to the window on every scan.

Instances cache the last grid pyramid and are not thread-safe: use one per thread.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from agent.correlative_matcher import RealTimeCorrelativeMatcher
from agent.grid_refiner import CeresLikeRefiner, _mean_cell_probability
from agent.probability_grid import ProbabilityGrid
from agent.voxel_filter import finite_points
from common.errors import CollabSlamError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MatchResult:
    """The outcome of `ScanMatcher.match`.

    `pose`: T_submap_sensor [x, y, yaw] (m, rad). `score`: mean probability of the
    cells the points fall in, unknown cells counted as the grid's min_probability.
    `covariance`: 3x3 over [x, y, yaw] (see module doc). `iterations`: LM iterations.
    `converged` is False when the scan had too few finite points (pose = prediction,
    covariance = the prior's), when the correlative search found no candidate above
    its min_score, or when LM did not converge; `pose` is then the best estimate
    available. `correlative_score`: NaN when the search was off or found nothing.
    """

    pose: FloatArray
    score: float
    covariance: FloatArray
    iterations: int
    converged: bool
    correlative_score: float = math.nan


class ScanMatcher:
    """Correlative search (optional), then refinement, with Olson's covariance.

    Degenerate directions are handled by solution remapping (Zhang, Kaess and Singh,
    ICRA 2016). A translation eigen-direction of the covariance whose standard
    deviation exceeds `unconstrained_sigma_xy` (m; default a third of the linear
    window) is taken from the prediction, not the match. The same holds for yaw
    against `unconstrained_sigma_yaw` (rad; default a third of the angular window).
    Otherwise the lattice's texture (stair-stepped walls, sparse far hits) would move
    the pose along a featureless corridor by up to the window on every scan. Pass
    math.inf to turn remapping off. The covariance comes from the correlative matcher
    even when `use_correlative` is off. A scan with fewer than `min_num_points`
    finite points is not matched.
    """

    def __init__(
        self,
        correlative: RealTimeCorrelativeMatcher | None = None,
        refiner: CeresLikeRefiner | None = None,
        use_correlative: bool = True,
        min_num_points: int = 3,
        unconstrained_sigma_xy: float | None = None,
        unconstrained_sigma_yaw: float | None = None,
    ) -> None:
        self.correlative = correlative or RealTimeCorrelativeMatcher()
        self.refiner = refiner or CeresLikeRefiner()
        self.use_correlative = bool(use_correlative)
        self.min_num_points = max(3, int(min_num_points))
        self.unconstrained_sigma_xy = (
            self.correlative.linear_window / 3.0
            if unconstrained_sigma_xy is None
            else float(unconstrained_sigma_xy)
        )
        self.unconstrained_sigma_yaw = (
            self.correlative.angular_window / 3.0
            if unconstrained_sigma_yaw is None
            else float(unconstrained_sigma_yaw)
        )

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> MatchResult:
        """Match (N, 2) sensor-frame points against `grid` near `predicted_pose`
        (T_submap_sensor). Raises CollabSlamError for a grid without scans, a bad
        shape or a non-finite prediction. An empty or all-NaN scan does not raise: it
        gives `converged=False` at the prediction."""
        if grid.num_scans == 0:
            raise CollabSlamError("cannot match against an empty probability grid")
        pred = np.asarray(predicted_pose, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(pred)):
            raise CollabSlamError(f"predicted pose must be finite, got {pred}")
        pts = finite_points(points_sensor, "points_sensor")
        if len(pts) < self.min_num_points:
            logger.warning(
                "scan has %d finite points (< %d): not matched", len(pts), self.min_num_points
            )
            covariance = self.correlative.covariance(grid, pts[:0], pred)
            return MatchResult(pred.copy(), 0.0, covariance, 0, False)
        initial, corr_score, found, covariance = pred, math.nan, True, None
        if self.use_correlative:
            corr = self.correlative.match(grid, pts, pred)
            if corr is None:
                found = False
                logger.debug("correlative search found no candidate above min_score")
            else:
                covariance, corr_score = corr.covariance, corr.score
                initial = self._remap(corr.pose, pred, covariance)
        # Cartographer's prior: the predicted translation and the initial yaw.
        prior = np.array([pred[0], pred[1], initial[2]])
        ref = self.refiner.refine(grid, pts, initial, prior)
        if covariance is None:
            covariance = self.correlative.covariance(grid, pts, ref.pose)
        pose = self._remap(ref.pose, pred, covariance)
        ox, oy = (float(v) for v in grid.origin_xy)
        score = _mean_cell_probability(
            grid.data, grid.min_probability, ox, oy, grid.resolution, pts, pose
        )
        return MatchResult(
            pose, float(score), covariance, ref.iterations, ref.converged and found, corr_score
        )

    def _remap(self, pose: FloatArray, pred: FloatArray, covariance: FloatArray) -> FloatArray:
        """`pose` in the constrained directions of `covariance`, `pred` in the others."""
        out = pose.copy()
        limit = self.unconstrained_sigma_xy**2
        a, b, c = covariance[0, 0], covariance[0, 1], covariance[1, 1]
        half_gap = math.hypot(0.5 * (a - c), b)
        big, small = 0.5 * (a + c) + half_gap, 0.5 * (a + c) - half_gap  # eigenvalues
        if small > limit:  # nothing constrains the translation
            out[:2] = pred[:2]
        elif big > limit:  # one loose direction: the eigenvector of `big`
            v = np.array([big - c, b]) if abs(big - c) >= abs(big - a) else np.array([b, big - a])
            v /= np.linalg.norm(v)
            out[:2] -= v * (v @ (pose[:2] - pred[:2]))
        if covariance[2, 2] > self.unconstrained_sigma_yaw**2:
            out[2] = pred[2]
        return out


_default_matcher: ScanMatcher | None = None


def match(
    grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
) -> MatchResult:
    """`ScanMatcher.match` with the default parameters (one shared, cached instance)."""
    global _default_matcher
    if _default_matcher is None:
        _default_matcher = ScanMatcher()
    return _default_matcher.match(grid, points_sensor, predicted_pose)
