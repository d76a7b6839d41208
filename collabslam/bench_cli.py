"""`collabslam bench NAME --json OUT`: the benchmark sub-commands and their dispatch.

Each benchmark is a module ``benchmarks/NAME.py`` (dashes become underscores) with
``run(cfg, out_stem, data_dir, **kwargs) -> dict``; its parser here sets
``bench_kwargs``, which maps the parsed arguments to those keyword arguments. To add
one: a ``_bench_parser(...)`` call in ``add_bench_parsers`` (see benchmarks/backend.py).
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from collabslam.cli_options import add_common_args, load_cfg

log = logging.getLogger("collabslam.bench")

BenchKwargs = Callable[[argparse.Namespace], dict[str, Any]]


def _default_data_dir() -> Path:
    """../shared/data next to the repository (where the shared real data lives)."""
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def _int_list(text: str) -> tuple[int, ...]:
    """A comma list of integers ("1,2,3"), for argparse."""
    try:
        return tuple(int(n) for n in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a comma list of integers, got {text!r}"
        ) from None


def _add_data_dir(b: argparse.ArgumentParser) -> None:
    b.add_argument("--data-dir", default=str(_default_data_dir()))


def _bench_parser(
    bn: argparse._SubParsersAction[argparse.ArgumentParser],
    name: str,
    help_text: str,
    bench_kwargs: BenchKwargs,
    json_help: str = "output JSON file",
    data_dir: bool = True,  # False: the caller adds --data-dir itself (its place in --help)
) -> argparse.ArgumentParser:
    """One benchmark's parser with ``--config``, ``--set``, ``--json`` and ``--data-dir``."""
    b = bn.add_parser(name, help=help_text)
    add_common_args(b, zenoh=False)
    b.add_argument("--json", required=True, help=json_help)
    if data_dir:
        _add_data_dir(b)
    b.set_defaults(func=cmd_bench, bench_kwargs=bench_kwargs)
    return b


