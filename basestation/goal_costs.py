"""The terms of a frontier's cost beyond eq. 3's distance, heading and previous goal
(`ExplorationManager._goals`): its information, whose ground it is, whether another
robot will see it first, and whose tour it is on (`tour_shares`)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from basestation.frontier_tours import minmax_tours
from basestation.goal_assigner import own_ground
from basestation.visibility import seen_from, unknown_in_view, viewpoints
from common.map_io import GridMap

if TYPE_CHECKING:
    from basestation.exploration import ExplorationManager

log = logging.getLogger("basestation.exploration")


def tour_shares(
    offset: NDArray[np.float64], D_all: NDArray[np.float64], between: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """(robots, frontiers) True where the frontier is on the robot's tour
    (`minmax_tours`): every robot (`D_all`'s rows) from where it will be free, after
    `offset` m (a flying robot: the rest of its way to its goal)."""
    tours, lengths = minmax_tours(offset, D_all, between)
    on = np.zeros(D_all.shape, dtype=bool)
    for k, t in enumerate(tours):
        on[k, t] = True
    log.debug("tours %s: %s m", tours, np.round(lengths, 1).tolist())
    return on


def frontier_costs(
    ex: ExplorationManager,
    grid: GridMap,
    F: NDArray[np.float64],
    D_all: NDArray[np.float64],
    rows: list[int],
    busy: list[NDArray[np.float64]],
    flying: list[str],
    P: dict[str, NDArray[np.float64]],
    between: NDArray[np.float64] | None = None,
    offset: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
    """(distances (robots to plan, frontiers) with the per-robot terms added, the
    per-frontier costs for every robot, (robots to plan, frontiers) True where the
    frontier is on another robot's tour (None: no tours)): `D_all` travel distances
    from every robot (a flying one: from its goal) to the frontiers `F`, `rows` the
    robots to plan in it; `busy` the goals of the robots `flying` (and those taken), `P`
    every pose; `between` the travel distances between the frontiers and `offset` how
    far each robot still flies to its goal (tours, when both are given)."""
    D = D_all[rows]  # a frontier right next to a robot lies in its blind sector or in
    # another's shadow: it goes once the robot turns or the other moves, not worth a trip
    D = np.where(D < ex.near_frontier_m, D + ex.near_frontier_cost_m, D)
    D -= ex.w_own * own_ground(D_all, D, rows, ex.own_cap_m)  # closer to it than others
    gain = unknown_in_view(grid, F, ex.gain_radius_m) if ex.w_gain > 0.0 else None
    seen = np.zeros(len(F), dtype=bool)
    if ex.seen_cost_m > 0.0 and flying:  # in sight of another robot's way there
        for r in (r for r in flying if r in P):
            points, headings = viewpoints(ex._remaining(r, P[r]), 0.5)
            fov = np.radians(ex.seen_fov_deg)
            seen |= seen_from(grid, points, headings, F, ex.seen_range_m, fov)
    others = None
    if between is not None and offset is not None and len(D_all) > 1:
        others = ~tour_shares(offset, D_all, between)[rows]
    if gain is not None:  # a door into an unexplored room before a far pocket
        short = np.clip(ex.gain_full_m2 - gain, 0.0, None)  # m^2
        D = D + ex.w_gain * short[None, :] * np.clip(D / ex.gain_near_m, 0.0, 1.0)
    spread = np.zeros(len(F))
    for g in busy:  # frontiers near where another robot is heading: it will see them
        spread += ex.w_spread * np.maximum(0.0, ex.spread_radius_m - np.hypot(*(F - g).T))
    if seen.any():  # ... or in sight of its way there
        spread += ex.seen_cost_m * seen
        log.debug("in sight of %s's way: %s", flying, np.round(F[seen], 1).tolist())
    return D, spread, others
