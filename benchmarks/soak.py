"""`collabslam bench soak`: a long mission with many robots, watched over time.

The mission is a real `collabslam run` (simulator, base station and one agent per
robot as separate processes over loopback Zenoh) flying scripted tours
(`exploration.enabled = false`: an exploring team stops when no frontier is left),
each long enough for the whole sim time at cruise speed. While it runs, every
`sample_s` of wall time the bench records:

- the base station's resident memory (VmRSS of its process, MB; and RssAnon, the part
  not backed by a file) and the agents' (the largest of them);
- each robot's outbox length (from the RobotState every agent publishes each
  `agent.state_period_s` of sim time; the bench joins the fleet's Zenoh network as
  a client of the base station once it listens, which takes a few seconds, so the
  first seconds of sim time may be missing): the largest value seen since the
  previous sample. `outbox_high_water` also takes each agent's own count;
- the sim time and the keyframes acknowledged so far (sum over robots).

After the run it adds the base station's iSAM2 update latencies per
`basestation.update_series_period_s` of wall time (basestation.json), the
keyframe counts and the map accuracy (summary.json).

"Memory flat": `rss_growth_mb_per_min_second_half` is the slope of a straight
line fitted to the base station's RSS over the second half of the mission
(`mission_wall_s`: from the first sim tick the bench sees to the simulator's exit;
process start-up, imports and tour planning come before it). The base station keeps every
keyframe's node in iSAM2 (its scan only in a bounded cache, older ones in the database),
so it must grow with the keyframes;
`rss_mb_per_1000_keyframes_second_half` gives that slope per keyframe for comparison;
the `rss_anon_*` keys the same for the anonymous part: the base station keeps its
per-keyframe arrays in memory-mapped files (common/growable.py), whose pages count in
VmRSS while they are cached but which the kernel writes back and drops when it needs
the memory (docs/architecture.md "Soak benchmark" has the measured numbers).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.soak_plot import plot_soak
from collabslam.launcher import Launcher
from collabslam.supervisor import Child
from common.bus import Bus
from common.config import Config
from common.config_validation import validate
from common.errors import CollabSlamError, ConfigError
from protocol import RobotState

log = logging.getLogger(__name__)

TOUR_MARGIN = 1.1  # tour length = margin * sim time * cruise speed


def rss_mb(pid: int) -> tuple[float, float, float] | None:
    """(VmRSS, VmHWM, RssAnon) of a process in MB (resident now, peak resident, resident
    and not backed by a file: what the kernel cannot drop); None if gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    kb = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM", "RssAnon"):
            kb[key] = float(value.split()[0])
    if "VmRSS" not in kb:
        return None  # a zombie
    rss = kb["VmRSS"]
    return rss / 1024.0, kb.get("VmHWM", rss) / 1024.0, kb.get("RssAnon", rss) / 1024.0


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far (s); None if it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (float(fields[11]) + float(fields[12])) / os.sysconf("SC_CLK_TCK")


def slope_per_min(series: list[list[float]], t0: float, t1: float) -> float | None:
    """Least-squares slope (per minute) of [t_s, value] samples with t0 <= t <= t1."""
    a = np.array([p for p in series if t0 <= p[0] <= t1], dtype=np.float64).reshape(-1, 2)
    if len(a) < 3 or np.ptp(a[:, 0]) <= 0.0:
        return None
    return float(np.polyfit(a[:, 0], a[:, 1], 1)[0] * 60.0)


def soak_config(cfg: Config, sim_minutes: float) -> Config:
    """Scripted tours long enough for the sim time at cruise speed."""
    c = copy.deepcopy(cfg)
    c.exploration.enabled = False
    c.sim.tour_length_m = TOUR_MARGIN * 60.0 * sim_minutes * c.agent.cruise_speed_mps
    validate(c)
    return c


