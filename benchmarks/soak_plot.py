"""The picture of `bench soak`: memory, outboxes and iSAM2 latencies over wall time.

Panels: (a) base-station RSS and the largest agent RSS (MB); dotted lines mark the
mission's start (first sim tick) and end (simulator exit); (b) the base station's
CPU use (cores) and the machine's load average; (c) every robot's outbox length
(largest per sample; gaps: no state received); (d) iSAM2 update latency per
period (p50, p95, max; ms, log scale). Agg canvas, no pyplot.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def _xy(series: list[list[float]], col: int = 1) -> tuple[np.ndarray, np.ndarray]:
    a = np.array(series, dtype=np.float64)
    if a.size == 0:
        return np.zeros(0), np.zeros(0)
    return a[:, 0], a[:, col]


def plot_soak(result: dict[str, Any], path: Path) -> None:
    """Write the three-panel PNG for a `bench soak` result dict."""
    fig = Figure(figsize=(9.0, 11.0))
    FigureCanvasAgg(fig)
    ax_mem, ax_cpu, ax_box, ax_upd = fig.subplots(
        4, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.5, 3, 3]}
    )

    t, mb = _xy(result["rss_mb"])
    ax_mem.plot(t, mb, color="tab:blue", lw=1.2, label="base station")
    if result.get("rss_anon_mb"):
        t, mb = _xy(result["rss_anon_mb"])
        ax_mem.plot(t, mb, color="tab:blue", lw=0.8, ls="--", label="base station, anonymous")
    t, mb = _xy(result["agent_rss_max_mb"])
    ax_mem.plot(t, mb, color="tab:orange", lw=1.0, label="largest agent")
    slope = result.get("rss_growth_mb_per_min_second_half")
    slope_txt = "n/a" if slope is None else f"{slope:+.2f} MB/min"
    anon = result.get("rss_anon_growth_mb_per_min_second_half")
    slope_txt += "" if anon is None else f" ({anon:+.2f} anonymous)"
    ax_mem.set_title(
        f"{result['robots']} robots, {result['sim_minutes']:g} sim min on {result['world']}: "
        f"base peak {result['rss_peak_mb']:.0f} MB, 2nd-half growth {slope_txt}",
        fontsize=9,
    )
    ax_mem.set_ylabel("resident memory (MB)")

    t, cores = _xy(result["basestation_cpu"])
    ax_cpu.plot(t, cores, color="tab:blue", lw=1.0)
    ax_cpu.set_ylabel("base station\nCPU (cores)", color="tab:blue")
    ax_cpu.set_ylim(bottom=0.0)
    ax_load = ax_cpu.twinx()
    t, load = _xy(result["basestation_cpu"], col=2)
    ax_load.plot(t, load, color="0.5", lw=1.0)
    ax_load.set_ylabel("load average", color="0.5")
    ax_load.set_ylim(bottom=0.0)

    box = result["outbox_series"]
    for rid, n in box.items():
        if rid != "t_s":
            y = np.array([np.nan if v is None else v for v in n], dtype=np.float64)
            ax_box.step(box["t_s"], y, where="post", lw=0.8, label=rid)
    ax_box.set_ylabel("outbox length\n(keyframes)")
    if len(box) <= 11:
        ax_box.legend(loc="upper left", fontsize=7, ncol=5)

    upd = np.array(result["update_ms"], dtype=np.float64).reshape(-1, 4)
    for col, name, color in ((1, "p50", "tab:green"), (2, "p95", "tab:red"), (3, "max", "0.5")):
        ax_upd.semilogy(upd[:, 0], np.maximum(upd[:, col], 1e-3), ".-", ms=3, lw=0.8,
                        color=color, label=name)  # fmt: skip
    ax_upd.set_ylabel(f"iSAM2 update (ms)\nper {result.get('update_period_s') or '?'} s")
    ax_upd.set_xlabel("wall time since start (s)")

    for ax in (ax_mem, ax_cpu, ax_box, ax_upd):
        for t_mark in result.get("mission_wall_s") or []:  # mission start and end
            ax.axvline(t_mark, color="k", ls=":", lw=0.8)
        ax.grid(True, alpha=0.3)
    ax_mem.legend(loc="upper left", fontsize=8)
    ax_upd.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, format="png")
