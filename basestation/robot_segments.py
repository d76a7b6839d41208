"""A robot's trajectory segments: one per run of its agent.

An agent started afresh (with no state to resume: restarted without its state folder,
or after `agent.resume_within_s`, or stopped and started again; or a second drone given
the same id) begins again at seq 0 and says which run it is by `session`
(protocol/messages.py). The base station maps each (robot id, session) to one robot of
the pose graph, a segment: the first run of robot `r0` is `r0`, the next `r0~2`, then
`r0~3` ("~" is never in a robot id). Before, a restarted agent's keyframes were refused
for good (their seqs clashed with the old run's), and the robot mapped nothing more.

A later segment starts in the frame of the robot's segment before it, loosely
(`segment_start`, `SEGMENT_START_SIGMAS`): an agent restarted in flight goes on in its
odometry's frame, the one the run before it began in (agent/node.py), and the loop
closures take it from there. A hovering drone's matches alone could not join it: they
come from one place, and joining maps takes matches from places apart (rooms that look
alike). While no segment before it is on the map it floats, and is joined to the map
by matching like a robot of unknown start (basestation/global_slam.py).

Everything sent to a segment goes to its robot's keys with the segment's session
(`RobotSegments.address`): the agent of another run drops it (agent/uplink.py).

The newest segment of a robot is its current one: the one its liveliness token, the
lock-step clock and its GNSS fixes are about. A new segment makes the one before it
past (`segment` returns it: the base station forgets its state and releases its goal).

Threads: `segment` runs on Zenoh's threads (keyframes, states) and on run()'s.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import numpy as np

log = logging.getLogger(__name__)

SEP = "~"  # between a robot id and the number of its segment
# [m, m, rad]: how loosely a segment starts in the frame of the one before it: an
# agent restarted goes on in the odometry's frame, as the run before it began (agent/
# node.py), but that run's local SLAM corrected the odometry's drift since
SEGMENT_START_SIGMAS = (1.0, 1.0, 0.2)
M = TypeVar("M")


def robot_of(segment: str) -> str:
    """The robot id of a segment ("r0~2" -> "r0")."""
    return segment.split(SEP, 1)[0]


def as_sent(msg: M) -> M:
    """A message of a segment, with its robot's id, as its agent sent it (for storing)."""
    rid: str = msg.robot_id  # type: ignore[attr-defined]
    return msg if SEP not in rid else dataclasses.replace(msg, robot_id=robot_of(rid))  # type: ignore[type-var]


def _number(segment: str) -> int:
    return int(segment.split(SEP, 1)[1]) if SEP in segment else 1


def segment_start(
    segment: str, robots: Iterable[str], T_map_odom: Callable[[str], np.ndarray | None]
) -> np.ndarray | None:
    """Where a segment starts, T_map_odom [x, y, yaw]: the latest of its robot's
    segments before it that is on the map (`T_map_odom(s)`, None while one is not)
    places its frame. None: none is, or `segment` is a robot's first."""
    robot, n = robot_of(segment), _number(segment)
    before = sorted((s for s in robots if robot_of(s) == robot and _number(s) < n), key=_number)
    placed = [(s, T) for s in before if (T := T_map_odom(s)) is not None]
    if not placed:
        return None
    log.info("robot segment %s starts in the frame of %s, at T_map_odom (%.2f, %.2f, %.1f "
             "deg), loosely", segment, placed[-1][0], *placed[-1][1][:2],
             np.degrees(placed[-1][1][2]))  # fmt: skip
    return placed[-1][1]


class RobotSegments:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._of: dict[tuple[str, int], str] = {}  # (robot id, session) -> segment
        self._session: dict[str, int] = {}  # segment -> session
        self._current: dict[str, str] = {}  # robot id -> its newest segment
        self._count: dict[str, int] = {}  # robot id -> segments so far

    def restore(self, sessions: Mapping[str, int]) -> None:
        """The segments of a database: segment -> the session of its keyframes, in the
        order they were first admitted."""
        with self._lock:
            for segment, session in sessions.items():
                n = int(segment.split(SEP, 1)[1]) if SEP in segment else 1
                self._add(robot_of(segment), session, segment, n)

    def segment(self, robot_id: str, session: int) -> tuple[str, str | None]:
        """(the segment of this run of `robot_id`, the segment it makes past or None)."""
        with self._lock:
            segment = self._of.get((robot_id, session))
            if segment is not None:
                return segment, None
            n = self._count.get(robot_id, 0) + 1
            segment = robot_id if n == 1 else f"{robot_id}{SEP}{n}"
            past = self._current.get(robot_id)
            self._add(robot_id, session, segment, n)
        if past is not None:
            log.warning("robot %s: another run of its agent (session %d; %s was session %d): "
                        "mapped as %s, placed from the segment before (restarted afresh, or "
                        "two drones with this id?)", robot_id, session, past,
                        self._session[past], segment)  # fmt: skip
        return segment, past

    def _add(self, robot_id: str, session: int, segment: str, n: int) -> None:
        self._of[(robot_id, session)] = segment
        self._session[segment] = session
        self._current[robot_id] = segment
        self._count[robot_id] = max(n, self._count.get(robot_id, 0))

    def current(self, robot_id: str) -> str:
        """The robot's newest segment (its id if it has none yet)."""
        return self._current.get(robot_id, robot_id)

    def address(self, msg: M) -> M:
        """A message for a segment (its robot_id), as sent: to its robot, with the
        segment's session (0 for one this base station has not heard from)."""
        segment: str = msg.robot_id  # type: ignore[attr-defined]
        session = self._session.get(segment, 0)
        return dataclasses.replace(msg, robot_id=robot_of(segment), session=session)  # type: ignore[type-var]

    def stats(self) -> dict[str, Any]:
        """Robots with more than one segment: robot id -> {segment: session}."""
        with self._lock:
            many = {robot_of(s) for s in self._session if SEP in s}
            return {r: {s: v for s, v in self._session.items() if robot_of(s) == r} for r in many}
