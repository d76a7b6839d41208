"""Exploration steps off the thread that takes in keyframes (a live base station).

A step can take seconds: 1.5 s of CPU when 8 drones replan, 3-7 s with 4 drones in a
real-time simulation on a loaded laptop. Run on the intake thread, it had held back
every acknowledgement that long: agents resent 56-89 % of their keyframes (arriving as
duplicates) while the drones waited. Live, each step now runs on one worker thread while
`run()`'s thread goes on taking in, optimizing and acknowledging.

Who touches the `ExplorationManager`: the worker while a step is in flight, `run()`'s
thread otherwise (its inputs are made there: losses released, poses read, then handed
over whole). In a lock-step simulation the step runs at once on `run()`'s thread, so
runs repeat exactly.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from basestation.exploration import ExplorationManager
from basestation.exploration_setup import path_message
from common.map_io import GridMap
from protocol import Path as PathMsg
from protocol import decode

log = logging.getLogger("basestation.node")

# s of wall time between the INFO lines that sum up the paths sent (`PathLog`)
PATH_SUMMARY_PERIOD_S = 30.0


@dataclass
class StepInputs:
    """One exploration step's view of the world, taken on `run()`'s thread."""

    grid: GridMap  # exploration's view (common.map_io.EXPLORATION_FREE_THRESH)
    strict: GridMap | None  # the published map's
    poses: dict[str, np.ndarray]  # [x, y, yaw] in map
    blocked: set[str]  # robots whose follower reports it cannot go on
    stamps: dict[str, float]  # of the states the poses came from (-1: a keyframe's)
    epoch: int  # the correction epoch the poses are in


@dataclass
class StepResult:
    inputs: StepInputs
    paths: dict[str, np.ndarray | None]  # map [x, y] points; None: hold
    over: bool  # no frontier left: a hold is sent as path id 0, the mission's end
    wall_ms: float


def path_messages(result: StepResult, last_id: int, z: float) -> list[tuple[str, int, PathMsg]]:
    """(robot, path id, Path at altitude `z`) of each robot a step planned for, numbered
    on from `last_id`, each logged at DEBUG (`PathLog` sums them up)."""
    out = []
    for path_id, (rid, path) in enumerate(result.paths.items(), last_id + 1):
        over_now = path is None and result.over
        what = "exploration over (path 0)" if over_now else "hold" if path is None else (
            f"{len(path)} points to {path[-1].round(1)}")  # fmt: skip
        log.debug("t=%.1f s: path %d for %s from (%.1f, %.1f): %s",
                 result.inputs.stamps.get(rid, -1.0), path_id, rid,
                 *result.inputs.poses[rid][:2], what)  # fmt: skip
        msg = path_message(rid, 0 if over_now else path_id, path, z, result.inputs.epoch)
        out.append((rid, path_id, msg))
    return out


class PathLog:
    """The paths sent, summed up at INFO: at the first step, then at most every
    `period_s` of wall time, and when exploration is over for a robot (path 0). A line
    per path had been 43 of the base station's 51 lines in `make run` (each step, for
    each robot that needed one: up to 8 lines a second live)."""

    def __init__(self, period_s: float = PATH_SUMMARY_PERIOD_S) -> None:
        self.period_s = period_s
        self.sent: Counter[str] = Counter()  # paths (holds too) by robot, since the last line
        self.holds = 0
        self._last = -math.inf  # wall time of the last line
        self._at = (-1.0, 0)  # (t, frontiers left) of the last step noted

    def note(self, result: StepResult, frontiers: int) -> None:
        """A step's paths (`frontiers`: how many the explorer has left)."""
        over = [rid for rid, path in result.paths.items() if path is None and result.over]
        for rid, path in result.paths.items():
            if rid not in over:
                self.sent[rid] += 1
                self.holds += path is None
        t = max(result.inputs.stamps.values(), default=-1.0)
        self._at = (t, frontiers)
        if over:
            log.info("t=%.1f s: exploration over for %s (path 0 sent)", t, ", ".join(over))
        if over or time.monotonic() - self._last >= self.period_s:
            self.flush()

    def flush(self) -> None:
        """Sum up the paths sent since the last line, if any (also at the mission's end:
        else up to `period_s` of paths were never summed up)."""
        if not self.sent:
            return
        (t, frontiers), now = self._at, time.monotonic()
        since = "" if math.isinf(self._last) else f" in {now - self._last:.0f} s"
        log.info("t=%.1f s: %d paths sent%s (%s; %d of them holds), %d frontiers left", t,
                 self.sent.total(), since, ", ".join(f"{r} {n}" for r, n in
                 sorted(self.sent.items())), self.holds, frontiers)  # fmt: skip
        self.sent.clear()
        self.holds, self._last = 0, now


def run_step(explorer: ExplorationManager, inputs: StepInputs) -> StepResult:
    t0 = time.perf_counter()
    paths = explorer.step(inputs.grid, inputs.poses, blocked=inputs.blocked, strict=inputs.strict)
    return StepResult(inputs, paths, explorer.done, (time.perf_counter() - t0) * 1e3)


class ExplorationWorker:
    """Runs `run_step` on one worker thread (`start`), or at once (`now`: lock-step).
    A `--lockstep` base station whose simulator never asked paces itself by the wall
    clock on the worker too (its thread is made at the first `start`)."""

    def __init__(self, explorer: ExplorationManager) -> None:
        self.explorer = explorer
        self._pool = ThreadPoolExecutor(1, "exploration")
        self._pending: Future[StepResult] | None = None
        self.path_log = PathLog()
        self._closed = False

    def path_messages(
        self, result: StepResult, last_id: int, z: float
    ) -> list[tuple[str, int, PathMsg]]:
        """`path_messages` of a step's result (over: not in flight), summed up in the log."""
        self.path_log.note(result, len(self.explorer.frontiers))
        if self._closed:  # the step in flight at the end: the last paths summed up
            self.path_log.flush()
        return path_messages(result, last_id, z)

    @property
    def busy(self) -> bool:
        """A step is in flight: the explorer is the worker's."""
        return self._pending is not None

    def restore(self, paths: dict[str, bytes]) -> None:
        """Each robot's task from its last Path sent (`Recovered.paths`), after a restart."""
        for rid, payload in paths.items():
            wp = decode(payload, PathMsg, max_bytes=len(payload) + 1).waypoints
            if len(wp):
                self.explorer.restore_task(rid, np.asarray(wp[:, :2], dtype=np.float64))

    def now(self, inputs: StepInputs) -> StepResult:
        """A step on `inputs` on the caller's thread (none may be in flight)."""
        if self._pending is not None:
            raise RuntimeError("an exploration step is still in flight")
        return run_step(self.explorer, inputs)

    def start(self, inputs: StepInputs) -> None:
        """A step on `inputs`, on the worker; `done()` gives its result once it is over."""
        if self._pending is not None:
            raise RuntimeError("an exploration step is still in flight")
        self._pending = self._pool.submit(run_step, self.explorer, inputs)

    def done(self, wait: bool = False) -> StepResult | None:
        """The step in flight once it is over (`wait`: until then), else None; a step
        that raised raises here, on the caller's thread."""
        pending = self._pending
        if pending is None or not (wait or pending.done()):
            return None
        self._pending = None
        return pending.result()

    def close(self) -> StepResult | None:
        """Wait for the step in flight (returned) and stop the thread; the paths sent
        since the path log's last line are summed up (those of the step returned too)."""
        result = self.done(wait=True)
        self._pool.shutdown(wait=True)
        self._closed = True
        if result is None:  # (else once its paths are noted)
            self.path_log.flush()
        return result
