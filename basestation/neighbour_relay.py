"""Tells each robot where the others are, for its neighbour guard (agent side).

Robots never hear each other directly (under the deploy access control a robot gets
only what is addressed to it), and the base station's paths keep them apart at the
exploration step's pace (1 Hz). So that a follower notices a leader that stopped
sooner than that, the base station answers every `RobotState` with a `Neighbours`
message: the other robots' last reported `map` positions, their stamps and
velocities (the difference of their last two states' `odom` positions, turned into
`map` with the latest correction: a correction's jump is not motion, and corrections
come several times a second). Robots whose last state is older than `max_age_s`
of the asking robot's time are left out, and so are robots without a correction yet
(their `map` pose is not known: correction epoch -1).

In a lock-step simulation (`strictly_earlier`) every robot reports at the same stamps,
and which of two states of one stamp arrives first is up to the machine's load: the
answer to a state of stamp t then holds each other robot's latest state before t, so
that it is the same on every run.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.geometry import pose7_to_pose4
from common.stamps import JumpGate
from protocol import Neighbours, RobotState

log = logging.getLogger(__name__)
# s: two states closer than this give no velocity (1e-300 s apart had made it infinite,
# and every answer then failed the agents' checks)
MIN_STEP_S = 1e-3


@dataclass
class _Track:
    stamp: float
    epoch: int
    xy: np.ndarray  # map
    odom_xy: np.ndarray
    velocity: np.ndarray  # map


class NeighbourRelay:
    def __init__(
        self, max_age_s: float = 2.0, max_dt_s: float = 2.0, strictly_earlier: bool = False
    ) -> None:
        self.max_age_s = max_age_s  # s, older positions are not relayed
        self.max_dt_s = max_dt_s  # s, states further apart give no velocity
        self.strictly_earlier = strictly_earlier
        self._tracks: dict[str, _Track] = {}
        self._previous: dict[str, _Track] = {}  # each robot's track before its latest
        self._jumps: dict[str, JumpGate] = {}  # a stamp far past a robot's last (1e9 s)

    def on_state(self, msg: RobotState) -> Neighbours:
        """Take `msg`'s position; the answer to send back to its robot."""
        xy = np.asarray(msg.pose_map[:2], dtype=np.float64)
        odom_xy = np.asarray(msg.pose_odom[:2], dtype=np.float64)
        old = self._tracks.get(msg.robot_id)
        velocity = np.zeros(2)
        if old is not None and MIN_STEP_S <= msg.stamp - old.stamp <= self.max_dt_s:
            turn = pose7_to_pose4(msg.pose_map)[3] - pose7_to_pose4(msg.pose_odom)[3]
            c, s = np.cos(turn), np.sin(turn)
            d = (odom_xy - old.odom_xy) / (msg.stamp - old.stamp)
            velocity = np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])
        gate = self._jumps.setdefault(msg.robot_id, JumpGate())
        if gate.holds(msg.stamp, None if old is None else old.stamp):
            log.error("robot %s: state stamp %.3f far past its last: held back unless the "
                      "next follows it", msg.robot_id, msg.stamp)  # fmt: skip
        elif old is None or msg.stamp > old.stamp:  # a late or repeated state changes nothing
            if old is not None:
                self._previous[msg.robot_id] = old
            self._tracks[msg.robot_id] = _Track(
                msg.stamp, msg.correction_epoch, xy, odom_xy, velocity
            )
        others: list[_Track] = []
        for rid in sorted(self._tracks):  # not in order of arrival
            t: _Track | None = self._tracks[rid]
            if rid == msg.robot_id:
                continue
            if self.strictly_earlier and t.stamp >= msg.stamp:
                t = self._previous.get(rid)
            if t is not None and t.stamp >= msg.stamp - self.max_age_s and t.epoch >= 0:
                others.append(t)
        return Neighbours(
            robot_id=msg.robot_id,
            stamp=msg.stamp,
            stamps=np.array([t.stamp for t in others], dtype=np.float64),
            xy=np.array([t.xy for t in others], dtype=np.float64).reshape(-1, 2),
            velocity=np.array([t.velocity for t in others], dtype=np.float64).reshape(-1, 2),
        )

    def forget(self, robot_id: str) -> None:
        """A robot that went away (liveliness lost) is no longer anyone's neighbour."""
        self._tracks.pop(robot_id, None)
        self._previous.pop(robot_id, None)
        self._jumps.pop(robot_id, None)
