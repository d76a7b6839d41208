"""Scan matching against a submap, on scans ray-cast exactly in synthetic worlds.

The worlds are line segments in the local frame. A 1081-beam, 270 deg, 30 m laser
(Hokuyo UTM-30LX) is cast against them with seeded 1 cm range noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.correlative_matcher import RealTimeCorrelativeMatcher
from agent.grid_refiner import CeresLikeRefiner, _normal_equations, refine
from agent.probability_grid import ProbabilityGrid
from agent.scan_matcher import ScanMatcher, match
from agent.submaps import ActiveSubmaps, Submap
from agent.voxel_filter import adaptive_voxel_filter, voxel_filter
from common.errors import CollabSlamError, ConfigError
from common.geometry import se2_between, se2_compose

BEAMS = 1081
FOV = math.radians(270.0)
MAX_RANGE = 30.0
NOISE = 0.01  # m, range noise


def _box(cx: float, cy: float, w: float, h: float, yaw: float) -> list[list[float]]:
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)]
    pts = [(cx + c * x - s * y, cy + s * x + c * y) for x, y in corners]
    return [[*pts[i], *pts[(i + 1) % 4]] for i in range(4)]


def _polygon(vertices: list[tuple[float, float]]) -> list[list[float]]:
    n = len(vertices)
    return [[*vertices[i], *vertices[(i + 1) % n]] for i in range(n)]


# An L-shaped room with a niche, and four pieces of clutter.
ROOM = np.array(
    _polygon([(-4, -3), (6, -3), (6, 1), (8, 1), (8, 5), (1, 5), (1, 4), (-4, 4)])
    + _box(2.0, 2.0, 0.6, 0.4, 0.3)
    + _box(-2.0, -1.5, 0.5, 0.5, 0.7)
    + _box(4.5, -1.0, 1.0, 0.3, -0.2)
    + _box(6.5, 3.5, 0.4, 0.8, 0.0)
)
# A straight corridor, 2 m wide, far longer than the laser's range.
CORRIDOR = np.array([[-200.0, -1.0, 200.0, -1.0], [-200.0, 1.0, 200.0, 1.0]])

T_ROOM = np.array([0.5, 0.3, 0.2])  # first scan, local frame


def cast(segments: np.ndarray, T_local_sensor: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(BEAMS, 2) returns in the sensor frame; NaN rows for beams with no return."""
    beam = -FOV / 2 + np.arange(BEAMS) * FOV / (BEAMS - 1)
    a = beam + T_local_sensor[2]
    d = np.stack([np.cos(a), np.sin(a)], axis=1)
    s0, e = segments[:, :2], segments[:, 2:] - segments[:, :2]
    w = s0[None] - T_local_sensor[:2]
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / den
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(ok, t, np.inf).min(axis=1) + rng.normal(0.0, NOISE, BEAMS)
    r[r > MAX_RANGE] = np.nan
    return np.stack([r * np.cos(beam), r * np.sin(beam)], axis=1)


def _submap_of(segments: np.ndarray, T_local_sensor: np.ndarray, seed: int) -> Submap:
    submaps = ActiveSubmaps(resolution=0.05, scans_per_submap=10)
    submaps.insert(T_local_sensor, cast(segments, T_local_sensor, np.random.default_rng(seed)))
    submap = submaps.matching_submap()
    assert submap is not None
    return submap


@pytest.fixture(scope="module")
def room_submap() -> Submap:
    return _submap_of(ROOM, T_ROOM, seed=0)


def assert_pose_close(T_a: np.ndarray, T_b: np.ndarray, tol_m: float, tol_deg: float) -> None:
    err = se2_between(T_a, T_b)
    assert math.hypot(err[0], err[1]) < tol_m, f"translation error {err[:2]} m"
    assert abs(math.degrees(err[2])) < tol_deg, f"yaw error {math.degrees(err[2])} deg"


# (dx m, dy m, dyaw deg) of the true pose from the prediction (the first scan's pose)
OFFSETS = [
    (0.3, 0.0, 10.0),
    (0.0, -0.3, -10.0),
    (0.21, 0.21, 5.0),
    (-0.2, 0.15, -7.0),
    (0.1, -0.25, 10.0),
    (-0.3, -0.05, 0.0),
]


@pytest.mark.parametrize("case", range(len(OFFSETS)))
def test_recovers_offsets_up_to_30cm_and_10deg(room_submap: Submap, case: int) -> None:
    dx, dy, dyaw = OFFSETS[case]
    truth = se2_compose(T_ROOM, [dx, dy, math.radians(dyaw)])
    points = adaptive_voxel_filter(cast(ROOM, truth, np.random.default_rng(100 + case)))
    result = ScanMatcher().match(room_submap.grid, points, room_submap.to_submap(T_ROOM))
    assert result.converged
    assert_pose_close(room_submap.to_local(result.pose), truth, 0.01, 0.2)
    assert result.score > room_submap.grid.min_probability
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0.0)


