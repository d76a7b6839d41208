"""iSAM2 update latencies over time, in constant memory per period (for soak runs).

`GlobalSlam` times every graph update; this keeps, per `period_s` of wall time, one
row [t_s, count, p50_ms, p95_ms, max_ms], where t_s is the end of the period in
seconds since the series started (wall, `time.monotonic`). Only the open period's
samples are held, so a long run adds one short row per period (180 rows for 30 min
at 10 s). `t0_unix` (time.time() at the start) lets a benchmark put the rows on its
own clock.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np


class UpdateSeries:
    def __init__(self, period_s: float = 10.0) -> None:
        self.period_s = float(period_s)
        self.t0 = time.monotonic()
        self.t0_unix = time.time()
        self.rows: list[list[float]] = []
        self._open: list[float] = []  # ms, samples of the period not closed yet
        self._open_end = self.period_s  # s since t0

    def add(self, ms: float, now: float | None = None) -> None:
        """One update that took `ms` milliseconds, finished at monotonic time `now`."""
        t = (time.monotonic() if now is None else now) - self.t0
        if t >= self._open_end:
            self._close()
            # skip idle periods: the next period is the one holding t
            self._open_end = (np.floor(t / self.period_s) + 1.0) * self.period_s
        self._open.append(float(ms))

    def _close(self) -> None:
        if self._open:
            self.rows.append(_row(self._open_end, self._open))
            self._open = []

    def to_json(self) -> dict[str, Any]:
        """{"period_s", "t0_unix", "columns", "rows"}; the open period included as a row
        ending now (without closing it)."""
        rows = list(self.rows)
        if self._open:
            rows.append(_row(min(self._open_end, time.monotonic() - self.t0), self._open))
        return {
            "period_s": self.period_s,
            "t0_unix": self.t0_unix,
            "columns": ["t_s", "count", "p50_ms", "p95_ms", "max_ms"],
            "rows": rows,
        }


def _row(t_s: float, samples: list[float]) -> list[float]:
    a = np.asarray(samples)
    p50, p95 = np.percentile(a, [50, 95])
    return [float(t_s), float(len(a)), float(p50), float(p95), float(a.max())]