class StateWatcher:
    """Joins the fleet at the base station's endpoint; keeps every robot's outbox
    length (largest since the last `take`), its keyframes acknowledged and sim time."""

    def __init__(self, cfg: Config, endpoint: str) -> None:
        zc = dataclasses.replace(
            cfg.zenoh, mode="client", listen=[], connect=[endpoint], config_file=""
        )
        self.bus = Bus(zc, cfg.fleet, cfg.protocol.max_message_bytes)
        self._lock = threading.Lock()
        self.window_max: dict[str, int] = {}
        self.high_water: dict[str, int] = {}
        self.acked: dict[str, int] = {}
        self.sim_s = 0.0
        self.messages = 0
        self.bus.subscribe(self.bus.keys.all_robots("state"), RobotState, self._on_state)

    def _on_state(self, msg: RobotState, key: str) -> None:
        with self._lock:
            rid, n = msg.robot_id, int(msg.outbox_len)
            self.window_max[rid] = max(self.window_max.get(rid, 0), n)
            self.high_water[rid] = max(self.high_water.get(rid, 0), n)
            self.acked[rid] = int(msg.keyframes_acked)
            self.sim_s = max(self.sim_s, float(msg.stamp))
            self.messages += 1

    def take(self) -> tuple[dict[str, int], int, float]:
        """(outbox max per robot since the last call, keyframes acked, sim time s)."""
        with self._lock:
            window, self.window_max = self.window_max, {}
            return window, sum(self.acked.values()), self.sim_s

    def close(self) -> None:
        self.bus.close()


def _child(launcher: Launcher, name: str) -> Child | None:
    return next((c for c in launcher.group.children if c.name == name), None)


def _listen_endpoint(child: Child) -> str:
    args = [str(a) for a in child.proc.args]  # type: ignore[union-attr]
    return args[args.index("--listen") + 1]


def _listening(ep: str) -> bool:
    """Whether something accepts TCP connections at a `tcp/host:port` endpoint."""
    host, _, port = ep.removeprefix("tcp/").rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=0.5):
            return True
    except OSError:
        return False


class _Sampler:
    def __init__(self, launcher: Launcher, cfg: Config, robot_ids: list[str]) -> None:
        self.launcher, self.cfg, self.robot_ids = launcher, cfg, robot_ids
        self.t0 = time.monotonic()
        self.t0_unix = time.time()
        self.rss: list[list[float]] = []
        self.rss_anon: list[list[float]] = []
        self.agent_rss: list[list[float]] = []
        self.rss_peak = 0.0
        self.agent_peak: dict[str, float] = {}
        self.outbox_t: list[float] = []
        self.outbox: dict[str, list[int | None]] = {rid: [] for rid in robot_ids}
        self.cpu: list[list[float]] = []  # [t, base-station CPU in cores, load average]
        self._cpu_last: tuple[float, float] | None = None  # (t, CPU seconds)
        self.sim: list[list[float]] = []
        self.acked: list[list[float]] = []
        self.mission_end_s: float | None = None
        self.watcher: StateWatcher | None = None

    def _sample_cpu(self, t: float, pid: int) -> None:
        """Cores the base station used since the last sample (1.0 = one core busy) and
        the machine's 1-min load average: a base station short of CPU falls behind."""
        cpu_s = cpu_seconds(pid)
        if cpu_s is None:
            return
        if self._cpu_last is not None and t > self._cpu_last[0]:
            cores = (cpu_s - self._cpu_last[1]) / (t - self._cpu_last[0])
            self.cpu.append([round(t, 2), round(cores, 3), round(os.getloadavg()[0], 2)])
        self._cpu_last = (t, cpu_s)

    def sample(self) -> None:
        t = time.monotonic() - self.t0
        base = _child(self.launcher, "basestation")
        if base is not None and (m := rss_mb(base.proc.pid)) is not None:
            self.rss.append([round(t, 2), round(m[0], 2)])
            self.rss_anon.append([round(t, 2), round(m[2], 2)])
            self.rss_peak = max(self.rss_peak, m[1])
            self._sample_cpu(t, base.proc.pid)
            ep = _listen_endpoint(base)
            # join once the base station listens (a session that connects too early
            # was seen to miss the robots' states)
            if self.watcher is None and _listening(ep):
                try:
                    self.watcher = StateWatcher(self.cfg, ep)
                except CollabSlamError as exc:  # keep sampling memory without states
                    log.warning("soak: cannot watch robot states: %s", exc)
        agents_mb = []
        for rid in self.robot_ids:
            c = _child(self.launcher, rid)
            m = rss_mb(c.proc.pid) if c is not None else None
            if m is not None:
                agents_mb.append(m[0])
                self.agent_peak[rid] = max(self.agent_peak.get(rid, 0.0), m[1])
        if agents_mb:
            self.agent_rss.append([round(t, 2), round(max(agents_mb), 2)])
        sim = _child(self.launcher, "sim")
        if self.mission_end_s is None and sim is not None and sim.proc.poll() is not None:
            self.mission_end_s = t
        if self.watcher is not None:
            window, acked, sim_s = self.watcher.take()
            self.outbox_t.append(round(t, 2))
            for rid in self.robot_ids:
                self.outbox[rid].append(window.get(rid))  # None: no state this period
            self.acked.append([round(t, 2), float(acked)])
            self.sim.append([round(t, 2), round(sim_s, 2)])


