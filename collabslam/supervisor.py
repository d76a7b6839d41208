"""Starts collabslam processes and watches them (used by `run` and `eval carmen`).

Each child is `python -m collabslam.cli ...` in its own session (so a terminal
Ctrl-C reaches only the parent, which stops children in order), with its output
in `<out>/logs/<name>.log`. A child that exits with an error is named in a
ProcessError pointing at its log.
"""

from __future__ import annotations

import logging
import os
import random
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from common.errors import ProcessError

log = logging.getLogger(__name__)


# Listening ports come from outside the kernel's ephemeral range: a port the kernel hands
# out for bind(0) goes back to that range once the probe closes, and an outgoing
# connection of any process (another mission's agents beside this one) may be given it
# before our listener binds it ("Address already in use": two bench batches at once).
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_LOWEST_PORT = 10000


def _listen_port_ranges() -> list[range]:
    """Ports for listeners: above _LOWEST_PORT, outside the ephemeral range."""
    try:
        lo, hi = (int(v) for v in _EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        lo, hi = 32768, 60999  # Linux's default
    spans = [range(_LOWEST_PORT, lo), range(hi + 1, 65536)]
    return [r for r in spans if len(r) > 0] or [range(_LOWEST_PORT, 65536)]


def free_ports(n: int) -> list[int]:
    """n distinct loopback TCP ports nothing listens on now, chosen at random outside the
    kernel's ephemeral range (see above), so two missions started at once on one
    machine do not take each other's (or their connections') ports."""
    ranges = _listen_port_ranges()
    weights = [len(r) for r in ranges]
    rng = random.SystemRandom()
    out: list[int] = []
    for _ in range(200 * n):
        if len(out) == n:
            return out
        port = rng.choice(rng.choices(ranges, weights)[0])
        if port in out:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        out.append(port)
    raise ProcessError(f"no {n} free loopback ports found outside the ephemeral range")


def free_port() -> int:
    """One port of `free_ports`."""
    return free_ports(1)[0]


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_file: IO[bytes]


# a child given this (its supervisor's pid) stops (SIGTERM) when the supervisor dies,
# even by SIGKILL or a second Ctrl-C (`common.shutdown.stop_with_supervisor`)
SUPERVISOR_ENV = "COLLABSLAM_SUPERVISOR_PID"


# what a mission writes into its --out folder: deleted before the next mission there, so
# none is read as this mission's (a 10 s tour had reported the exploration's time_to_95_s
# from an earlier run's map history, and an old segment's r0~2.tum had made r0's ATE 4 m)
RUN_OUTPUTS = (
    "agents", "control_poses", "ground_truth", "local_trajectories", "logs", "trajectories",
    "basestation.json", "simulator.json", "summary.json", "map.pgm", "map.yaml", "map.png",
    "map_history.npz", "trajectory.tum",
)  # fmt: skip


RUN_MARKER = ".collabslam-run"  # in a folder a mission wrote into


def clear_run_outputs(out: Path) -> None:
    """Delete an earlier mission's outputs in ``out``: those names only, and only in a
    folder that holds a mission's marker (`--out .` in a user's own folder keeps its
    `logs/`); then mark the folder as this mission's."""
    if not (out / RUN_MARKER).is_file():
        (out / RUN_MARKER).write_text("outputs of collabslam missions: replaced by the next\n")
        return
    for name in RUN_OUTPUTS:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def delete_database(path: str | Path) -> None:
    """A mission never resumes an older one's: its database (and SQLite's WAL files)
    goes first. An `eval carmen` run again on one `basestation.db_path` had restored the
    last run's robots, mapped this run's as seg0~2, ... onto the old map, and scored the
    old trajectories."""
    for suffix in ("", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


class ProcessGroup:
    def __init__(self, out: Path, log_level: str = "INFO") -> None:
        self.out = out
        self.log_level = log_level
        self.children: list[Child] = []

    def spawn(self, name: str, args: list[str]) -> Child:
        logs = self.out / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        f = open(logs / f"{name}.log", "wb")  # noqa: SIM115 - closed in terminate_all
        cmd = [sys.executable, "-m", "collabslam.cli", "--log-level", self.log_level, *args]
        proc = subprocess.Popen(
            cmd,
            stdout=f,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1", **{SUPERVISOR_ENV: str(os.getpid())}),
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        child = Child(name, proc, f)
        self.children.append(child)
        log.info("started %s (pid %d)", name, proc.pid)
        return child

    def died(self, c: Child, rc: int) -> str:
        return (
            f"{c.name} (pid {c.proc.pid}) exited with code {rc}; "
            f"see {self.out / 'logs' / (c.name + '.log')}"
        )

    def check(self, children: list[Child]) -> None:
        """Raise if any of `children` has exited (they should still be running)."""
        for c in children:
            rc = c.proc.poll()
            if rc is not None:
                raise ProcessError(self.died(c, rc))

    def wait(self, children: list[Child], timeout: float) -> None:
        """Wait for children to exit with code 0."""
        deadline = time.monotonic() + timeout
        for c in children:
            try:
                rc = c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise ProcessError(f"{c.name} did not stop within {timeout:.0f} s") from None
            if rc != 0:
                raise ProcessError(self.died(c, rc))

    def wait_all_or_fail(
        self, finishing: list[Child], running: list[Child], timeout: float, poll_s: float = 0.2
    ) -> None:
        """Wait until every child in `finishing` exits 0 while `running` stay up."""
        deadline = time.monotonic() + timeout
        pending = list(finishing)
        while pending:
            if time.monotonic() > deadline:
                raise ProcessError(f"{pending[0].name} did not finish within {timeout:.0f} s")
            for c in list(pending):
                rc = c.proc.poll()
                if rc is not None:
                    if rc != 0:
                        raise ProcessError(self.died(c, rc))
                    pending.remove(c)
            self.check(running)
            time.sleep(poll_s)

    def terminate_all(self) -> None:
        for c in self.children:
            if c.proc.poll() is None:
                log.warning("killing %s", c.name)
                c.proc.kill()
                c.proc.wait()
            c.log_file.close()
