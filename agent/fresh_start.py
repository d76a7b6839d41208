"""How an agent that starts afresh (no state to take up, agent/resume.py) begins.

Its `odom` frame begins at its first pose, at the identity; where that is on the
odometry source's frame goes with every keyframe (`OdomOrigin`), so the base station
can start a later run of the robot in the frame of the run before it
(basestation/robot_segments.py). Started away from the source's origin and airborne,
the agent was restarted in flight: it hovers until the base station's first correction
says where it is (a later run where the odometry's frame puts it; a robot's first run
at its start pose: the agent cannot tell which it is), `PLACEMENT_WAIT_S` at most (then
its start pose composed with the source's pose: a simulator's odometry and a VIO's
begin at the start pose), and flies on from the waypoint of its tour nearest to it
(from the first, it had flown into a wall). Its first keyframe waits
for the odometry, and the decision for the altimeter, `ODOM_WAIT_S` at most (an agent
joining a running sensor stream may get a scan first); its scans are taken meanwhile.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from agent.resume import ResumePoint
from common.geometry import pose4_compose, se2_compose, se2_inverse
from protocol import OdomOrigin
from protocol.messages import IN_FLIGHT_M

log = logging.getLogger(__name__)

ODOM_WAIT_S = 0.5  # s of scans held at the start for the odometry
PLACEMENT_WAIT_S = 5.0  # s a drone restarted in flight hovers for the base station's word
AIRBORNE_M = 0.3  # m: above this the drone is in the air


class FreshStart:
    @staticmethod
    def of(resume: ResumePoint | None) -> FreshStart:
        """An agent's start: a resumed one has begun, with the origin it had."""
        o = None if resume is None or not resume.odom_origin else OdomOrigin(*resume.odom_origin)
        return FreshStart(o, resumed=resume is not None)

    def __init__(self, origin: OdomOrigin | None = None, resumed: bool = False) -> None:
        """`resumed`: the agent took up a state (its `origin` is the one it had)."""
        self.origin = origin
        self.begun = resumed  # the origin is known (or there is no odometry): keyframes go
        self.settled = resumed  # and whether it was restarted in flight
        self.in_flight = False
        self.placed = False  # in flight: where it is in map is known (agent/node.py)
        self._first_stamp: float | None = None

    def take(
        self, stamp: float, odometry: np.ndarray | None, altitude: float | None, pose: np.ndarray
    ) -> bool:
        """At each scan until settled: the odometry source's pose [x, y, yaw] at `stamp`
        (None: none yet), the altimeter's latest (None: none yet) and the local pose
        [x, y, z, yaw] then. True when it has just found the drone restarted in flight.
        Either missing, it waits `ODOM_WAIT_S` from the first scan at most."""
        if self._first_stamp is None:
            self._first_stamp = stamp
        late = stamp - self._first_stamp >= ODOM_WAIT_S
        if not self.begun and (odometry is not None or late):
            self.begun = True  # T_source_odom = T_source_base * T_odom_base^-1
            self.origin = None if odometry is None else self.now(odometry, pose)
        if not self.begun or self.settled or (altitude is None and not late):
            return False
        self.settled, o = True, self.origin
        far = o is not None and math.hypot(o.x, o.y) > IN_FLIGHT_M
        self.in_flight = far and altitude is not None and altitude > AIRBORNE_M
        if self.in_flight and o is not None:
            log.warning("restarted in flight %.1f m from the odometry's origin, with no "
                        "state to take up", math.hypot(o.x, o.y))  # fmt: skip
        return self.in_flight

    def waited(self, stamp: float) -> bool:
        """Whether it has waited `PLACEMENT_WAIT_S` since its first scan."""
        return self._first_stamp is not None and stamp - self._first_stamp >= PLACEMENT_WAIT_S

    def start_in_map(self, T_map_odom: np.ndarray) -> np.ndarray:
        """Restarted in flight: its `odom` frame in `map`, [x, y, z, yaw], from the start
        pose (`T_map_odom`: where the source's frame begins) and `origin`."""
        o = self.origin
        assert o is not None
        return pose4_compose(T_map_odom, [o.x, o.y, 0.0, o.yaw])

    def now(self, odometry: np.ndarray | None, pose: np.ndarray) -> OdomOrigin | None:
        """Where the odom frame's origin is on the source's frame now (a keyframe's
        `odom_origin`): local SLAM and the odometry drift apart as it corrects it, so the
        base station pairs a run's latest with its latest `T_map_odom`. `origin` without
        the odometry (None: none yet)."""
        if odometry is None:
            return self.origin
        o = se2_compose(odometry[:3], se2_inverse(np.asarray(pose)[[0, 1, 3]]))
        return OdomOrigin(float(o[0]), float(o[1]), float(o[2]))

    def as_list(self) -> list[float] | None:
        """The origin as [x, y, yaw] (for the state file)."""
        o = self.origin
        return None if o is None else [o.x, o.y, o.yaw]


def nearest_waypoint(tour: np.ndarray, xy: np.ndarray) -> int:
    """Index of the waypoint of `tour` ((M, 2), map) nearest to `xy` (0 if none). In a
    straight line: one behind a wall can be nearest (the guard holds the drone there)."""
    return int(np.argmin(np.hypot(*(tour - xy).T))) if len(tour) else 0
