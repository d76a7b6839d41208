"""The base station's log of the paths it sends: each path a DEBUG line, an INFO line
that sums them up at the first step, then at most every `PATH_SUMMARY_PERIOD_S`, and
when exploration is over for a robot (a line per path had been 43 of the base
station's 51 lines in `make run`)."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from basestation.exploration_worker import (
    ExplorationWorker,
    PathLog,
    StepInputs,
    StepResult,
    path_messages,
)


def _result(paths: dict[str, np.ndarray | None], over: bool = False, t: float = 1.0) -> StepResult:
    poses = {rid: np.array([1.0, 2.0, 0.0]) for rid in paths}
    inputs = StepInputs(None, None, poses, set(), {rid: t for rid in paths}, 0)  # type: ignore[arg-type]
    return StepResult(inputs, paths, over, 1.0)


def _infos(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]


def test_each_path_is_a_debug_line_not_an_info_line(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="basestation.node")
    way = np.array([[1.0, 2.0], [3.0, 2.0]])
    last = 0
    for k in range(20):  # 20 steps of 3 drones: 60 paths
        msgs = path_messages(_result({"r0": way, "r1": way, "r2": None}, t=k), last, 1.0)
        last += len(msgs)
    assert last == 60 and not _infos(caplog)
    debug = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG]
    assert len(debug) == 60 and "path 60 for r2 from (1.0, 2.0): hold" in debug[-1]


def test_the_paths_are_summed_up_at_the_first_step_then_each_period_and_at_the_end(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="basestation.node")
    paths = PathLog(period_s=3600.0)
    way = np.array([[1.0, 2.0], [3.0, 2.0]])
    paths.note(_result({"r0": way, "r1": way}, t=0.0), frontiers=5)
    assert _infos(caplog) == [
        "t=0.0 s: 2 paths sent (r0 1, r1 1; 0 of them holds), 5 frontiers left"
    ]
    caplog.clear()
    for k in range(1, 30):  # within the period: nothing at INFO
        paths.note(_result({"r0": way, "r1": None}, t=float(k)), frontiers=3)
    assert not _infos(caplog)
    paths.note(_result({"r0": None, "r1": None}, over=True, t=30.0), frontiers=0)
    over, summary = _infos(caplog)
    assert over == "t=30.0 s: exploration over for r0, r1 (path 0 sent)"
    assert summary.startswith("t=30.0 s: 58 paths sent in ")
    assert summary.endswith(" s (r0 29, r1 29; 29 of them holds), 0 frontiers left")
    caplog.clear()
    paths.period_s = 0.0  # a period gone by: the next step is summed up
    paths.note(_result({"r2": way}, t=31.0), frontiers=1)
    assert len(_infos(caplog)) == 1 and "1 paths sent in" in _infos(caplog)[0]


def test_the_paths_since_the_last_line_are_summed_up_at_the_end(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A mission that ends without exploration over (its time up): the paths sent since
    the last line are summed up once more (else up to a period's were never told)."""
    caplog.set_level(logging.INFO, logger="basestation.node")
    paths = PathLog(period_s=3600.0)
    way = np.array([[1.0, 2.0], [3.0, 2.0]])
    paths.note(_result({"r0": way}, t=0.0), frontiers=5)
    for k in range(1, 4):
        paths.note(_result({"r0": way, "r1": None}, t=float(k)), frontiers=4)
    assert len(_infos(caplog)) == 1
    paths.flush()
    last = _infos(caplog)[-1]
    assert last.startswith("t=3.0 s: 6 paths sent in ")
    assert last.endswith(" s (r0 3, r1 3; 3 of them holds), 4 frontiers left")
    paths.flush()  # nothing new: no line
    assert len(_infos(caplog)) == 2
    caplog.clear()
    worker = ExplorationWorker(SimpleNamespace(frontiers=[1, 2]))  # type: ignore[arg-type]
    worker.path_log.period_s = 3600.0
    for k in range(3):
        worker.path_messages(_result({"r0": way}, t=float(k)), k, 1.0)
    assert worker.close() is None  # the mission's end (basestation/node.py `drain`)
    assert [m[:25] for m in _infos(caplog)] == [
        "t=0.0 s: 1 paths sent (r0",
        "t=2.0 s: 2 paths sent in ",
    ]
