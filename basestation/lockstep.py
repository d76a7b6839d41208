"""The base station's side of a lock-step simulation's clock (simulation/simulator.py).

A lock-step simulator with exploration holds its clock every `exploration.period_s` of
sim time at a stamp T and asks the base station (`clock/sim`); the base station
answers T (`clock/basestation`) once it has taken everything the robots sent up to T,
verified, optimized, mapped and explored. So that the answer depends on the sim time
only, never on how loaded the machine is:

- the base station does nothing between two requests: keyframes wait in the inbox and
  candidates in the constraint builder's queues (no worker thread);
- at a request for T it first waits for every robot's `VehicleCommand` of stamp T and
  for what that command says the robot sent by then (its keyframes and its latest
  state), and for the GNSS fixes the request says the simulator sent: they come on
  other keys, whose order Zenoh does not keep between subscribers;
- it then takes all those keyframes in (robot, seq) order as one batch, verifies up to
  `max_candidates_per_s` x the period of waiting candidates, redraws the whole map and
  explores; then it tells each robot what it has sent it in all (`robot/<id>/clock`,
  DownlinkMark: paths, the latest correction epoch), which the agent waits for before
  its next tick once the simulator says that T was answered (agent/downlink_gate.py).

All that from the start (`collabslam run` starts the base station with `--lockstep`),
until the simulator's liveliness token goes away; without a request for
`basestation_timeout_s` (no simulator came) it processes keyframes as they arrive and
explores by the wall clock instead.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

from common.stamps import JumpGate
from protocol import ClockSync, DownlinkMark, VehicleCommand

log = logging.getLogger(__name__)

POLL_S = 0.002  # s: keyframes and states come on other subscribers than the commands
MAX_FIX_JUMP = 100_000  # GNSS fixes between two clock requests, at most


class LockstepClock:
    def __init__(self, active: bool, timeout_s: float) -> None:
        self.active = active  # a lock-step simulator with exploration is expected
        self.requested = self.answered = -1.0  # sim time
        self._wall_pacing_from = time.monotonic() + timeout_s if active else 0.0
        self.sim_gone = False  # the simulator's liveliness token went away
        self.input_timeouts = 0  # syncs answered without everything the robots sent
        self._commands: dict[str, VehicleCommand] = {}  # robot -> its latest command
        self._paths: dict[str, int] = {}  # robot -> Path messages sent to it
        self._epochs: dict[str, int] = {}  # robot -> the latest correction epoch sent to it
        self._fixes = self._fixes_due = 0  # GNSS fixes received / sent by the simulator
        self.takes_fixes = False  # the base station takes them (basestation.gps.enabled)
        self._fix_jump = JumpGate(MAX_FIX_JUMP)  # a count of fixes far past the last: held
        self._command_jumps: dict[str, JumpGate] = {}  # a command stamped far past its last
        self._jump = JumpGate()  # a request far past the last: held (one at 1e9 s had
        # been answered, and every real one after it taken as answered already)
        self._cond = threading.Condition()

    # --- Zenoh threads ------------------------------------------------------------------
    def on_request(self, msg: ClockSync, key: str) -> None:
        with self._cond:
            if self._jump.holds(msg.stamp, max(self.requested, 0.0)):
                log.error("clock request for t=%.3f, far past the last (t=%.3f): dropped "
                          "unless the next follows it", msg.stamp, self.requested)  # fmt: skip
                return
            self.requested = max(self.requested, msg.stamp)
            if self._fix_jump.holds(msg.gnss_fixes, self._fixes_due):  # (2^63 had had every
                log.error("clock request counts %d GNSS fixes, far past %d: not waited for "
                          "unless the next follows it", msg.gnss_fixes,
                          self._fixes_due)  # fmt: skip
            else:  # later sync wait for them, 10 s each)
                self._fixes_due = max(self._fixes_due, msg.gnss_fixes)
            self._cond.notify_all()

    def on_fix(self) -> None:
        with self._cond:
            self._fixes += 1

    def on_sim_alive(self, name: str, alive: bool) -> None:
        with self._cond:
            self.sim_gone |= not alive
            self._cond.notify_all()

    def on_command(self, msg: VehicleCommand, key: str) -> None:
        with self._cond:
            old = self._commands.get(msg.robot_id)
            gate = self._command_jumps.setdefault(msg.robot_id, JumpGate())
            last = max(self.requested, 0.0) if old is None else old.stamp  # (1e300 had been
            if gate.holds(msg.stamp, last):
                log.error("robot %s: command stamped %.6g, far past its last: dropped unless "
                          "the next follows it", msg.robot_id, msg.stamp)  # fmt: skip
            elif old is None or msg.stamp >= old.stamp:  # its latest for good, unnoticed)
                self._commands[msg.robot_id] = msg
            self._cond.notify_all()

    # --- the base station's thread ------------------------------------------------------
    def paced_by_sim(self) -> bool:
        """True while the simulator's requests alone pace the base station."""
        if not self.active or self.sim_gone:
            return False
        with self._cond:
            asked = self.requested > self.answered or self.answered >= 0.0
        return asked or time.monotonic() < self._wall_pacing_from

    def verify_on_worker(self, now: float) -> bool:
        """Candidates are verified on the constraint builder's thread, except in lock-step
        simulation (or while its simulator is awaited)."""
        return (
            not self.active or self.answered >= 0.0 or now >= self._wall_pacing_from
            or self.sim_gone  # (gone before its first request: a Ctrl-C took a minute)
        )  # fmt: skip

    def wall_paced(self, now: float) -> bool:
        """No lock-step simulator (or none has asked in time): explore by the wall clock."""
        return self.answered < 0.0 and now >= self._wall_pacing_from

    def wait_request(self, timeout_s: float) -> float | None:
        """The stamp of a request not answered yet, waiting up to `timeout_s` for one."""
        with self._cond:
            if self.requested <= self.answered:
                self._cond.wait(timeout_s)
            return self.requested if self.requested > self.answered else None

    def wait_inputs(
        self,
        stamp: float,
        robots: Iterable[str],
        received: Callable[[str], tuple[int, float]],
        timeout_s: float,
    ) -> list[str]:
        """Wait until each of `robots` has commanded at `stamp` and everything its command
        says it sent is in (`received(robot)`: keyframes received, the latest state's
        stamp), and the GNSS fixes the simulator sent; returns what is still missing after
        `timeout_s` (wall)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = [r for r in sorted(robots) if not self._in(r, stamp, received)]
                if self.takes_fixes and self._fixes < self._fixes_due:
                    missing.append(f"GNSS ({self._fixes} of {self._fixes_due} fixes)")
                rest = deadline - time.monotonic()
                if not missing or rest <= 0.0:
                    self.input_timeouts += bool(missing)  # (the run may not repeat)
                    return missing
                self._cond.wait(min(rest, POLL_S))

    def _in(self, robot: str, stamp: float, received: Callable[[str], tuple[int, float]]) -> bool:
        cmd = self._commands.get(robot)
        if cmd is None or cmd.stamp < stamp - 1e-9:
            return False
        keyframes, state_stamp = received(robot)
        return keyframes >= cmd.keyframes_sent and state_stamp >= cmd.state_stamp - 1e-9

    # --- what went down to each robot ---------------------------------------------------
    def sent_path(self, robot: str) -> None:
        self._paths[robot] = self._paths.get(robot, 0) + 1

    def sent_correction(self, robot: str, epoch: int) -> None:
        self._epochs[robot] = epoch

    def mark(self, robot: str, stamp: float) -> DownlinkMark:
        return DownlinkMark(robot, stamp, self._paths.get(robot, 0), self._epochs.get(robot, -1))


__all__ = ["LockstepClock"]