def add_bench_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``bench`` and its benchmarks to the top-level sub-parsers ``sub``."""
    sp = sub.add_parser("bench", help="benchmarks (JSON out)")
    bn = sp.add_subparsers(dest="bench_name", required=True)
    b = _bench_parser(
        bn,
        "local-slam",
        "local SLAM speed (sim, 1081 beams) and accuracy (sim drift, Intel/ACES relations)",
        lambda a: {"world": a.world, "length_m": a.length},
        data_dir=False,
    )
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--length", type=float, default=220.0, help="tour length (m)")
    _add_data_dir(b)

    b = _bench_parser(
        bn,
        "backend",
        "iSAM2 fed node by node vs. batch LM on 3-robot g2o graphs (M3500, city10000)",
        lambda a: {"sizes": a.sizes},
    )
    b.add_argument(
        "--sizes",
        type=_int_list,
        default="500,2000,10000",
        help="comma list of graph sizes in nodes (<= 3500: M3500 prefix, else city10000)",
    )

    b = _bench_parser(
        bn,
        "exploration",
        "time to 95 %% explored for 1..N drones: coordinated (ours) vs greedy baseline",
        lambda a: {
            "worlds": a.world.split(","),
            "robots": list(a.robots),
            "seeds": a.seeds,
            "first_seed": a.first_seed,
            "max_sim_time": a.max_sim_time,
            "strategies": a.strategies.split(","),
            "bound": a.bound,
            "kinematic": a.kinematic,
        },
        json_help="output JSON file; runs and plots go next to it",
    )
    b.add_argument(
        "--world",
        default="bshape",
        help="comma list: shipped names, map_server YAML paths, or random:SEED (generated)",
    )
    b.add_argument("--robots", type=_int_list, default="1,2,3", help="comma list of team sizes")
    b.add_argument("--seeds", type=int, default=1, help="N runs per team size: sim.seed K..K+N-1")
    b.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="K, the first sim.seed (0): one setting's batch split over cores or machines",
    )
    b.add_argument("--max-sim-time", type=float, default=400.0, help="s of sim time per run")
    b.add_argument("--strategies", default="ours,baseline", help="comma list of ours, baseline")
    b.add_argument(
        "--bound",
        action="store_true",
        help="add time_to_95_bound_s to every row: no team could know 95 %% sooner "
        "(benchmarks/exploration_bound.py; ~10-60 s per world and start)",
    )
    b.add_argument(
        "--kinematic",
        action="store_true",
        help="exploration decisions alone: perfect poses, the agent's path follower on a "
        "kinematic drone, no SLAM or processes (benchmarks/exploration_kinematic.py; "
        "seconds a run, repeatable; for comparing settings, not the benchmark's numbers)",
    )

    b = _bench_parser(
        bn,
        "smoothing",
        "control-pose steps when loops close, raw vs. smoothed (seed 000 Fig. 1)",
        lambda a: {
            "world": a.world,
            "robots": a.robots,
            "length_m": a.length,
            "max_sim_time": a.max_sim_time,
            "scenarios": a.scenarios,
        },
        json_help="output JSON file (runs and PNG next to it)",
    )
    b.add_argument("--world", default="bshape")
    b.add_argument("--robots", type=int, default=2)
    b.add_argument("--length", type=float, default=120.0, help="tour length per robot (m)")
    b.add_argument("--max-sim-time", type=float, default=150.0, help="s of sim time per flight")
    b.add_argument(
        "--scenarios",
        type=lambda text: tuple(text.split(",")),
        default="odometry_drift,local_slam",
        help="comma list of flights: odometry_drift (odometry-only agent), local_slam",
    )

    b = _bench_parser(
        bn,
        "gps",
        "GPS factors (seed 000 eq. 3-7): georeferenced ATE per weighting, Huber vs. "
        "multipath outliers, iSAM2 update p95 with/without GPS, Fig. 8-like PNG",
        lambda a: {"world": a.world, "length_m": a.length, "gnss_seeds": a.seeds},
        json_help="output JSON file (PNG and TUMs next to it)",
    )
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--length", type=float, default=300.0, help="flight length (m)")
    b.add_argument("--seeds", type=int, default=6, help="GNSS noise draws per setting")

    b = _bench_parser(
        bn,
        "soak",
        "long mission on scripted tours: base-station RSS, outboxes and iSAM2 update "
        "latencies over time (memory flat?)",
        lambda a: {
            "robots": a.robots,
            "sim_minutes": a.sim_minutes,
            "world": a.world,
            "sample_s": a.sample_s,
        },
        json_help="output JSON file (run/ and PNG next to it)",
    )
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--robots", type=int, default=10)
    b.add_argument("--sim-minutes", type=float, default=30.0, help="mission length (sim min)")
    b.add_argument("--sample-s", type=float, default=5.0, help="wall s between samples")

    b = _bench_parser(
        bn,
        "security",
        "secure base station (mTLS + access control) vs. unauthorized clients and robots",
        lambda a: {
            "keyframes": a.keyframes,
            "base_mode": a.base_mode,
            "agent_seconds": a.agent_seconds,
        },
    )
    b.add_argument("--keyframes", type=int, default=5, help="legitimate keyframes per robot")
    b.add_argument("--base-mode", choices=("router", "peer"), default="router")
    b.add_argument(
        "--agent-seconds",
        type=float,
        default=45.0,
        help="also run a real agent replaying this much of DATA_DIR/carmen/intel.clf.bz2 (0: no)",
    )

    b = _bench_parser(
        bn,
        "faults",
        "3-robot mission with base-station SIGKILLs, link cuts, duplicated/reordered "
        "keyframes and malformed messages, vs. the same mission undisturbed",
        lambda a: {
            "world": a.world,
            "robots": a.robots,
            "restarts": a.restarts,
            "restart_period_s": a.restart_period,
            "cut_s": a.cut,
            "dup_fraction": a.dup_fraction,
            "malformed": a.malformed,
            "agent_kills": a.agent_kills,
            "fresh_kills": a.fresh_kills,
        },
    )
    b.add_argument("--world", default="bshape")
    b.add_argument("--robots", type=int, default=3)
    b.add_argument("--restarts", type=int, default=3, help="base-station SIGKILL + restart")
    b.add_argument("--restart-period", type=float, default=15.0, help="s wall between kills")
    b.add_argument("--cut", type=float, default=30.0, help="s each agent's link is cut")
    b.add_argument("--dup-fraction", type=float, default=0.1, help="keyframes re-put")
    b.add_argument("--malformed", type=int, default=10000, help="bad messages injected")
    b.add_argument("--agent-kills", type=int, default=1, help="agents SIGKILLed + restarted")
    b.add_argument("--fresh-kills", type=int, default=1, help="agents stopped + started afresh")


def cmd_bench(args: argparse.Namespace) -> int:
    """Run ``benchmarks.<bench_name>`` and write its result to ``--json`` (and stdout)."""
    import importlib

    cfg = load_cfg(args)
    module = importlib.import_module(f"benchmarks.{args.bench_name.replace('-', '_')}")
    out = Path(args.json)
    result = module.run(cfg, out.parent / out.stem, Path(args.data_dir), **args.bench_kwargs(args))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return bench_exit_code(result)


def bench_exit_code(result: dict[str, Any]) -> int:
    """1 when a run failed or a target was missed (a breached `bench security` had exited
    0, and scripts could not tell), 130 when interrupted (the report holds the runs
    finished), else 0."""
    if result.get("interrupted"):
        return 130
    if result.get("failed_runs"):  # the rest is measured, but not all that was asked for
        log.error("%d run(s) failed (their rows say why); the report holds the rest",
                  result["failed_runs"])  # fmt: skip
        return 1
    missed = [k for k, v in result.get("targets_met", {}).items() if v is False]
    missed += [k for k in ("all_rejected", "legitimate_ok") if result.get(k) is False]
    if missed:
        log.error("target(s) not met: %s", ", ".join(missed))
        return 1
    return 0
