"""In a lock-step simulation, holds a tick until what the base station sent for it is in.

Paths, corrections and neighbour answers reach the agent from the base station, and
the ticks (sensor messages) from the simulator: two senders, and on a loaded machine
either may come first, so a path could start a tick early or late. When the base
station has answered the simulator's clock at T, the simulator says so on the agent's
sensor topics (`robot/<id>/sensor/clock`, ClockSync from "sim"; one subscriber keeps
them in order, so before the next tick's scan), and the base station tells the agent
what it sent by then (`robot/<id>/clock`, DownlinkMark: paths sent in all, the latest
correction epoch; basestation/lockstep.py). Before a tick the agent waits until it has
those, and the base station's answer (`Neighbours`) to the last state it sent.
Without a lock-step simulator no such ClockSync comes and nothing waits.
"""

from __future__ import annotations

import logging
import threading

from common.stamps import JumpGate
from protocol import DownlinkMark

log = logging.getLogger(__name__)


class DownlinkGate:
    def __init__(self, timeout_s: float, resumed: bool = False) -> None:
        """`resumed`: this agent goes on from one before it (agent/resume.py): the first
        mark's counts include what was sent to that one, which this one never gets (it
        had waited `timeout_s` at every step for it: a mission at 0.14x real time)."""
        self.timeout_s = timeout_s  # s wall, then go on (and stop waiting for neighbours)
        self._resumed = resumed
        self._due = -1.0  # the latest clock the base station answered, by the simulator
        self._clock = 0.0  # the latest such clock (not reset: `_clock_jump` compares to it)
        self._clock_jump = JumpGate()  # one at 1e9 s had every tick wait `timeout_s`
        self._mark: DownlinkMark | None = None  # the base station's latest
        self._mark_jump = JumpGate()
        self._paths = 0  # Path messages received
        self._epoch = -1  # the latest correction's epoch received
        self._state_sent = -1.0  # stamp of the latest state sent
        self._answered = -1.0  # stamp of the latest Neighbours answer
        self._neighbours = True  # wait for them (off after one never came)
        self.waits = self.timeouts = 0
        self._cond = threading.Condition()

    # --- Zenoh threads ------------------------------------------------------------------
    def on_mark(self, mark: DownlinkMark, key: str = "") -> None:
        with self._cond:
            # one stamped far ahead had been kept for good, and every tick waited for it
            last = self._clock if self._mark is None else max(self._mark.stamp, self._clock)
            if self._mark_jump.holds(mark.stamp, last):
                log.error("downlink mark stamped %.6g, far past the last: dropped unless "
                          "the next follows it", mark.stamp)  # fmt: skip
                return
            if self._resumed:  # counted from the first: what came before is not for us
                self._resumed = False
                self._paths, self._epoch = (
                    max(self._paths, mark.paths),
                    max(self._epoch, mark.epoch),
                )
            if self._mark is None or mark.stamp >= self._mark.stamp:
                self._mark = mark
            self._cond.notify_all()

    def on_path(self) -> None:
        with self._cond:
            self._paths += 1
            self._cond.notify_all()

    def on_correction(self, epoch: int) -> None:
        with self._cond:
            self._epoch = max(self._epoch, epoch)
            self._cond.notify_all()

    def on_neighbours(self, stamp: float) -> None:
        with self._cond:
            self._answered = max(self._answered, stamp)
            self._cond.notify_all()

    # --- the agent's thread (in order with the ticks) -----------------------------------
    def on_clock(self, stamp: float) -> None:
        """The simulator: the base station has answered its clock at `stamp`."""
        with self._cond:
            if self._clock_jump.holds(stamp, self._clock):
                log.error("simulator clock t=%.3f is far past t=%.3f: dropped unless the "
                          "next follows it", stamp, self._clock)  # fmt: skip
                return
            self._clock = max(self._clock, stamp)
            self._due = max(self._due, stamp)

    def state_sent(self, stamp: float) -> None:
        with self._cond:
            self._state_sent = stamp

    def _marked(self) -> bool:
        m = self._mark
        return (
            m is not None
            and m.stamp >= self._due
            and self._paths >= m.paths
            and (self._epoch >= m.epoch)
        )

    def _ready(self) -> bool:
        neighbours = not self._neighbours or self._answered >= self._state_sent
        return self._marked() and neighbours

    def wait(self) -> None:
        """Before a new tick: wait until the base station's downlink for it is in."""
        with self._cond:
            if self._due < 0.0 or self._ready():  # no lock-step simulator, or all in
                return
            self.waits += 1
            if self._cond.wait_for(self._ready, self.timeout_s):
                return
            self.timeouts += 1
            if not self._marked():
                log.warning(
                    "lock-step: what the base station sent by t=%.3f is not all in after "
                    "%.0f s (mark %s, %d paths, epoch %d); going on",
                    self._due,
                    self.timeout_s,
                    self._mark,
                    self._paths,
                    self._epoch,
                )
                self._due = -1.0  # until the simulator's next word
            else:
                log.warning(
                    "lock-step: no neighbours' answer to the state of t=%.3f in %.0f s; "
                    "not waiting for them any more (runs may not repeat)",
                    self._state_sent,
                    self.timeout_s,
                )
                self._neighbours = False


__all__ = ["DownlinkGate"]
