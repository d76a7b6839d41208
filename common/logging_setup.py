"""Logging configuration; only entry points call `setup_logging`.

A process with a simulation clock (a lock-step base station) gives it to
`set_sim_clock`: its DEBUG lines then say the sim time they are about (`t=12.0 s:`),
which wall-clock stamps cannot tell in a run paced by the simulator.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable

_sim_clock: Callable[[], float | None] | None = None


def set_sim_clock(clock: Callable[[], float | None] | None) -> None:
    """`clock()`: the sim time now (None: none yet); None: no sim time in the lines."""
    global _sim_clock
    _sim_clock = clock


class SimTimeFilter(logging.Filter):
    """Puts the sim time before the message of DEBUG lines (see the module doc)."""

    def filter(self, record: logging.LogRecord) -> bool:
        t = _sim_clock() if _sim_clock is not None and record.levelno <= logging.DEBUG else None
        if t is not None and not getattr(record, "sim_time_set", False):
            record.msg, record.sim_time_set = f"t={t:.1f} s: {record.msg}", True
        return True


def setup_logging(level: str = "INFO", name: str = "") -> None:
    """One line per record on stderr, tagged with the process role."""
    tag = f"[{name}] " if name else ""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s %(levelname)s {tag}%(name)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )
    for handler in logging.getLogger().handlers:
        handler.addFilter(SimTimeFilter())
    for noisy in ("numba", "matplotlib", "PIL"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    # Zenoh's own lines on a refused TLS link (an expired certificate, another CA's, a
    # host name not in it: "invalid peer certificate: Expired") on stderr too, plain
    # text: nothing else says why a drone never reaches the base station (RUST_LOG, if
    # set, decides instead)
    os.environ.setdefault("NO_COLOR", "1")
    import zenoh

    zenoh.init_log_from_env_or("zenoh_link_tls=warn")


def worth_logging(before: int) -> bool:
    """Whether to log the next of a repeated message, `before` of it so far: the 1st, the
    10th, the 100th and every 1000th (a driver's jittery stamps had written an error line
    for every message)."""
    return before in (0, 9, 99) or (before + 1) % 1000 == 0
