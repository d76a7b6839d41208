"""An agent's state on disk, for an agent restarted in the middle of a mission (a
crash, systemd restarting it).

With `agent.state_dir` set, the agent writes there, at each keyframe and each
`RobotState` (so that it stays fresh while the drone hovers) and at a new keyframe
chain, where it is (`state.json`, replaced in one step): its keyframe chain and next
seq, the last seq acknowledged, the last keyframe's pose, the last scan's stamp,
`T_odom_base` and the odometry source's pose then, the sensor clock's offset, the latest
correction (epoch, `T_map_odom`) and the path it flies (the waypoint it was flying to:
from the tour's first, it had flown into walls); every keyframe it cuts goes to the
same folder first (agent/keyframe_history.py: a keyframe sent after the last save is
found there on resuming, `KeyframeUplink._resume`). An agent started on it takes
them up: the keyframes not acknowledged are sent again, its local pose goes on from
the last keyframe by the odometry since (an autopilot's odometry runs on through the
restart), and its next keyframe spans the gap, so the base station's trajectory of
the robot goes on in the same frame. An agent with no state to take up begins again
at seq 0 in a session of its own: the base station maps it as a new segment of the
robot (basestation/robot_segments.py); it had linked it into the old trajectory.

A state older than `agent.resume_within_s` is another mission's: it is deleted, with
its keyframes, and the agent starts afresh; keyframes of it that no base station
acknowledged are kept aside (`_keep_unsent`), not sent.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from dataclasses import dataclass, fields
from pathlib import Path

from common.errors import ConfigError
from common.file_lock import exclusive
from protocol.messages import MAX_SESSION

log = logging.getLogger(__name__)

STATE_FILE = "state.json"
ADDED_LATER = ("session", "odom_origin")  # fields a state file may lack (an older agent's)


@dataclass
class ResumePoint:
    chain: int = 0
    next_seq: int = 0
    acked_seq: int = -1
    epoch: int = -1
    T_map_odom: list[float] | None = None  # [x, y, z, yaw]
    stamp: float | None = None  # the last scan's (sensor clock, moved on by the offset) ...
    pose_odom: list[float] | None = None  # ... T_odom_base [x, y, z, yaw]
    odometry: list[float] | None = None  # ... and the odometry source's [x, y, yaw]
    path: list[list[float]] | None = None  # the tour or path flown, map [x, y] ...
    path_index: int = 0  # ... and the waypoint it was flying to
    keyframe_pose: list[float] | None = None  # T_odom_base of the last keyframe sent
    clock_offset: float = 0.0  # s, common.stamps.BackStepRepair's
    session: int = 0  # the agent's run (protocol MAX_SESSION): the resumed one goes on in it
    odom_origin: list[float] | None = None  # where its odom frame began (protocol OdomOrigin)
    saved_unix: float = 0.0

    def check(self) -> None:
        """ValueError if a field is not what this program writes."""
        ints = {"chain": 0, "next_seq": 0, "acked_seq": -1, "epoch": -1, "path_index": 0,
                "session": 0}  # fmt: skip
        for name, low in ints.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not low <= v < 2**62:
                raise ValueError(f"{name}: {v!r}")
        if not self.acked_seq < self.next_seq or (self.next_seq and self.keyframe_pose is None):
            raise ValueError(f"acked_seq {self.acked_seq}, next_seq {self.next_seq}")
        if self.session > MAX_SESSION:
            raise ValueError(f"session: {self.session!r}")
        named = ("T_map_odom", 4), ("pose_odom", 4), ("odometry", 3), ("keyframe_pose", 4)
        for name, n in (*named, ("odom_origin", 3)):
            v = getattr(self, name)
            if v is not None and (len(v) != n or not all(_finite(x) for x in v)):
                raise ValueError(f"{name}: {v!r}")
        if not all(_finite(v) for v in (self.stamp or 0.0, self.saved_unix, self.clock_offset)):
            raise ValueError("stamp / saved_unix / clock_offset")
        path = self.path or []
        if not all(isinstance(p, list) and len(p) == 2 and all(map(_finite, p)) for p in path):
            raise ValueError("path: expected [[x, y], ...]")


def _finite(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _write(path: Path, text: str) -> None:
    """`text` on the disk itself, then in place of `path` (a power cut: old or new)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fdatasync(f.fileno())
    os.replace(tmp, path)


def save(directory: Path, point: ResumePoint) -> bool:
    """Write `point` (now) in one step: a reader finds the old state or the new one. The
    path goes to a file of its own (`path-<n>.json`) when it changes, and the state names
    it: written whole at every state (5 a second), a 2,000-waypoint tour had cost ~10 ms
    a save on the control thread. A disk error (full, read-only) is logged when it
    starts and the agent flies on (it had raised out of its loop): False."""
    global _failing
    point.saved_unix = time.time()
    raw = {f.name: getattr(point, f.name) for f in fields(point)}  # (asdict copies the path)
    try:
        if point.path is not None:
            written = _paths_written.get(directory)
            if written is None or written[1] != point.path or not (directory / written[0]).exists():
                # numbered after any a state names (a crash between the two writes)
                n = max((int(p.name[5:-5]) for p in _path_files(directory)), default=-1)
                name = f"path-{n + 1}.json"
                _write(directory / name, json.dumps(point.path))
                _paths_written[directory] = written = (name, point.path)
            raw["path"] = written[0]
        _write(directory / STATE_FILE, json.dumps(raw))
        for old in _path_files(directory):  # the paths no state names any more
            if old.name != raw["path"]:
                old.unlink(missing_ok=True)
    except OSError as exc:
        if not _failing:
            log.error("state not saved in %s (%s): restarted, this agent would go on from "
                      "an older state, or afresh", directory, exc)  # fmt: skip
        _failing = True
        return False
    _failing = False
    return True


