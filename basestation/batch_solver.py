"""Batch Levenberg-Marquardt on the same factors as a PoseGraph (for benchmarks).

``batch_optimize(graph)`` solves the factors iSAM2 currently holds (priors, gauge
priors, odometry and constraints, robust kernels included; pending changes are
not, so call ``PoseGraph.update`` first) from scratch and leaves the PoseGraph
untouched. Compare ``BatchResult.chi2`` with ``PoseGraph.chi2()``: both are
sums of squared whitened residuals (2x gtsam's error).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from basestation.pose_graph import PoseGraph
from common.errors import CollabSlamError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BatchResult:
    poses: dict[str, FloatArray]  # robot id -> (N, 3) T_map_node [x, y, yaw]
    wall_ms: float  # LM optimize() only (building the problem is not counted)
    cpu_ms: float  # the same, CPU time of this thread (robust to a loaded machine)
    chi2_initial: float
    chi2: float
    iterations: int


def batch_optimize(
    graph: PoseGraph,
    start: str = "guess",
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
    absolute_error_tol: float = 1e-5,
) -> BatchResult:
    """Levenberg-Marquardt from the nodes' initial guesses ("guess") or the iSAM2 estimate
    ("current"). "guess" is the fair baseline for timing: the same start iSAM2 had."""
    problem = graph._gtsam_problem(start)
    if problem.values.size() == 0:
        raise CollabSlamError("batch_optimize needs a graph with optimized nodes")
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(absolute_error_tol)
    chi2_initial = 2.0 * problem.graph.error(problem.values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(problem.graph, problem.values, params)
    c0, t0 = time.thread_time(), time.perf_counter()
    try:
        values = optimizer.optimize()
    except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException and kin
        raise CollabSlamError(f"batch LM failed: {exc}") from exc
    wall_ms = (time.perf_counter() - t0) * 1e3
    cpu_ms = (time.thread_time() - c0) * 1e3
    result = BatchResult(
        poses=graph._split(values),
        wall_ms=wall_ms,
        cpu_ms=cpu_ms,
        chi2_initial=chi2_initial,
        chi2=2.0 * problem.graph.error(values),
        iterations=optimizer.iterations(),
    )
    logger.debug(
        "batch LM: %d factors, %d iterations, chi2 %.4g -> %.4g, %.1f ms",
        problem.graph.size(),
        result.iterations,
        chi2_initial,
        result.chi2,
        wall_ms,
    )
    return result