def test_module_match_uses_defaults(room_submap: Submap) -> None:
    truth = se2_compose(T_ROOM, [0.1, 0.1, 0.05])
    points = adaptive_voxel_filter(cast(ROOM, truth, np.random.default_rng(7)))
    result = match(room_submap.grid, points, room_submap.to_submap(T_ROOM))
    assert_pose_close(room_submap.to_local(result.pose), truth, 0.01, 0.2)


def test_branch_and_bound_equals_exhaustive_search(room_submap: Submap) -> None:
    grid = room_submap.grid
    step, res = math.radians(0.5), grid.resolution
    matcher = RealTimeCorrelativeMatcher(
        linear_window=0.15, angular_window=math.radians(3.0), angular_step=step
    )
    truth = room_submap.to_submap(se2_compose(T_ROOM, [0.07, -0.04, 0.02]))
    scan = cast(ROOM, room_submap.to_local(truth), np.random.default_rng(3))
    points = adaptive_voxel_filter(scan)
    pred = np.zeros(3)
    found = matcher.match(grid, points, pred)
    assert found is not None

    # Every lattice pose, scored as the matcher does: uint8 probabilities, unknown
    # 0.5, Cartographer's penalty exp(-(w_t |t| + w_r |yaw|)^2).
    p = np.where(grid.data > 0, grid.data, np.float32(0.5))
    q = np.floor(p * np.float32(255.0) + np.float32(0.5)).astype(np.float64) / 255.0
    win = 3
    best = -1.0
    for k in range(-6, 7):
        yaw = pred[2] + k * step
        c, s = math.cos(yaw), math.sin(yaw)
        px, py = points[:, 0] * (1.0 / res), points[:, 1] * (1.0 / res)
        u0, v0 = (pred[:2] - grid.origin_xy) * (1.0 / res)
        ix = np.floor(c * px - s * py + u0).astype(int)
        iy = np.floor(s * px + c * py + v0).astype(int)
        for dx in range(-win, win + 1):
            for dy in range(-win, win + 1):
                score = q[iy + dy, ix + dx].mean()
                cost = 0.1 * math.hypot(dx, dy) * res + 0.1 * abs(k * step)
                best = max(best, score * math.exp(-cost * cost))
    assert found.score == pytest.approx(best, abs=1e-9)


def test_candidates_are_the_distinct_places_a_scan_fits() -> None:
    # Two copies of the room 12 m apart (walls of both, seen from both): a scan of
    # one fits both. `match` keeps one; `candidates` finds both, best first, and the
    # best equals `match`'s.
    shift = np.array([12.0, 0.0, 0.0])
    twin = np.concatenate([ROOM, ROOM + np.tile(shift[:2], 2)])
    submaps = ActiveSubmaps(resolution=0.05, scans_per_submap=10)
    rng = np.random.default_rng(5)
    for T in (T_ROOM, T_ROOM + shift):
        submaps.insert(T, cast(twin, T, rng))
    submap = submaps.matching_submap()
    assert submap is not None
    truth = se2_compose(T_ROOM, [0.1, -0.1, 0.03])
    points = adaptive_voxel_filter(cast(twin, truth, rng))
    matcher = RealTimeCorrelativeMatcher(
        linear_window=8.0,
        angular_window=math.radians(5.0),
        translation_delta_cost_weight=0.0,  # no pull toward the prediction, between the two
        rotation_delta_cost_weight=0.0,
    )
    pred = submap.to_submap(T_ROOM + 0.5 * shift)
    best = matcher.match(submap.grid, points, pred)
    found = matcher.candidates(submap.grid, points, pred, 3, 1.0, math.radians(10.0))
    assert best is not None and len(found) >= 2
    assert np.array_equal(found[0][0], best.pose) and found[0][1] == best.score
    assert [s for _, s in found] == sorted((s for _, s in found), reverse=True)
    places = [submap.to_local(p) for p, _ in found[:2]]
    for T in (truth, truth + shift):
        assert min(float(np.hypot(*(p - T)[:2])) for p in places) < 0.1
    with pytest.raises(ConfigError):
        matcher.candidates(submap.grid, points, pred, 0, 1.0, 0.1)


def test_corridor_covariance_is_long_along_the_corridor() -> None:
    T0 = np.array([0.0, 0.1, 0.3])
    submap = _submap_of(CORRIDOR, T0, seed=1)
    truth = se2_compose(T0, [0.15, 0.05, 0.03])
    points = adaptive_voxel_filter(cast(CORRIDOR, truth, np.random.default_rng(2)))
    result = ScanMatcher().match(submap.grid, points, submap.to_submap(T0))
    yaw = submap.T_local_submap[2]
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    cov_local = R @ result.covariance[:2, :2] @ R.T  # corridor along local x
    assert cov_local[0, 0] > 20.0 * cov_local[1, 1]
    assert math.sqrt(cov_local[0, 0]) > 0.05  # m: of the order of the search window
    error_local = submap.to_local(result.pose) - truth
    assert abs(error_local[1]) < 0.01  # across the corridor: matched
    # Along it the scan says nothing: the pose stays at the prediction (remapping).
    assert submap.to_local(result.pose)[0] == pytest.approx(T0[0], abs=0.01)