_failing = False  # the last save failed (one error line until one succeeds)
_paths_written: dict[Path, tuple[str, list[list[float]]]] = {}  # folder: its path file
PATH_NAME = re.compile(r"^path-[0-9]{1,18}\.json$")


def _path_files(directory: Path) -> list[Path]:
    return [p for p in directory.glob("path-*.json") if PATH_NAME.match(p.name)]


def load(directory: Path, max_age_s: float) -> ResumePoint | None:
    """The state of an agent that ran here less than `max_age_s` ago, else None (an
    older one, or one this program cannot read, is deleted with its keyframes). The
    folder is this process's from then on (`hold`)."""
    directory.mkdir(parents=True, exist_ok=True)
    hold(directory)
    path = directory / STATE_FILE
    if not path.exists():
        return _start_afresh(directory, None)
    try:
        raw = json.loads(path.read_text())
        names = {f.name for f in fields(ResumePoint)}
        if isinstance(raw, dict):  # a state of the version before, with its keyframes
            raw = {**{k: None for k in ADDED_LATER if k not in raw}, **raw}
            raw["session"] = raw["session"] or 0
        if not isinstance(raw, dict) or set(raw) != names:
            raise ValueError(f"fields {sorted(raw) if isinstance(raw, dict) else raw!r}")
        if isinstance(raw["path"], str):  # the file of its own it was saved to
            if not PATH_NAME.match(raw["path"]):
                raise ValueError(f"path: {raw['path']!r}")
            raw["path"] = json.loads((directory / raw["path"]).read_text())
        point = ResumePoint(**raw)
        point.check()
    except (OSError, ValueError, TypeError) as exc:  # (another version's, say: its keyframes
        keep = _move_aside(directory, f"unreadable-{int(time.time())}")  # had been deleted)
        log.error("%s cannot be read (%s): starting afresh%s", path, exc,
                  "" if keep is None else f"; its keyframes kept in {keep}, not sent")  # fmt: skip
        return _start_afresh(directory, None)
    age = time.time() - point.saved_unix
    if not abs(age) <= max_age_s:  # (< 0: the host's clock was set back meanwhile)
        why = f"saved {age:.0f} s ago (> agent.resume_within_s)"
        _keep_unsent(directory, point, why)
        return _start_afresh(directory, why)
    log.warning("resuming from %s (saved %.1f s ago): keyframe chain %d at seq %d, %d not "
                "acknowledged", path, age, point.chain, point.next_seq,
                point.next_seq - point.acked_seq - 1)  # fmt: skip
    return point


def _keep_unsent(directory: Path, point: ResumePoint, why: str) -> None:
    """A stale state's keyframes no base station acknowledged are moved, with the state,
    to a folder of their own (`unsent-<saved unix time>`), not deleted: a drone whose link
    was lost, then landed and restarted after `agent.resume_within_s` (a battery swap),
    had lost all it mapped meanwhile. They are not sent: that mission's base station may
    be gone, and a new one would map them into its own mission."""
    unsent = point.next_seq - point.acked_seq - 1
    if unsent <= 0:
        return
    keep = _move_aside(directory, f"unsent-{int(point.saved_unix)}")
    if keep is not None:
        log.error("%s: another mission's state, %s, with %d keyframes (seqs %d-%d of chain "
                  "%d) no base station acknowledged: kept in %s, not sent", directory, why,
                  unsent, point.acked_seq + 1, point.next_seq - 1, point.chain,
                  keep)  # fmt: skip


_held: dict[Path, int] = {}  # state folders this process holds: a descriptor with a flock


def hold(directory: Path) -> None:
    """An exclusive flock on the state folder for the rest of this process, or
    ConfigError: a second agent started on a running one's folder (a manual start beside
    the systemd unit) had taken over its session and keyframe numbers, and the base
    station dropped the robot's keyframes for the rest of the mission."""
    key = directory.resolve()
    if key in _held:  # (this process's already: an agent made again, as tests do)
        return
    fd = exclusive(directory)  # (the folder itself: no file of its own in it)
    if fd is None:
        raise ConfigError(f"agent.state_dir {directory}: in use by another agent (one "
                          "folder per running agent)")  # fmt: skip
    _held[key] = fd


def _move_aside(directory: Path, name: str) -> Path | None:
    """The keyframes, state and path files into `directory / name` (None: there were no
    keyframes, or they could not be moved: they are deleted with the rest)."""
    logs = sorted(directory.glob("keyframes-*.log"))
    if not logs:
        return None
    keep = directory / name
    try:
        keep.mkdir(exist_ok=True)
        for p in (*logs, *directory.glob("path-*.json"), *directory.glob(STATE_FILE)):
            os.replace(p, keep / p.name)
    except OSError as exc:
        log.error("%s: could not keep its keyframes in %s (%s): deleted", directory, keep, exc)
        return None
    return keep


def _start_afresh(directory: Path, why: str | None) -> None:
    old = [*directory.glob("keyframes-*.log"), *directory.glob(STATE_FILE + "*"),
           *directory.glob("path-*.json*")]  # fmt: skip
    if old and why:
        log.warning("%s: another mission's state, %s: deleted", directory, why)
    for p in old:
        p.unlink(missing_ok=True)
    return None
