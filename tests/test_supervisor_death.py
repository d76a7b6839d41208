"""A process `collabslam run` started stops when `run` dies, even by SIGKILL (its
children had stayed up, orphaned, using CPU): it is sent SIGHUP."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from collabslam.supervisor import SUPERVISOR_ENV

# the supervisor: starts one child as ProcessGroup does (own session, its pid in the
# environment), prints the child's pid, then waits to be killed
SUPERVISOR = f"""
import os, subprocess, sys, time
child = subprocess.Popen(
    [sys.executable, "-c", {{child!r}}], start_new_session=True,
    env=dict(os.environ, {SUPERVISOR_ENV}=str(os.getpid())),
)
print(child.pid, flush=True)
time.sleep(60)
"""
CHILD = """
import signal, sys, time
from common.shutdown import stop_with_supervisor
signal.signal(signal.SIGHUP, lambda *a: (open(sys.argv[1], "a").write("SIGHUP"), sys.exit(0)))
stop_with_supervisor()
time.sleep(60)
"""


def test_a_child_gets_sigterm_when_its_supervisor_is_killed(tmp_path: Path) -> None:
    mark = tmp_path / "mark"
    child = CHILD.replace("sys.argv[1]", repr(str(mark)))
    sup = subprocess.Popen(
        [sys.executable, "-c", SUPERVISOR.format(child=child)],
        stdout=subprocess.PIPE,
        cwd=Path(__file__).resolve().parents[1],
        env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])),
    )
    assert sup.stdout is not None
    pid = int(sup.stdout.readline())
    time.sleep(2.0)  # the child has imported and called prctl
    assert not mark.exists()
    sup.send_signal(signal.SIGKILL)
    sup.wait(10)
    sup.stdout.close()
    deadline = time.monotonic() + 10.0
    while not (mark.exists() and mark.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)  # (made, then written: read between, it had been empty)
    try:
        assert mark.read_text().startswith("SIGHUP")  # told to stop, as by a first Ctrl-C
    finally:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
