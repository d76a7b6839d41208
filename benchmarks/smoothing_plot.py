"""The picture of `bench smoothing`, like seed 000 Fig. 1: the control pose with
and without the smoothing filter around a loop closure.

Panels: (a) map-frame x and y over the whole flight, raw vs. filtered; (b) a
zoom on the largest correction jump (its shift of the control pose); (c) the
per-tick step beyond the robot's own motion (m, log scale), raw vs. filtered.
Agg canvas, no pyplot.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from agent.control_log import ControlLog, control_positions, correction_steps

RAW, FILTERED = "tab:red", "tab:blue"


def plot_smoothing(ctl: ControlLog, path: Path, title: str = "", zoom_s: float = 10.0) -> None:
    """Write the three-panel PNG for one robot's control log."""
    t = ctl.stamps - ctl.stamps[0]
    raw = control_positions(ctl.T_map_odom_raw, ctl.T_odom_base)
    fil = control_positions(ctl.T_map_odom_applied, ctl.T_odom_base)
    step_raw, _ = correction_steps(ctl.T_map_odom_raw, ctl.T_odom_base)
    step_fil, _ = correction_steps(ctl.T_map_odom_applied, ctl.T_odom_base)
    k = int(np.argmax(step_raw)) + 1 if len(step_raw) else 0

    fig = Figure(figsize=(9.0, 9.0))
    FigureCanvasAgg(fig)
    ax_full, ax_zoom, ax_step = fig.subplots(3, 1)
    for axis, style in ((0, "-"), (1, "--")):
        name = "xy"[axis]
        ax_full.plot(t, raw[:, axis], style, color=RAW, lw=1.0, label=f"{name} raw")
        ax_full.plot(t, fil[:, axis], style, color=FILTERED, lw=1.0, label=f"{name} filtered")
    ax_full.set_ylabel("position in map (m)")
    ax_full.legend(loc="best", fontsize=8, ncol=2)
    ax_full.set_title(title or "control pose", fontsize=10)

    # Zoom: the shift the corrections put into the control pose relative to the
    # correction held just before the largest jump (the robot's own motion removed),
    # along the jump's direction: a step (raw) against the eq. 2 sigmoid (filtered).
    sel = (t >= t[k] - 0.2 * zoom_s) & (t <= t[k] + zoom_s)
    before = np.repeat(ctl.T_map_odom_raw[max(k - 1, 0)][None], int(sel.sum()), axis=0)
    base = control_positions(before, ctl.T_odom_base[sel])
    shift_raw, shift_fil = raw[sel] - base, fil[sel] - base
    u = shift_raw[-1] / max(float(np.linalg.norm(shift_raw[-1])), 1e-12)
    ax_zoom.plot(t[sel], shift_raw @ u, ".-", color=RAW, ms=2, lw=0.8, label="raw")
    ax_zoom.plot(t[sel], shift_fil @ u, ".-", color=FILTERED, ms=2, lw=0.8, label="filtered")
    ax_zoom.set_ylabel("correction shift of\nthe control pose (m)")
    ax_zoom.set_title(f"largest correction jump, t = {t[k]:.2f} s", fontsize=9)
    ax_zoom.legend(loc="best", fontsize=8)

    floor = 1e-5
    ax_step.semilogy(t[1:], np.maximum(step_raw, floor), color=RAW, lw=0.8, label="raw")
    ax_step.semilogy(t[1:], np.maximum(step_fil, floor), color=FILTERED, lw=0.8, label="filtered")
    ax_step.set_ylim(floor, max(1.0, float(step_raw.max(initial=0.0)) * 2))
    ax_step.set_ylabel("step per tick beyond\nown motion (m)")
    ax_step.set_xlabel("time (s)")
    ax_step.legend(loc="best", fontsize=8)
    for ax in (ax_full, ax_zoom, ax_step):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, format="png")
