"""Graceful shutdown (uvicorn's capture_signals): the first SIGINT/SIGTERM asks the
process to drain and persist; a second one forces exit."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from types import FrameType

log = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def install_signal_handlers(stop: threading.Event) -> None:
    """Set `stop` on the first SIGINT/SIGTERM; exit at once (code 130) on the second."""

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            log.warning("second %s: forcing exit", signal.Signals(signum).name)
            os._exit(130)
        log.info("%s received: shutting down (send again to force)", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    # the supervisor died (`stop_with_supervisor`; it may come more than once): drain
    signal.signal(signal.SIGHUP, lambda signum, frame: stop.set())


def stop_with_supervisor(env_var: str = "COLLABSLAM_SUPERVISOR_PID") -> None:
    """In a process `collabslam run` started: be sent SIGHUP when it dies (Linux
    PR_SET_PDEATHSIG), so none is left running on its own when `run` is killed (its
    children had stayed up, orphaned, after a SIGKILL or a second Ctrl-C). SIGHUP
    stops the process as a first Ctrl-C does; it came twice in a row, and a second
    SIGTERM would have forced an exit without outputs."""
    parent = os.environ.get(env_var)
    if not parent or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGHUP)
    except (OSError, AttributeError) as exc:  # no prctl: outlives it, as before
        log.warning("cannot tie this process to its supervisor: %s", exc)
        return
    if os.getppid() != int(parent):  # it died before prctl took effect
        os.kill(os.getpid(), signal.SIGHUP)
