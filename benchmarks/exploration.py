"""`collabslam bench exploration`: how much faster a team explores than one drone.

Every row is one whole simulated mission, run exactly as `collabslam run` runs it
(simulator, one agent process per drone and the base station over loopback Zenoh,
lock-step clock synchronized with the base station's exploration steps), until no
frontier is left or `max_sim_time`:

- ours: `exploration.strategy = "coordinated"` (joint eq. 3 assignment, distinct
  goals, RRT* paths around the other robots and their paths);
- baseline: `"greedy"`: every drone to its own nearest frontier, no coordination
  (explore_lite's rule), same simulator, SLAM, planner and safety guard.

`time_to_95_s` is the sim time at which the base station's map first knew 95 % of
the reachable free area (the world's free cells connected to the start), read from
its per-sync map history: a cell is known when the map has it free, or occupied
within `WALL_TOLERANCE_M` of a real wall (its surface, `common.metrics.map_coverage`);
`time_to_95_free_only_s` counts map-free cells only (this benchmark's metric until
2026-11-26). With `bound`, `time_to_95_bound_s` is the floor no team starting where
this one did could beat (`benchmarks/exploration_bound.py`: the travel to the places
that see 95 %, map lag not counted). `collisions` counts wall contacts (simulator)
plus robot-robot contacts (ground-truth discs overlapping). Worlds: shipped names,
map_server YAML paths, or `random:SEED` for a generated floor plan nobody tuned on.
With `kinematic`, every row is a kinematic run of the exploration decisions alone
(`benchmarks/exploration_kinematic.py`: seconds a run, the same for a seed; for
comparing exploration settings, not for these numbers).
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.exploration_bound import time_to_fraction_bound_s
from benchmarks.exploration_kinematic import run_kinematic
from collabslam.launcher import Launcher
from common.config import Config
from common.errors import ConfigError, ProcessError
from common.map_io import read_map, write_map
from common.scenario import read_scenario
from simulation.world_generator import generate_world

log = logging.getLogger(__name__)

STRATEGIES = {"ours": "coordinated", "baseline": "greedy"}


def resolve_bench_world(world: str, out_dir: Path) -> str:
    """A world name/path for the launcher; `random:SEED` is generated into out_dir."""
    if not world.startswith("random:"):
        return world
    seed = int(world.split(":", 1)[1])
    path = out_dir / "worlds" / f"random_{seed}.yaml"
    if not path.is_file():
        write_map(generate_world("random", seed), path)
    return str(path)


def run_mission(
    cfg: Config, world: str, n_robots: int, seed: int, strategy: str, out: Path, max_sim_time: float
) -> dict[str, Any]:
    """One exploration mission; its row of the benchmark."""
    c = copy.deepcopy(cfg)
    c.exploration.enabled = True
    c.exploration.strategy = strategy
    c.sim.seed = seed
    c.sim.clock = "lockstep"
    summary = Launcher(c, world, n_robots, out, max_sim_time, log_level="WARNING").run()
    robots = summary["robots"]
    sep = summary.get("min_robot_separation_m")
    return {
        "robots": n_robots,
        "seed": seed,
        "time_to_95_s": summary.get("time_to_95_s"),
        "time_to_95_free_only_s": summary.get("time_to_95_free_only_s"),
        "distance_m": [round(r["distance_m"], 2) for r in robots],
        "collisions": sum(r["collisions"] for r in robots) + int(summary["robot_contact"]),
        "min_clearance_m": min(r["min_clearance_m"] for r in robots),
        "min_robot_separation_m": sep,
        "sim_time_s": summary["sim_time_s"],
        "end_reason": summary["sim_end_reason"],
        "final_coverage": summary["coverage_curve"][-1][1]
        if summary.get("coverage_curve")
        else None,
        "map_accuracy": summary["map_accuracy"],
        "lockstep_timeouts": summary["lockstep_timeouts"],  # > 0: it may not repeat
        "wall_time_s": round(summary["wall_time_s"], 1),
        "coverage_curve": summary.get("coverage_curve", []),
        "out": str(out),
    }


def failed_row(n_robots: int, seed: int, error: ProcessError, out: Path) -> dict[str, Any]:
    """The row of a mission that did not run to its end (a process died: the log it
    names says why): no measurement, left out of the summary, counted in
    `failed_runs`."""
    return {"robots": n_robots, "seed": seed, "time_to_95_s": None, "error": str(error),
            "coverage_curve": [], "out": str(out)}  # fmt: skip


def _times(
    rows: list[dict[str, Any]], n: int, max_sim_time: float, seeds: set[Any] | None = None
) -> list[float]:
    """Times to 95 % of the n-robot runs (a run that never got there counts as max time;
    one that failed is no measurement), of `seeds` only if given."""
    ok = [r for r in _ok(rows, n) if seeds is None or r.get("seed") in seeds]
    return [r["time_to_95_s"] or max_sim_time for r in ok]


def _ok(rows: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    return [r for r in rows if r["robots"] == n and "error" not in r]


def _seeds(rows: list[dict[str, Any]], n: int) -> set[Any]:
    return {r.get("seed") for r in _ok(rows, n)}


def speedups(
    result: dict[str, list[dict[str, Any]]], counts: list[int], max_sim_time: float
) -> dict[str, Any]:
    """Team speed-ups over one drone (same strategy) and ours over the baseline, on the
    means over the seeds and on the medians (one run that got stuck, a baseline's
    deadlock, moves the mean by its whole max time), each ratio over the seeds both of
    its sides measured (a failed run had left one side's mean over fewer seeds)."""
    out: dict[str, Any] = {}
    for stat, f in (("mean", np.mean), ("median", np.median)):
        sep = "" if stat == "mean" else "median_"

        def stat_of(
            rows: list[dict[str, Any]], n: int, seeds: set[Any] | None, f: Any = f
        ) -> float | None:
            ts = _times(rows, n, max_sim_time, seeds)
            return float(f(ts)) if ts else None

        for name, rows in result.items():
            for n in counts:
                out[f"{name}_{stat}_time_to_95_s_{n}"] = stat_of(rows, n, None)
                if n > 1:  # the ratio over the seeds both team sizes measured
                    both = _seeds(rows, 1) & _seeds(rows, n)
                    t1, tn = stat_of(rows, 1, both), stat_of(rows, n, both)
                    if t1 and tn:
                        out[f"{name}_{sep}speedup_{n}"] = round(t1 / tn, 3)
        if "ours" in result and "baseline" in result:
            for n in counts:
                both = _seeds(result["ours"], n) & _seeds(result["baseline"], n)
                a, b = stat_of(result["ours"], n, both), stat_of(result["baseline"], n, both)
                if a and b:
                    out[f"ours_faster_than_baseline_{sep}pct_{n}"] = round(100.0 * (b - a) / b, 1)
    out["failed_runs"] = sum("error" in r for rows in result.values() for r in rows)
    return out


def _bound(
    cfg: Config, world: str, out: Path, cache: dict[tuple[str, str], float | None]
) -> float | None:
    """`time_to_95_bound_s` for the starts of the mission in `out` (cached per start)."""
    sc = read_scenario(out / "scenario.json")
    starts = [r.start_pose[:2] for r in sc.robots]
    key = (world, repr(np.round(np.asarray(starts, dtype=np.float64), 3).tolist()))
    if key not in cache:
        q = cfg.sim.quadrotor
        cache[key] = time_to_fraction_bound_s(
            read_map(sc.world),
            starts,
            0.95,
            min(q.max_speed_mps, cfg.agent.cruise_speed_mps),
            q.max_accel_mps2,
            radius_m=q.radius_m,
            range_m=cfg.sim.laser.range_max_m,
        )
    return cache[key]


def plot_coverage(result: dict[str, list[dict[str, Any]]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for name, rows in result.items():
        for r in rows:
            curve = np.array(r["coverage_curve"]).reshape(-1, 2)
            if len(curve):
                ax.plot(
                    curve[:, 0],
                    100.0 * curve[:, 1],
                    color=f"C{(r['robots'] - 1) % 10}",  # team sizes 1, 2, 3: blue, orange, green
                    linestyle="-" if name == "ours" else "--",
                    alpha=0.8,
                    label=f"{name}, {r['robots']} robot(s)",
                )
    ax.axhline(95.0, color="k", linewidth=0.8)
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), loc="lower right")
    ax.set_xlabel("sim time [s]")
    ax.set_ylabel("reachable free area known [%]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def run(
    cfg: Config,
    out_dir: Path,
    data_dir: Path,
    worlds: list[str],
    robots: list[int],
    seeds: int,
    max_sim_time: float,
    strategies: list[str] | None = None,
    bound: bool = False,
    kinematic: bool = False,
    first_seed: int = 0,
) -> dict[str, Any]:
    """Every world x seed (`sim.seed` `first_seed` .. + `seeds` - 1) x team size x
    strategy; `kinematic`: decisions only (`benchmarks/exploration_kinematic.py`), not
    the whole system."""
    if kinematic and bound:
        raise ConfigError("--bound needs the missions' runs; it does not go with --kinematic")
    if first_seed < 0 or seeds < 1:
        raise ConfigError(f"--first-seed must be >= 0 and --seeds >= 1, got {first_seed}, {seeds}")
    if not robots or min(robots) < 1:
        raise ConfigError(f"--robots: team sizes must be >= 1, got {robots}")
    names = strategies or list(STRATEGIES)
    if unknown := [n for n in names if n not in STRATEGIES]:
        raise ConfigError(f"--strategies: expected {' and/or '.join(STRATEGIES)}, got {unknown}")
    for world in worlds:  # a bad random:SEED before any mission flies
        if world.startswith("random:") and not world.split(":", 1)[1].isdigit():
            raise ConfigError(f"--world {world}: random:SEED needs a seed >= 0, e.g. random:1")
    report: dict[str, Any] = {"worlds": {}}
    bounds: dict[tuple[str, str], float | None] = {}  # (world, starts) -> time_to_95_bound_s
    for world in worlds:
        path = resolve_bench_world(world, out_dir)
        result: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
        try:
            _fly(cfg, path, world, names, robots, range(first_seed, first_seed + seeds),
                 max_sim_time, out_dir, kinematic, bound, bounds, result)  # fmt: skip
        except KeyboardInterrupt:  # (Ctrl-C: the mission in flight is lost, not the rest)
            log.error("interrupted: the report holds the %d runs finished",
                      sum(map(len, result.values())))  # fmt: skip
            report["interrupted"] = True
        png = out_dir / f"coverage_{world.replace(':', '_')}.png"
        plot_coverage(result, png, f"exploration of {world}")
        report["worlds"][world] = {
            **result,
            "summary": speedups(result, robots, max_sim_time),
            "plot": str(png),
        }
        if report.get("interrupted"):
            break
    report["failed_runs"] = sum(w["summary"]["failed_runs"] for w in report["worlds"].values())
    if len(worlds) == 1:  # the shape: {"ours": [...], "baseline": [...]} at the top
        only = report["worlds"][worlds[0]]
        report.update({k: v for k, v in only.items()})
    return report


def _fly(
    cfg: Config,
    path: str,
    world: str,
    names: list[str],
    robots: list[int],
    seeds: range,
    max_sim_time: float,
    out_dir: Path,
    kinematic: bool,
    bound: bool,
    bounds: dict[tuple[str, str], float | None],
    result: dict[str, list[dict[str, Any]]],
) -> None:
    """The runs of one world, each row added to `result` as it ends."""
    for seed in seeds:
        for n in robots:
            for name in names:
                tag = f"{world.replace(':', '_')}-{name}-n{n}-s{seed}"
                out = out_dir / "runs" / tag
                try:
                    if kinematic:
                        row = run_kinematic(cfg, path, n, seed, STRATEGIES[name], max_sim_time)
                    else:
                        row = run_mission(cfg, path, n, seed, STRATEGIES[name], out, max_sim_time)
                except ProcessError as exc:  # one mission lost, not the whole batch
                    log.error("%s: the mission failed, going on with the next: %s", tag, exc)
                    result[name].append(failed_row(n, seed, exc, out))
                    continue
                log.warning(
                    "%s: time_to_95 %s s, collisions %d, min separation %s m",
                    tag,
                    row["time_to_95_s"],
                    row["collisions"],
                    row["min_robot_separation_m"],
                )
                if bound:
                    row["time_to_95_bound_s"] = _bound(cfg, path, Path(row["out"]), bounds)
                result[name].append(row)