def run(
    cfg: Config,
    out_dir: Path,
    data_dir: Path,
    robots: int = 10,
    sim_minutes: float = 30.0,
    world: str = "floor30x25",
    sample_s: float = 5.0,
) -> dict[str, Any]:
    """Fly the soak mission and sample it (data_dir unused). Outputs in out_dir:
    run/ (the mission's results and logs) and soak.png."""
    if robots < 1 or not sim_minutes > 0.0 or not sample_s > 0.0:
        raise ConfigError("bench soak: --robots >= 1, --sim-minutes > 0, --sample-s > 0")
    c = soak_config(cfg, sim_minutes)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_dir = out_dir / "run"
    launcher = Launcher(c, world, robots, run_dir, 60.0 * sim_minutes, "WARNING")
    robot_ids = [f"r{i}" for i in range(robots)]
    sampler = _Sampler(launcher, c, robot_ids)
    outcome: dict[str, Any] = {}

    def fly() -> None:
        try:
            outcome["summary"] = launcher.run()
        except BaseException as exc:  # re-raised on the caller's thread
            outcome["error"] = exc

    thread = threading.Thread(target=fly, name="soak-launcher")
    thread.start()
    try:
        while thread.is_alive():
            sampler.sample()
            thread.join(sample_s)
    except KeyboardInterrupt:
        launcher.stop.set()
        thread.join()
        raise
    finally:
        if sampler.watcher is not None:
            sampler.watcher.close()
    if "error" in outcome:
        raise outcome["error"]
    return _result(sampler, outcome["summary"], run_dir, out_dir, robots, sim_minutes, world)


def _result(
    s: _Sampler,
    summary: dict[str, Any],
    run_dir: Path,
    out_dir: Path,
    robots: int,
    sim_minutes: float,
    world: str,
) -> dict[str, Any]:
    wall_s = time.monotonic() - s.t0
    base = json.loads((run_dir / "basestation.json").read_text())
    series = base.get("isam2_update_ms_series", {"rows": [], "t0_unix": s.t0_unix})
    shift = series["t0_unix"] - s.t0_unix  # base-station clock -> bench clock
    rows = series["rows"]
    update_ms = [[round(r[0] + shift, 2), r[2], r[3], r[4]] for r in rows]
    end = s.mission_end_s if s.mission_end_s is not None else wall_s
    # the mission: from the first sim tick seen (processes up, robots flying) to the end
    flying = [t for t, sim_s in s.sim if sim_s > 0.0]
    start = flying[0] if flying else (s.rss[0][0] if s.rss else 0.0)
    half = start + 0.5 * (end - start)
    high_water = {rid: max((n for n in s.outbox[rid] if n is not None), default=0)
                  for rid in s.robot_ids}  # fmt: skip
    for rid in s.robot_ids:  # the agent's own count sees every keyframe, not samples
        p = run_dir / "agents" / f"{rid}.json"
        if p.is_file():
            high_water[rid] = max(high_water[rid], json.loads(p.read_text())["outbox_high_water"])
    kf_vs_rss = _rss_per_keyframe(s.rss, s.acked, half, end)
    result: dict[str, Any] = {
        "robots": robots,
        "sim_minutes": sim_minutes,
        "world": world,
        "sim_time_s": summary.get("sim_time_s"),
        "wall_s": round(wall_s, 1),
        "mission_wall_s": [round(start, 1), round(end, 1)],
        "sample_s": _median_step([r[0] for r in s.rss]),
        "rss_mb": s.rss,
        "rss_peak_mb": round(max([s.rss_peak, *(r[1] for r in s.rss)]), 2),
        "rss_growth_mb_per_min_second_half": slope_per_min(s.rss, half, end),
        "rss_mb_per_1000_keyframes_second_half": kf_vs_rss,
        "rss_anon_mb": s.rss_anon,
        "rss_anon_growth_mb_per_min_second_half": slope_per_min(s.rss_anon, half, end),
        "rss_anon_mb_per_1000_keyframes_second_half": _rss_per_keyframe(
            s.rss_anon, s.acked, half, end
        ),
        "basestation_cpu": s.cpu,
        "basestation_cpu_cores_mean": _mean_between(s.cpu, start, end),
        "load_average_mean": _mean_between(s.cpu, start, end, col=2),
        "agent_rss_max_mb": s.agent_rss,
        "agent_rss_peak_mb": {rid: round(v, 2) for rid, v in s.agent_peak.items()},
        "agent_rss_growth_mb_per_min_second_half": slope_per_min(s.agent_rss, half, end),
        "outbox_high_water": high_water,
        "outbox_series": {"t_s": s.outbox_t, **s.outbox},
        "outbox_max": max(high_water.values(), default=0),
        "state_messages": s.watcher.messages if s.watcher is not None else 0,
        "sim_s": s.sim,
        "keyframes_acked_series": s.acked,
        "update_ms": update_ms,
        **_memory_breakdown(base.get("memory_series"), s.t0_unix, half, end),
        "update_counts": [[round(r[0] + shift, 2), int(r[1])] for r in rows],
        "update_period_s": series.get("period_s"),
        "isam2_updates": base.get("isam2_updates"),
        "isam2_update_ms_p95": base.get("isam2_update_ms_p95"),
        "keyframes_sent": sum(r["keyframes_sent"] for r in summary["robots"]),
        "keyframes_in_graph": sum(r["keyframes_in_graph"] for r in summary["robots"]),
        "map_accuracy": summary.get("map_accuracy"),
        "map_coverage": summary.get("map_coverage"),
        "run_dir": str(run_dir),
    }
    png = out_dir / "soak.png"
    plot_soak(result, png)
    result["plot"] = str(png)
    return result


