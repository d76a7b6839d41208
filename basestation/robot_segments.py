"""A robot's trajectory segments: one per run of its agent.

An agent started afresh (with no state to resume: restarted without its state folder,
or after `agent.resume_within_s`, or stopped and started again; or a second drone given
the same id) begins again at seq 0 and says which run it is by `session`
(protocol/messages.py). The base station maps each (robot id, session) to one robot of
the pose graph, a segment: the first run of robot `r0` is `r0`, the next `r0~2`, then
`r0~3` ("~" is never in a robot id). Before, a restarted agent's keyframes were refused
for good (their seqs clashed with the old run's), and the robot mapped nothing more.

A later segment that began in flight (`OdomOrigin`, on every keyframe: where the
agent's odom frame begins on its odometry source's frame, away from the source's
origin) starts, loosely (`SEGMENT_START_SIGMAS`), where the source's frame puts it:
the run before it had the same source, and its `T_map_odom` and origin place the
source's frame in `map` (`segment_start`). The loop closures take it from there. A
hovering drone's matches alone could not join it to the map: they come from one place,
and joining maps takes matches from places apart (rooms that look alike). A run that
began where its source did (another flight, or another drone with the id), or one
with no segment before it on the map, floats, and is joined to the map by matching
like a robot of unknown start (basestation/global_slam.py).

Everything sent to a segment goes to its robot's keys with the segment's session
(`RobotSegments.address`): the agent of another run drops it (agent/uplink.py).

The newest segment of a robot is its current one: the one its liveliness token, the
lock-step clock and its GNSS fixes are about, and the one explored for. A new segment
makes the one before it past (`segment` returns it: the base station forgets its state
and releases its goal; states of a past run still reach the other drones' guards).
The pose graph holds `capacity` chains (62): a run beyond them is not mapped (an error
line, its messages dropped).

Threads: `segment` runs on Zenoh's threads (keyframes, states) and on run()'s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import numpy as np

from basestation.pose_graph import ROBOT_KEY_ALPHABET
from common.geometry import se2_compose, se2_inverse
from protocol.messages import IN_FLIGHT_M

log = logging.getLogger(__name__)

SEP = "~"  # between a robot id and the number of its segment
PAST_QUIET_S = 30.0  # s: a past segment not heard from this long gets no more corrections
# [m, m, rad]: how loosely a later segment starts where the odometry source's frame puts
# it (`segment_start`): the source drifted, where the run before it had its local SLAM
SEGMENT_START_SIGMAS = (2.0, 2.0, 0.25)
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
    segment: str,
    robots: Iterable[str],
    T_map_odom: Callable[[str], np.ndarray | None],
    keyframes: Callable[[str], Any],
) -> np.ndarray | None:
    """Where a later segment's odom frame begins, T_map_odom [x, y, yaw], if it began in
    flight (its first keyframe's `odom_origin` more than `IN_FLIGHT_M` from its odometry
    source's origin: the source's frame is the one the robot's run before it had) and
    that run (the segment just before it, `keyframes(s).odom_origin_latest` paired with
    `T_map_odom(s)`, both at its latest keyframe) is on the map. None otherwise: the
    segment floats (a run that began where its source did is another flight or drone)."""
    robot, n, own = robot_of(segment), _number(segment), keyframes(segment).odom_origin
    before = [s for s in robots if robot_of(s) == robot and _number(s) < n]
    if own is None or math.hypot(own[0], own[1]) <= IN_FLIGHT_M or not before:
        return None
    s = max(before, key=_number)  # (not across a run of another flight)
    T, o = T_map_odom(s), keyframes(s).odom_origin_latest
    if T is None or o is None:
        return None
    T_map_source = se2_compose(T, se2_inverse(o))  # the odometry source's frame in map
    log.info(
        "robot segment %s starts in the odometry frame of %s: at (%.2f, %.2f, %.1f deg), loosely",
        segment,
        s,
        *T_map_source[:2],
        math.degrees(T_map_source[2]),
    )
    return se2_compose(T_map_source, own)


class RobotSegments:
    def __init__(self, capacity: int = len(ROBOT_KEY_ALPHABET)) -> None:
        """`capacity`: segments in all (the pose graph's chains)."""
        self.capacity = capacity
        self.refused: set[tuple[str, int]] = set()  # runs beyond it
        self._lock = threading.Lock()
        self._of: dict[tuple[str, int], str] = {}  # (robot id, session) -> segment
        self._session: dict[str, int] = {}  # segment -> session
        self._current: dict[str, str] = {}  # robot id -> its newest segment
        self._count: dict[str, int] = {}  # robot id -> segments so far
        self._heard: dict[str, float] = {}  # segment -> when its agent last sent (monotonic)

    def restore(self, sessions: Mapping[str, int]) -> None:
        """The segments of a database: segment -> the session of its keyframes, in the
        order they were first admitted."""
        with self._lock:
            for segment, session in sessions.items():
                self._add(robot_of(segment), session, segment, _number(segment))

    def segment(self, robot_id: str, session: int) -> tuple[str | None, str | None]:
        """(the segment of this run of `robot_id`, the segment it makes past or None);
        (None, None) once there are `capacity` segments (logged: its messages dropped)."""
        with self._lock:
            segment = self._of.get((robot_id, session))
            if segment is not None:
                self._heard[segment] = time.monotonic()
                return segment, None
            if len(self._session) >= self.capacity:
                if (robot_id, session) not in self.refused:
                    self.refused.add((robot_id, session))
                    log.error("robot %s: a new run of its agent (session %d) is not mapped: "
                              "the pose graph holds %d robot segments, its most (restart "
                              "agents on their state folders)", robot_id, session,
                              self.capacity)  # fmt: skip
                return None, None
            n = self._count.get(robot_id, 0) + 1
            segment = robot_id if n == 1 else f"{robot_id}{SEP}{n}"
            past = self._current.get(robot_id)
            self._add(robot_id, session, segment, n)
            self._heard[segment] = time.monotonic()
        if past is not None:
            log.warning("robot %s: another run of its agent (session %d; %s was session %d): "
                        "mapped as %s (restarted with no state to take up, or two drones "
                        "with this id?)", robot_id, session, past,
                        self._session[past], segment)  # fmt: skip
        return segment, past

    def _add(self, robot_id: str, session: int, segment: str, n: int) -> None:
        self._of[(robot_id, session)] = segment
        self._session[segment] = session
        if n >= _number(self._current.get(robot_id, segment)):  # the newest (restored in
            self._current[robot_id] = segment  # the order first admitted: not the same)
        self._count[robot_id] = max(n, self._count.get(robot_id, 0))

    def served(self, segment: str) -> bool:
        """Whether corrections go to `segment`: its robot's current one, or a past one
        heard from within `PAST_QUIET_S` (a second drone with the id; a restarted run's
        old session is dead: corrections for it would only load the link)."""
        if self._current.get(robot_of(segment), segment) == segment:
            return True
        return time.monotonic() - self._heard.get(segment, -math.inf) < PAST_QUIET_S

    def current(self, robot_id: str) -> str:
        """The robot's newest segment (its id if it has none yet)."""
        return self._current.get(robot_id, robot_id)

    def address(self, msg: M) -> M:
        """A message for a segment (its robot_id), as sent: to its robot, with the
        segment's session (0 for one this base station has not heard from)."""
        segment: str = msg.robot_id  # type: ignore[attr-defined]
        session = self._session.get(segment, 0)
        return dataclasses.replace(msg, robot_id=robot_of(segment), session=session)  # type: ignore[type-var]

    def refused_runs(self) -> dict[str, list[int]]:
        """Robot id -> the sessions of its runs refused (past the segment limit): not
        mapped, named only in one error line before."""
        with self._lock:
            out: dict[str, list[int]] = {}
            for robot, session in sorted(self.refused):
                out.setdefault(robot, []).append(session)
            return out

    def stats(self) -> dict[str, Any]:
        """Robots with more than one segment: robot id -> {segment: session}."""
        with self._lock:
            many = {robot_of(s) for s in self._session if SEP in s}
            return {r: {s: v for s, v in self._session.items() if robot_of(s) == r} for r in many}
