"""Log lines: a lock-step base station's DEBUG lines say the sim time of their step
(before, only wall-clock stamps, which a simulator-paced run cannot be read by)."""

from __future__ import annotations

import io
import logging

from common.logging_setup import SimTimeFilter, set_sim_clock


def test_debug_lines_carry_the_sim_time() -> None:
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.addFilter(SimTimeFilter())  # as `setup_logging` adds it
    log = logging.getLogger("test.sim_time")
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    log.propagate = False
    try:
        set_sim_clock(lambda: 12.34)
        log.debug("robot %s: no path", "r0")
        log.info("a path")  # INFO lines say it themselves where it matters
        set_sim_clock(lambda: None)  # no step yet
        log.debug("before the clock")
    finally:
        set_sim_clock(None)
        log.removeHandler(handler)
    assert out.getvalue().splitlines() == ["t=12.3 s: robot r0: no path", "a path",
                                           "before the clock"]  # fmt: skip