def _mean_between(series: list[list[float]], t0: float, t1: float, col: int = 1) -> float | None:
    vals = [row[col] for row in series if t0 <= row[0] <= t1]
    return round(float(np.mean(vals)), 3) if vals else None


def _median_step(t: list[float]) -> float | None:
    return round(float(np.median(np.diff(t))), 2) if len(t) > 1 else None


def _rss_per_keyframe(
    rss: list[list[float]], acked: list[list[float]], t0: float, t1: float
) -> float | None:
    """Slope of base-station RSS (MB) against keyframes acknowledged, per 1000, over
    samples in [t0, t1] (both series share the sample times)."""
    by_t = {t: v for t, v in acked}
    pts = np.array([[by_t[t], m] for t, m in rss if t0 <= t <= t1 and t in by_t]).reshape(-1, 2)
    if len(pts) < 3 or np.ptp(pts[:, 0]) <= 0.0:
        return None
    return float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0] * 1000.0)


def _memory_breakdown(
    series: dict[str, Any] | None, t0_unix: float, t0: float, t1: float
) -> dict[str, Any]:
    """The base station's own memory samples (`HeapTrimmer`: one per heap trim) on the
    bench clock, and each column's slope per 1000 keyframes admitted over [t0, t1]:
    whether the RSS grows with live heap (malloc's in use; SQLite's share of it, the
    per-keyframe arrays and iSAM2's factor slots apart), fragmentation (free but not
    given back), malloc's own mappings (large arrays) or Python's objects."""
    if not series or not series.get("rows"):
        return {}
    cols = series["columns"]
    shift = series["t0_unix"] - t0_unix
    rows = [[r[0] + shift, *r[1:]] for r in series["rows"]]
    count = cols.index("count")
    slopes: dict[str, float | None] = {}
    for k, name in enumerate(cols[1:count], start=1):
        pts = np.array(
            [[r[count], r[k]] for r in rows if t0 <= r[0] <= t1 and None not in (r[k], r[count])]
        ).reshape(-1, 2)
        ok = len(pts) >= 3 and np.ptp(pts[:, 0]) > 0.0
        slopes[name] = (
            round(float(np.polyfit(pts[:, 0], pts[:, 1], 1)[0] * 1000.0), 4) if ok else None
        )
    return {
        "basestation_memory": {"columns": cols, "rows": rows},
        "basestation_memory_per_1000_keyframes_second_half": slopes,
    }
