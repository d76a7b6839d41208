"""GNSS fixes into the map frame (ENU at the map's WGS84 origin) for the pose graph.

The origin is the world's (its map YAML) when it has one, else the median of the first
`ORIGIN_FIXES` fixes (held until then): taken from the first fix alone, one bad fix
had set it for good, and every later fix lay thousands of km away. A fix farther from
the origin than `reach_m` is dropped with an error line: one 465 km off had pulled its
robot there (with `basestation.gps.huber` off), and the map with it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from common.errors import CollabSlamError
from common.geodesy import GeoOrigin, geodetic_to_enu
from common.scenario import Scenario
from common.world_files import world_wgs84_origin
from protocol import GnssFix

log = logging.getLogger(__name__)

ORIGIN_FIXES = 5  # fixes whose median sets an origin the world does not give
# m: a fix whose horizontal 1-sigma is larger has no say in the origin (a receiver's
# output before lock reports ~4e6 m: three of the first five had set it in the sea)
ORIGIN_MAX_SIGMA_M = 50.0
ORIGIN_SAME_M = 0.05  # m: a world origin this close to the stored one is the same
MAX_HELD_FIXES = 1000  # held for the origin at most (the newest)


def map_georeference(scenario: Scenario | None, headings: bool) -> tuple[GeoOrigin | None, str]:
    """The map frame's WGS84 origin (None: not known yet) and why the map is not ENU ("":
    it is). With a scenario the map is its world frame, ENU at the scenario's WGS84
    origin, else the world map YAML's; robots started from GNSS headings put it in ENU
    at the first fixes' median (`GnssIntake.take`)."""
    if scenario is None:
        return None, "without a scenario (--scenario) the map is the first robot's odom frame"
    origin = scenario.wgs84_origin
    if origin is None:
        try:
            origin = world_wgs84_origin(scenario.world)
        except CollabSlamError as exc:
            log.warning("no WGS84 origin for the map: %s", exc)
    if origin is None and not headings:
        return None, ("the map is the scenario's world frame, whose WGS84 origin is not "
                      "known (give the scenario a wgs84_origin, or the world's map YAML "
                      "one)")  # fmt: skip
    return origin, ""


class GnssIntake:
    def __init__(self, origin: GeoOrigin | None, reach_m: float, not_enu: str = "") -> None:
        """`not_enu`: why the map frame is not ENU (empty: it is), when it is not: every
        fix is then ignored (counted, named once). The fixes' median had been taken for
        the origin of a world frame that has none (a scenario with known starts: 3.25 m
        and 21 degrees of bend), or of the first robot's odom frame (no scenario), and
        its files had claimed a georeference they did not have."""
        self.origin = origin
        self.reach_m = reach_m  # m from the origin: farther fixes are dropped
        self.not_enu = not_enu
        self._first: list[GnssFix] = []  # held until the origin is known
        self.dropped = 0
        self.ignored = 0  # fixes not taken: the map frame is not ENU
        self._origin_saved = False  # on the database (persistence.Batch.origin)

    def new_origin(self) -> list[float] | None:
        """The origin, once it is set and not on the database yet (for it; else None): a
        restart converts later fixes as the stored ones were."""
        if self.origin is None or self._origin_saved:
            return None
        self._origin_saved = True
        return self.origin.as_list()

    def restore(self, stored: list[float] | None) -> None:
        """The origin of a restored database (None: none was set), unless the world gives
        one: set from the first fixes, it had been set again from the next five."""
        if stored is not None and self.origin is None and not self.not_enu:
            self.origin = GeoOrigin.from_sequence(stored)
        elif stored is not None and self.origin is not None:
            was = GeoOrigin.from_sequence(stored)
            off = float(np.linalg.norm(geodetic_to_enu(was.as_list(), self.origin)))
            if off > ORIGIN_SAME_M:  # (the stored fixes, and the graph, are in its frame)
                log.error("the world's WGS84 origin %s is %.1f m from the one this mission's "
                          "database was made with, %s: the mission goes on with the stored "
                          "one (start a new database for the new one)", self.origin, off,
                          was)  # fmt: skip
                self.origin = was
        self._origin_saved |= stored is not None

    def take(self, fix: GnssFix) -> list[tuple[GnssFix, NDArray[np.float64]]]:
        """The fixes now ready for the graph (this one, or the held ones once the origin
        is set), each with its east-north position (m) in the map frame."""
        if self.not_enu:
            if not self.ignored:
                log.error("GNSS fixes ignored: %s", self.not_enu)
            self.ignored += 1
            return []
        fixes = [fix]
        if self.origin is None:
            self._first.append(fix)
            sure = [f.lla for f in self._first if max(f.sigmas_enu[:2]) <= ORIGIN_MAX_SIGMA_M]
            if len(sure) < ORIGIN_FIXES:
                del self._first[:-MAX_HELD_FIXES]
                return []
            fixes, self._first = self._first, []
            self.origin = GeoOrigin.from_sequence(np.median(sure, axis=0))
            log.info("map frame: ENU at the median of the first %d GNSS fixes within %.0f m "
                     "(1-sigma) %s", len(sure), ORIGIN_MAX_SIGMA_M, self.origin)  # fmt: skip
        ready = []
        for f in fixes:
            xy = np.asarray(geodetic_to_enu(f.lla, self.origin)[:2], dtype=np.float64)
            if np.hypot(*xy) <= self.reach_m:
                ready.append((f, xy))
                continue
            self.dropped += 1
            log.error("GNSS fix of %s at t=%.3f lies %.0f m from the map's origin (> %.0f m): "
                      "dropped", f.robot_id, f.stamp, np.hypot(*xy), self.reach_m)  # fmt: skip
        return ready


__all__ = ["ORIGIN_FIXES", "GnssIntake"]
