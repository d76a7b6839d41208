"""Verification of loop-closure and inter-robot candidates by scan matching (seed 002 §1.1).

The base station's constraint builder asks: does the query scan (points in the body
frame b of a new node) really see the place around a target node (frame a)? And if
so, what is T_a_b and how sure are we? Conventions (same as `basestation.pose_graph`):
a pose `T_a_b = [x, y, yaw]` (m, m, rad) maps points from frame b into frame a.

1. `ScanVerifier.build_target` turns the target node's scans (already in frame a)
   into a `Target`, built once and reused for several queries: a likelihood field
   (each cell holds exp(-d^2 / 2 score_sigma^2), d = distance to the nearest target
   point, Olson 2009), a KD-tree, per-point line normals (PCA over neighbours) and,
   when the scans' origins are given, a probability grid of the space they saw free.
2. `verify` searches the window around the guess with Cartographer's branch and
   bound (`agent.correlative_matcher.RealTimeCorrelativeMatcher`, on the field), then
   refines with point-to-line ICP (Censi 2008, CSM): residual n_j . (R q_i + t - p_j)
   against the nearest target point's line; corners and clutter (no line) use
   point-to-point residuals. With the target's scan origins, a pair is used only when
   the target point's surface, as its scan saw it, faces the sensor that saw the query
   point (`facing_correspondences`): the two faces of a 0.1 m wall are 0.1 m apart, and
   pairing one with the other pulled matches through walls toward the target (in the
   simulator's missions, matches came out ~1 % of the distance between their nodes
   short: 2-4 cm; with the test, 0.6 cm rms).
3. A match is accepted only if ICP converged (without sliding more than
   `max_corr_dist` from the search's pose), the score (mean field value of the query
   points at the refined pose) >= `min_score`, the overlap (fraction of query points
   with a target point within `max_corr_dist`) >= `min_overlap`, and little of the
   evidence contradicts free space: at most `max_beam_violation` of the query's beams
   passed through a target point (the query's sensor is the origin of frame b), and,
   with origins, at most `max_free_space_violation` of the query points fall in cells
   the target's beams passed through. Score and overlap alone accept many wrong
   matches between rectangular rooms (in the tests, 13 of 20 global searches of a scan
   against another room); the free-space tests reject them. With the target's origins
   both tests read the target's probability grid, so that a stray point in one target
   scan (a person, noise) is outvoted by the scans that saw its cell free; the beam
   test then asks whether a query beam crosses a cell the target saw occupied. The
   thresholds allow for the people and doors of real logs: on ACES, 9-11 % of a
   correct match's points fall in space the target saw free.

Covariance (3x3 over [x, y, yaw], in the body frame b: gtsam's Pose2 tangent space,
what `PoseGraph.add_constraint` expects): the Gauss-Newton information of the ICP
residuals divided by `covariance_scale` times their variance, sigma^2 =
max(sum r^2 / (n - 3), min_residual_sigma^2), plus a prior information of the search
windows (1/window^2). Noise in the normals gives a flat direction (along a corridor) a
small but spurious information; an eigen-direction of the (length-scaled) information
carrying less than `degeneracy_threshold` of one residual's worth per residual is
treated as unconstrained (Zhang & Singh 2016): ICP does not move along it and it keeps
the window prior only. So a corridor reads as metres along its axis and millimetres
across. The residuals are not independent (every query point sees the same noisy
target), so the raw covariance is optimistic: on the synthetic rooms of the tests its
NEES was ~8 for 3 dof; `covariance_scale` = 3 brings it to ~2.5.

`global_search` (Cartographer's global localization, to anchor a robot whose start
pose is unknown) runs the branch and bound over the whole target and all headings on a
coarse field (`global_resolution`, cached in the target), then `verify`'s search,
refinement and tests in a small window around each of the best few coarse optima.

A `Target` caches the correlative pyramid: use one per thread.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from agent.correlative_matcher import RealTimeCorrelativeMatcher
from agent.probability_grid import ProbabilityGrid
from agent.voxel_filter import adaptive_voxel_mask, finite_points, voxel_mask
from basestation.free_space import (
    beam_violation_grid,
    beam_violation_points,
    free_space_grid,
    target_free_violation,
)
from basestation.match_target import (
    FIELD_FLOOR,
    LikelihoodField,
    Target,
    facing_correspondences,
    facing_normals,
    icp_normal_equations,
    line_normals,
)
from common.errors import CollabSlamError, ConfigError, TooFewPoints
from common.geometry import se2_transform_points, wrap_angle

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class VerifiedMatch:
    """An accepted match of a query scan (frame b) against a target (frame a).

    `T_a_b` [x, y, yaw] (m, rad); `covariance` 3x3 over [x, y, yaw] in frame b (see
    module doc), never singular; `score` mean likelihood-field value in [0, 1] of the
    query points at `T_a_b`; `overlap` fraction of query points with a target point
    within `max_corr_dist` (m); `icp_rmse` (m) of the ICP residuals at the solution;
    `iterations` of ICP.
    """

    T_a_b: FloatArray
    covariance: FloatArray
    score: float
    overlap: float
    icp_rmse: float
    iterations: int


class ScanVerifier:
    """Correlative search + point-to-line ICP + acceptance tests (see module doc).

    `resolution` (m) of the score field; `linear_window` (m) and `angular_window` (rad)
    half-widths of the search around the guess (default windows of `verify`);
    `min_score`, `min_overlap` acceptance thresholds; `max_corr_dist` (m) ICP
    correspondence and overlap distance; `icp_max_iterations`; `score_sigma` (m) width of
    the field around target points (default 2 cells); `icp_tolerance_m` / `_rad` step
    sizes that count as converged; `min_residual_sigma` (m) floor of the residual sigma
    in the covariance; `degeneracy_threshold` (see module doc); `normal_neighbors` and
    `normal_radius` (m) for the line fits; `query_min_points` and `query_max_voxel` (m)
    for the adaptive voxel filter applied to queries; `translation_delta_cost_weight`
    (1/m) and `rotation_delta_cost_weight` (1/rad): the matcher's tie-breaker toward the
    guess (a corridor's plateau resolves to the point nearest the guess);
    `pyramid_margin_m` (m) margin of the cached pyramid around a query;
    `max_beam_violation` (fraction of the query's beams that cross a target point),
    `max_free_space_violation` (fraction of query points in the target's free space) and
    `free_space_margin` (m) for the free-space tests; `global_resolution` (m) of the
    coarse field of `global_search`, `global_separation_m` / `_rad` between the coarse
    optima it tries;
    `covariance_scale` inflates the ICP covariance (module doc); `facing_test` pairs
    only points that see the same side of a surface (module doc); `max_target_cells`
    bounds a target's grid (a stray point kilometres away must not allocate gigabytes).
    """

    def __init__(
        self,
        resolution: float = 0.05,
        linear_window: float = 2.0,
        angular_window: float = math.radians(30.0),
        min_score: float = 0.55,
        min_overlap: float = 0.5,
        max_corr_dist: float = 0.2,
        icp_max_iterations: int = 30,
        *,
        score_sigma: float | None = None,
        icp_tolerance_m: float = 2e-4,
        icp_tolerance_rad: float = 2e-4,
        min_residual_sigma: float = 0.01,
        degeneracy_threshold: float = 0.01,
        normal_neighbors: int = 16,
        normal_radius: float = 1.0,
        max_flatness: float = 0.1,
        query_min_points: int = 300,
        query_max_voxel: float = 0.5,
        translation_delta_cost_weight: float = 0.1,
        rotation_delta_cost_weight: float = 0.1,
        pyramid_margin_m: float = 2.0,
        max_free_space_violation: float = 0.15,
        max_beam_violation: float = 0.2,
        free_space_margin: float = 0.3,
        global_resolution: float = 0.2,
        global_separation_m: float = 1.0,
        global_separation_rad: float = 0.35,
        covariance_scale: float = 3.0,
        facing_test: bool = True,
        max_target_cells: int = 16_000_000,
    ) -> None:
        if not (math.isfinite(resolution) and resolution > 0.0):
            raise ConfigError(f"resolution must be > 0 m, got {resolution}")
        if not (linear_window >= 0.0 and angular_window >= 0.0):
            raise ConfigError("search windows must be >= 0")
        if not (0.0 <= min_score <= 1.0 and 0.0 <= min_overlap <= 1.0):
            raise ConfigError("min_score and min_overlap must be in [0, 1]")
        if not max_corr_dist > 0.0 or icp_max_iterations < 1:
            raise ConfigError("need max_corr_dist > 0 m and icp_max_iterations >= 1")
        self.resolution = float(resolution)
        self.linear_window = float(linear_window)
        self.angular_window = float(angular_window)
        self.min_score = float(min_score)
        self.min_overlap = float(min_overlap)
        self.max_corr_dist = float(max_corr_dist)
        self.icp_max_iterations = int(icp_max_iterations)
        self.score_sigma = float(score_sigma) if score_sigma else 2.0 * self.resolution
        self.icp_tolerance_m = float(icp_tolerance_m)
        self.icp_tolerance_rad = float(icp_tolerance_rad)
        self.min_residual_sigma = float(min_residual_sigma)
        self.degeneracy_threshold = float(degeneracy_threshold)
        self.normal_neighbors = int(normal_neighbors)
        self.normal_radius = float(normal_radius)
        self.max_flatness = float(max_flatness)
        self.query_min_points = int(query_min_points)
        self.query_max_voxel = float(query_max_voxel)
        self.translation_delta_cost_weight = float(translation_delta_cost_weight)
        self.rotation_delta_cost_weight = float(rotation_delta_cost_weight)
        self.pyramid_margin_m = float(pyramid_margin_m)
        self.max_free_space_violation = float(max_free_space_violation)
        self.max_beam_violation = float(max_beam_violation)
        self.free_space_margin = float(free_space_margin)
        self.global_resolution = float(global_resolution)
        self.global_separation_m = float(global_separation_m)
        self.global_separation_rad = float(global_separation_rad)
        self.covariance_scale = float(covariance_scale)
        self.facing_test = bool(facing_test)
        self.max_target_cells = int(max_target_cells)

    # ----- targets ----------------------------------------------------------------
    def build_target(
        self, scans_in_a: list[np.ndarray], origins_in_a: list[ArrayLike] | None = None
    ) -> Target:
        """A `Target` from (Ni, 2) point arrays already in frame a (m); non-finite rows
        are dropped. `origins_in_a`: optional sensor position [x, y] (or pose
        [x, y, yaw]) of each scan in frame a; with them the target also knows its free
        space and rejects queries whose points fall in it. Raises CollabSlamError with
        fewer than 3 finite points or a wrong number of origins."""
        parts = [finite_points(s, "scan") for s in scans_in_a]
        pts = np.concatenate(parts) if parts else np.zeros((0, 2))
        keep = voxel_mask(pts, self.resolution) if len(pts) else np.zeros(0, bool)
        pts = pts[keep]
        if len(pts) < 3:
            raise TooFewPoints(f"a target needs >= 3 finite points, got {len(pts)}")
        span = np.ptp(pts, axis=0) / self.resolution
        if (span[0] + 100) * (span[1] + 100) > self.max_target_cells:
            raise CollabSlamError(
                f"target spans {np.ptp(pts, axis=0)} m: more than {self.max_target_cells} cells"
            )
        free_space = None
        if origins_in_a is not None:
            if len(origins_in_a) != len(parts):
                raise CollabSlamError(f"got {len(origins_in_a)} origins for {len(parts)} scans")
            free_space = free_space_grid(self.resolution, parts, origins_in_a)
        tree = cKDTree(pts)
        normals, has_line = line_normals(
            pts, tree, self.normal_neighbors, self.normal_radius, self.max_flatness
        )
        facing = None
        if origins_in_a is not None and self.facing_test:
            at = [np.asarray(o, dtype=np.float64)[:2] for o in origins_in_a]
            sensors = np.concatenate(
                [np.broadcast_to(o, p.shape) for o, p in zip(at, parts, strict=True)]
            )[keep]
            facing = facing_normals(pts, sensors, normals, has_line)
        extent = np.concatenate([pts.min(axis=0), pts.max(axis=0)])
        return Target(
            pts,
            normals,
            has_line,
            tree,
            LikelihoodField(pts, self.resolution, self.score_sigma),
            extent,
            free_space,
            facing,
        )

    # ----- verification -------------------------------------------------------------
    def verify(
        self,
        target: Target,
        query_points_b: ArrayLike,
        T_a_b_guess: ArrayLike,
        linear_window: float | None = None,
        angular_window: float | None = None,
        sensor_points: ArrayLike | None = None,
        query_sensors_b: ArrayLike | None = None,
    ) -> VerifiedMatch | None:
        """Match the query (M, 2 points in frame b, m) against `target` within the
        windows (m, rad; default the verifier's; >= pi: all headings) around the guess
        T_a_b. None when nothing passes the acceptance tests (module doc).
        `sensor_points`: the part of the query seen by one scan from the origin of b,
        for the beam test (default: the whole query; pass it when the query merges
        scans from several poses). `query_sensors_b`: (M, 2) the sensor position in
        frame b each query point was seen from (default: b's origin), for the test of
        which side of a surface each pair sees (`facing_correspondences`)."""
        guess = np.asarray(T_a_b_guess, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(guess)):
            raise CollabSlamError(f"T_a_b_guess must be finite, got {guess}")
        lw = self.linear_window if linear_window is None else float(linear_window)
        aw = self.angular_window if angular_window is None else float(angular_window)
        aw = min(aw, math.pi)
        raw = finite_points(query_points_b, "query_points_b")
        beams = raw if sensor_points is None else finite_points(sensor_points, "sensor_points")
        q, qs = self._query(query_points_b, query_sensors_b)
        if len(q) < 3:
            return None
        return self._search(target, beams, q, qs, guess, lw, aw, 1.0, self.min_score)

    def global_search(
        self,
        target: Target,
        query_points_b: ArrayLike,
        min_score: float | None = None,
        sensor_points: ArrayLike | None = None,
        candidates: int = 1,
        query_sensors_b: ArrayLike | None = None,
    ) -> VerifiedMatch | None:
        """Search the whole target (every position inside its extent, all headings) for
        the pose of the query (M, 2 points in frame b); same acceptance tests, with
        `min_score` (default the verifier's); `sensor_points`, `query_sensors_b` as in
        `verify`. The
        `candidates` best coarse optima (distinct places, `global_separation_m` or
        `global_separation_rad` apart) are each refined and tested; the best-scoring
        one that passes is returned, None when none does."""
        raw = finite_points(query_points_b, "query_points_b")
        beams = raw if sensor_points is None else finite_points(sensor_points, "sensor_points")
        q, qs = self._query(query_points_b, query_sensors_b)
        if len(q) < 3:
            return None
        lo, hi = target.extent[:2], target.extent[2:]
        centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.0])
        window = 0.5 * float(np.max(hi - lo)) + self.global_resolution
        ms = self.min_score if min_score is None else float(min_score)
        coarse = target._cache.get("coarse_field")
        if not isinstance(coarse, LikelihoodField):
            sigma = max(self.score_sigma, self.global_resolution)
            coarse = LikelihoodField(target.points, self.global_resolution, sigma)
            target._cache["coarse_field"] = coarse
        m = self._matcher(target, "global", window, math.pi, 0.0)
        found = m.candidates(
            cast(ProbabilityGrid, coarse),
            q,
            centre,
            candidates,
            self.global_separation_m,
            self.global_separation_rad,
        )
        # Fine search around each coarse optimum: a few coarse cells and angular steps.
        d_max = float(np.sqrt(np.einsum("ij,ij->i", q, q).max()))
        step = math.acos(max(1.0 - self.global_resolution**2 / (2.0 * d_max**2), -1.0))
        lw, aw = 2.0 * self.global_resolution, max(3.0 * step, 0.02)
        passed = [
            r for p, _ in found if (r := self._search(target, beams, q, qs, p, lw, aw, 0.0, ms))
        ]
        if len(passed) > 1:
            logger.debug("global search: %d of %d coarse optima pass", len(passed), len(found))
        return max(passed, key=lambda r: r.score, default=None)

    # ----- internals ----------------------------------------------------------------
    def _query(
        self, points_b: ArrayLike, sensors_b: ArrayLike | None
    ) -> tuple[FloatArray, FloatArray]:
        """The query points matched (finite, thinned by voxel filters; the caller checked
        their shape) and where each was seen from (frame b; default its origin)."""
        p = np.asarray(points_b, dtype=np.float64).reshape(-1, 2)
        s = np.zeros_like(p) if sensors_b is None else np.asarray(sensors_b, dtype=np.float64)
        if s.shape != p.shape:
            raise CollabSlamError(f"{len(p)} query points but sensors of shape {s.shape}")
        ok = np.isfinite(p.sum(axis=1) + s.sum(axis=1))
        p, s = p[ok], s[ok]
        keep = np.flatnonzero(voxel_mask(p, 0.5 * self.resolution))
        keep = keep[adaptive_voxel_mask(p[keep], self.query_max_voxel, self.query_min_points)]
        return p[keep], s[keep]

    def _search(
        self,
        target: Target,
        beams: FloatArray,
        q: FloatArray,
        qs: FloatArray,
        guess: FloatArray,
        lw: float,
        aw: float,
        penalty_scale: float,
        min_score: float,
    ) -> VerifiedMatch | None:
        m = self._matcher(target, "fine", lw, aw, penalty_scale)
        corr = m.match(cast(ProbabilityGrid, target.field), q, guess)
        if corr is None:
            return None
        rho = max(float(np.sqrt(np.mean(np.einsum("ij,ij->i", q, q)))), self.resolution)
        pose, iterations, converged = self._icp(target, q, qs, corr.pose, rho)
        if not converged:
            logger.debug("ICP did not converge from %s", corr.pose)
            return None
        if np.hypot(*(pose[:2] - corr.pose[:2])) > self.max_corr_dist:
            logger.debug("ICP slid %s -> %s: rejected", corr.pose, pose)
            return None
        score = target.field.score(q, pose)
        moved = se2_transform_points(pose, q)
        _, idx = target.tree.query(moved, distance_upper_bound=self.max_corr_dist)
        overlap = float(np.mean(idx < len(target.points)))
        if score < min_score or overlap < self.min_overlap:
            logger.debug("candidate rejected: score %.3f, overlap %.3f", score, overlap)
            return None
        if target.free_space is not None:
            beam_violation = beam_violation_grid(
                target.free_space, beams, pose, self.free_space_margin
            )
        else:
            beam_violation = beam_violation_points(target, beams, pose, self.free_space_margin)
        if beam_violation > self.max_beam_violation:
            logger.debug(
                "candidate rejected: %.3f of the beams cross target points", beam_violation
            )
            return None
        if target.free_space is not None:
            violation = target_free_violation(target, moved, idx)
            if violation > self.max_free_space_violation:
                logger.debug(
                    "candidate rejected: %.3f of the points in target free space", violation
                )
                return None
        H = np.empty((3, 3))
        g = np.empty(3)
        idx = facing_correspondences(target, moved, se2_transform_points(pose, qs), idx)
        ss, n_res = icp_normal_equations(
            q, pose, idx, target.points, target.normals, target.has_line, H, g
        )
        rmse = math.sqrt(ss / max(n_res, 1))
        cov = self._covariance(H, ss, n_res, pose, rho, lw, aw)
        return VerifiedMatch(pose, cov, float(score), overlap, rmse, iterations)

    def _matcher(
        self, target: Target, key: str, lw: float, aw: float, penalty_scale: float
    ) -> RealTimeCorrelativeMatcher:
        """The target's matcher for `key`, set to these windows (m, rad)."""
        m = target._cache.get(key)
        if not isinstance(m, RealTimeCorrelativeMatcher):
            m = RealTimeCorrelativeMatcher(
                pyramid_margin_m=self.pyramid_margin_m, unknown_probability=FIELD_FLOOR
            )
            target._cache[key] = m
        m.linear_window, m.angular_window, m.min_score = lw, aw, 0.0
        m.translation_delta_cost_weight = penalty_scale * self.translation_delta_cost_weight
        m.rotation_delta_cost_weight = penalty_scale * self.rotation_delta_cost_weight
        return m

    def _icp(
        self, target: Target, q: FloatArray, qs: FloatArray, pose0: FloatArray, rho: float
    ) -> tuple[FloatArray, int, bool]:
        """Point-to-line ICP from pose0: (pose, iterations, converged). Converged: a step
        below the tolerances, or a 2-cycle of steps (a few correspondences flipping)
        that small, which ends at its midpoint."""
        pose = pose0.copy()
        H = np.empty((3, 3))
        g = np.empty(3)
        n_t = len(target.points)
        tol = np.array([self.icp_tolerance_m, self.icp_tolerance_m, self.icp_tolerance_rad])
        prev = np.full(3, np.inf)
        for it in range(1, self.icp_max_iterations + 1):
            moved = se2_transform_points(pose, q)
            _, idx = target.tree.query(moved, distance_upper_bound=self.max_corr_dist)
            idx = facing_correspondences(target, moved, se2_transform_points(pose, qs), idx)
            _, n_res = icp_normal_equations(
                q, pose, idx, target.points, target.normals, target.has_line, H, g
            )
            if n_res < 6 or int(np.sum(idx < n_t)) < 3:
                return pose, it, False
            # Gauss-Newton step in the well-constrained directions only: along a
            # degenerate one (a corridor's axis) the pose stays where the search put it.
            delta = -self._truncated(H, n_res, rho)[1] @ g
            if np.all(np.abs(delta + prev) < tol) and np.all(np.abs(delta) < 10.0 * tol):
                # a 2-cycle: a few correspondences flip between two target points
                pose = pose + 0.5 * delta
                pose[2] = float(wrap_angle(pose[2]))
                return pose, it, True
            pose = pose + delta
            pose[2] = float(wrap_angle(pose[2]))
            if np.all(np.abs(delta) < tol):
                return pose, it, True
            prev = delta
        return pose, self.icp_max_iterations, False

    def _covariance(
        self,
        H: FloatArray,
        ss: float,
        n_res: int,
        pose: FloatArray,
        rho: float,
        lw: float,
        aw: float,
    ) -> FloatArray:
        """Covariance of T_a_b in frame b (module doc)."""
        sigma2 = max(ss / max(n_res - 3, 1), self.min_residual_sigma**2)
        info = self._truncated(H, n_res, rho)[0] / (sigma2 * self.covariance_scale)
        prior = np.diag([max(lw, self.resolution) ** -2] * 2 + [max(aw, 1e-3) ** -2])
        cov_a = np.linalg.inv(info + prior)  # additive [x, y, yaw] in frame a
        c, s = math.cos(pose[2]), math.sin(pose[2])
        G = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # frame a -> frame b
        cov = G @ cov_a @ G.T
        return 0.5 * (cov + cov.T)

    def _truncated(self, H: FloatArray, n_res: int, rho: float) -> tuple[FloatArray, FloatArray]:
        """H without its degenerate eigen-directions, and the pseudo-inverse of that.

        Yaw is scaled by `rho` (m, the RMS radius of the query) so that one unit of each
        coordinate moves the points by about one metre; an eigenvalue of the scaled
        H / n_res below `degeneracy_threshold` marks a direction as unconstrained."""
        S = np.diag([1.0, 1.0, 1.0 / rho])
        n = max(n_res, 1)
        lam, vec = np.linalg.eigh(S @ H @ S / n)
        keep = lam >= self.degeneracy_threshold
        vk, lk = vec[:, keep], lam[keep] * n
        S_inv = np.diag([1.0, 1.0, rho])
        return S_inv @ (vk * lk) @ vk.T @ S_inv, S @ (vk / lk) @ vk.T @ S