@pytest.mark.parametrize(
    "points",
    [np.zeros((0, 2)), np.full((BEAMS, 2), np.nan), np.array([[1.0, 0.0], [np.nan, 2.0]])],
    ids=["empty", "all-nan", "one-point"],
)
def test_unusable_scans_are_not_converged(room_submap: Submap, points: np.ndarray) -> None:
    pred = np.array([0.05, -0.02, 0.01])
    result = ScanMatcher().match(room_submap.grid, points, pred)
    assert not result.converged
    assert result.iterations == 0
    np.testing.assert_array_equal(result.pose, pred)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0.0)


def test_bad_inputs_raise(room_submap: Submap) -> None:
    matcher = ScanMatcher()
    with pytest.raises(CollabSlamError):
        matcher.match(room_submap.grid, np.zeros((5, 3)), np.zeros(3))
    with pytest.raises(CollabSlamError):
        matcher.match(room_submap.grid, np.ones((5, 2)), [np.nan, 0.0, 0.0])
    with pytest.raises(CollabSlamError):
        matcher.match(ProbabilityGrid(0.05, (0.0, 0.0), (10, 10)), np.ones((5, 2)), np.zeros(3))
    with pytest.raises(CollabSlamError):
        refine(room_submap.grid, np.ones((2, 2)), np.zeros(3))


def test_refiner_gradient_matches_finite_differences(room_submap: Submap) -> None:
    grid = room_submap.grid
    points = adaptive_voxel_filter(cast(ROOM, T_ROOM, np.random.default_rng(5)))
    ox, oy = grid.origin_xy
    prior = np.array([0.01, -0.02, 0.03])

    def cost(pose: np.ndarray, b: np.ndarray) -> float:
        return _normal_equations(
            grid.data,
            0.5,
            ox,
            oy,
            grid.resolution,
            points,
            pose,
            prior,
            0.1,
            0.3,
            0.4,
            np.empty((3, 3)),
            b,
        )

    pose = np.array([0.012, 0.007, 0.004])
    gradient = np.empty(3)
    cost(pose, gradient)
    for k, h in enumerate([1e-6, 1e-6, 1e-7]):
        e = np.zeros(3)
        e[k] = h
        numeric = (cost(pose + e, np.empty(3)) - cost(pose - e, np.empty(3))) / (2 * h)
        assert gradient[k] == pytest.approx(numeric, rel=1e-4, abs=1e-8)


def test_refiner_alone_converges_from_a_close_start(room_submap: Submap) -> None:
    truth = se2_compose(T_ROOM, [0.02, -0.015, 0.01])
    points = adaptive_voxel_filter(cast(ROOM, truth, np.random.default_rng(9)))
    start = room_submap.to_submap(T_ROOM)
    result = CeresLikeRefiner().refine(room_submap.grid, points, start)
    assert result.converged
    assert_pose_close(room_submap.to_local(result.pose), truth, 0.01, 0.2)
    assert result.residual_variance > 0.0


def test_adaptive_voxel_filter() -> None:
    scan = cast(ROOM, T_ROOM, np.random.default_rng(4))
    finite = scan[np.isfinite(scan).all(axis=1)]
    out = adaptive_voxel_filter(scan, max_length=0.5, min_num_points=200, max_range=30.0)
    assert 200 <= len(out) < len(finite) // 2
    assert np.isin(out, finite).all()  # a subset of the input, nothing invented
    # Few points: all finite points in range come back, in order.
    few = np.array([[1.0, 0.0], [np.nan, 1.0], [40.0, 0.0], [1.01, 0.0]])
    np.testing.assert_array_equal(
        adaptive_voxel_filter(few, min_num_points=200, max_range=30.0),
        [[1.0, 0.0], [1.01, 0.0]],
    )
    # One point per voxel.
    kept = voxel_filter(finite, 0.2)
    keys = np.floor(kept / 0.2)
    assert len(np.unique(keys, axis=0)) == len(kept)
    assert len(np.unique(np.floor(finite / 0.2), axis=0)) == len(kept)


def test_voxel_filter_keeps_an_unbiased_point_of_each_voxel() -> None:
    # A scan's points come in beam order: keeping the first of each voxel would keep
    # its one end (here x at the voxel's lower edge) and turn the local SLAM's heading.
    line = np.column_stack([np.linspace(0.0, 10.0, 100_001)[:-1], np.full(100_000, 0.01)])
    for points in (line, line[::-1]):
        kept = voxel_filter(points, 0.1)
        assert len(kept) == 100
        where = kept[:, 0] / 0.1 - np.floor(kept[:, 0] / 0.1)  # 0..1 across its voxel
        assert abs(where.mean() - 0.5) < 0.1  # the first in order: ~0 (or ~1 reversed)
        np.testing.assert_array_equal(kept, voxel_filter(points, 0.1))  # reproducible
