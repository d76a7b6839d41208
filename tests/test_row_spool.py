"""Rows recorded over a whole run stay on disk, not in the process's memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from agent.control_log import COLUMNS, ControlRecorder
from common.errors import ConfigError
from common.row_spool import RowSpool


def test_rows_come_back_as_appended() -> None:
    spool = RowSpool(3)
    assert spool.rows().shape == (0, 3)
    rows = np.random.default_rng(0).normal(size=(1000, 3))
    for r in rows:
        spool.append(r)
    assert len(spool) == 1000
    np.testing.assert_array_equal(spool.rows(), rows)
    spool.append([1.0, 2.0, 3.0])  # appending goes on after a read
    np.testing.assert_array_equal(spool.rows()[-1], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="3 numbers"):
        spool.append([1.0, 2.0])
    with pytest.raises(ConfigError):
        RowSpool(0)
    spool.close()


def test_a_control_tick_costs_no_memory() -> None:
    """An agent records a control row 40 times a second for the whole flight: 50,000
    rows (21 minutes) must not grow what the process holds (a list of them held
    ~300 bytes a row: 15 MB)."""
    rec = ControlRecorder()
    pose7 = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0])
    rec.add(0.0, pose7, pose7, pose7)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for k in range(1, 50_000):
            rec.add(k * 0.025, pose7, pose7, pose7)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 64 * 1024, grown
    log = rec.log()
    assert len(log) == 50_000 and log.T_map_odom_applied.shape == (50_000, 7)
    np.testing.assert_allclose(log.stamps[-1], 49_999 * 0.025)
    assert log.rows().shape[1] == COLUMNS
