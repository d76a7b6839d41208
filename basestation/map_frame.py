"""Which robot defines `map` when no start is known, and whether the others can join it.

With unknown starts one robot defines `map`: with a scenario its first robot (its start
is the one known, basestation/roster.py `scenario_starts`), without one
`basestation.map_frame_robot` or else the first robot to send (`defines_map`). The
others float until verified matches join them to it. A join needs matches seen from
places of each robot at least `merge_min_spread_m` apart (loop_closure_manager.py
`_spread_enough`): while the map is one robot's whose keyframes are not that far apart
(it never took off, or stays on the ground, or its agent died after its first
keyframe), or no robot's at all (its agent never started), no floating robot can ever
be joined, and the map holds only that robot's few scans. `MapFrame.check` notices
this once a floating robot has flown that far and logs a warning naming the robots
left off the map and why: at most once per `WARN_PERIOD_S` (wall), the first that
long after the first keyframe, and once more at the end. `stats` is basestation.json's
``map_frame`` (summary.json: ``unjoined_robots``, ``unjoinable_reason``).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import ConvexHull

if TYPE_CHECKING:
    from basestation.global_slam import GlobalSlam

log = logging.getLogger(__name__)

WARN_PERIOD_S = 30.0  # s wall between warnings
_SPREAD_CELL_M = 0.05  # m: positions rounded to this before the exact pairwise spread


def spread_m(xy: np.ndarray, enough: float = np.inf) -> float:
    """Largest distance between two of the (n, 2) positions (a robot's keyframes), over
    the corners of their convex hull (positions rounded to 5 cm first: a robot hovering
    for hours has thousands in one spot); the longest side of their bounding box, a
    lower bound, once that is `enough` already."""
    if len(xy) < 2:
        return 0.0
    side = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    if side >= enough:
        return side
    pts = np.unique(np.rint(xy / _SPREAD_CELL_M), axis=0) * _SPREAD_CELL_M
    if len(pts) > 3:  # (QJ: collinear positions too)
        pts = pts[ConvexHull(pts, qhull_options="QJ").vertices]
    d = np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1))
    return max(side, float(d.max()))


class MapFrame:
    def __init__(self, slam: GlobalSlam, period_s: float = WARN_PERIOD_S) -> None:
        self.slam = slam
        self.period_s = period_s
        self.warnings = 0
        self._next: float | None = None  # wall time of the next check

    def defines_map(self, rid: str) -> bool:
        """Whether a robot's first node, with no start pose known, defines `map`: without
        any known start, `basestation.map_frame_robot` or else the first robot to send."""
        s = self.slam
        if s.known_starts or s.start_headings:
            return False
        chosen = s.cfg.basestation.map_frame_robot
        return rid == chosen if chosen else not s.graph.robots()

    def _awaited(self) -> list[str]:
        """Robots that would put their chain on `map` and have sent no keyframe yet."""
        s = self.slam
        chosen = s.cfg.basestation.map_frame_robot
        if not (s.known_starts or s.start_headings) and chosen:
            return [] if chosen in s.graph.robots() else [chosen]
        return sorted(r for r in {*s.known_starts, *s.start_headings} if r not in s.graph.robots())

    def stats(self) -> dict[str, Any]:
        """The map's robots, their keyframes and largest spread (one robot's), the
        floating robots, and the reason they cannot be joined (None: they can)."""
        g, need = self.slam.graph, self.slam.cc.merge_min_spread_m
        robots = [r for r in g.robots() if g.num_nodes(r)]
        on_map = sorted(r for r in robots if g.is_anchored(r))
        spread = {r: spread_m(g.poses(r)[:, :2], need) for r in robots}
        floating = sorted(r for r in robots if r not in on_map)
        best = max((spread[r] for r in on_map), default=0.0)
        n = sum(g.num_nodes(r) for r in on_map)
        reason = None
        flown = [r for r in floating if spread[r] >= need]  # far enough to be joined
        # (two robots on the map: a floating robot's matches with both that agree need
        # only its own spread, loop_closure_manager._agreeing_elsewhere)
        if self.slam.cc.enabled and flown and best < need and len(on_map) <= 1:
            if not on_map:
                silent, fix = self._awaited(), sorted(self.slam._floating_starts)
                parts = [f"{', '.join(silent)} sent no keyframe"] if silent else []
                parts += [f"{', '.join(fix)} had no GNSS fix yet"] if fix else []
                reason = "no robot is on the map" + (f": {'; '.join(parts)}" if parts else "")
            else:
                # (GPS: one still without a fix joins at its first; said so, not blamed on
                # the map's drone alone)
                fix = sorted(r for r in flown if r in self.slam._floating_starts)
                reason = (f"the map ({', '.join(on_map)}) has {n} keyframe{'s' * (n != 1)} "
                          f"spread over {best:.1f} m; a join needs matches seen from places "
                          f"of it at least {need:g} m apart (merge_min_spread_m): its "
                          f"drone has not flown")  # fmt: skip
                reason += f"; {', '.join(fix)} had no GNSS fix yet" if fix else ""
        return {
            "map_robots": on_map,
            "map_keyframes": n,
            "map_spread_m": round(best, 3),  # (from merge_min_spread_m on, a lower bound)
            "unjoined": floating,
            "unjoinable_reason": reason,
            "warnings": self.warnings,
        }

    def check(self, now: float, final: bool = False) -> None:
        """Warn (see the module doc) if the floating robots cannot be joined; `final`: the
        mission's end, whenever the last check was."""
        if self._next is None:
            self._next = now + self.period_s
        if not final and now < self._next:
            return
        self._next = now + self.period_s
        st = self.stats()
        if st["unjoinable_reason"] is not None:
            self.warnings += 1
            log.warning("robots %s not joined to the map%s: %s", ", ".join(st["unjoined"]),
                        " at the end" if final else " yet", st["unjoinable_reason"])  # fmt: skip
