"""The `collabslam` command line: sim, agent, basestation, run."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import tomllib
from pathlib import Path
from typing import Any

from collabslam import __version__
from common.errors import CollabSlamError, ConfigError

log = logging.getLogger("collabslam")


def _version() -> str:
    from importlib.metadata import version

    import gtsam  # noqa: F401  (the check: every core library imports)
    import ompl.base  # noqa: F401
    import zenoh

    libs = {
        n: version(d)
        for n, d in (
            ("gtsam", "gtsam"),
            ("ompl", "ompl"),
            ("zenoh", "eclipse-zenoh"),
            ("numpy", "numpy"),
        )
    }
    del zenoh
    return f"collabslam {__version__} (" + ", ".join(f"{k} {v}" for k, v in libs.items()) + ")"


def _parse_set(items: list[str]) -> dict[str, Any]:
    """--set key=value, value parsed as TOML (numbers, booleans, strings, lists)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected key=value")
        try:
            out[key.strip()] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = raw  # bare word: a string
    return out


def _load_cfg(args: argparse.Namespace) -> Any:
    from common.config import load_config

    overrides = _parse_set(args.set)
    if getattr(args, "listen", None):
        overrides["zenoh.listen"] = args.listen
    if getattr(args, "connect", None):
        overrides["zenoh.connect"] = args.connect
    if getattr(args, "zenoh_config", None):
        overrides["zenoh.config_file"] = args.zenoh_config
    if getattr(args, "db", None):
        overrides["basestation.db_path"] = args.db
    return load_config(args.config, overrides)


def _bus(cfg: Any) -> Any:
    from common.bus import Bus

    return Bus(cfg.zenoh, cfg.fleet, cfg.protocol.max_message_bytes)


def cmd_sim(args: argparse.Namespace) -> int:
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = _load_cfg(args)
    scenario = read_scenario(args.scenario)
    world = World.load(scenario.world)
    stop = threading.Event()
    install_signal_handlers(stop)
    with _bus(cfg) as bus:
        sim = Simulator(cfg, bus, scenario, world, args.max_sim_time)
        sim.start()
        try:
            sim.run(stop)
        finally:
            sim.write_outputs(Path(args.out))
    return 0


def cmd_agent(args: argparse.Namespace) -> int:
    import numpy as np

    from agent.node import AgentNode
    from agent.sensor_sources import CarmenReplay, ZenohSensors
    from agent.vehicle import NullVehicle
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers

    cfg = _load_cfg(args)
    tour, T_map_odom = np.zeros((0, 2)), None
    if args.scenario:
        r = read_scenario(args.scenario).robot(args.robot_id)
        tour = r.tour
        x, y, yaw = r.start_pose
        T_map_odom = np.array([x, y, 0.0, yaw])
    stop = threading.Event()
    install_signal_handlers(stop)
    with _bus(cfg) as bus:
        if args.replay:
            source = CarmenReplay(args.replay, args.robot_id, _segment(args.segment))
            node = AgentNode(cfg, args.robot_id, bus, tour, T_map_odom, NullVehicle())
        else:
            source = ZenohSensors(bus, args.robot_id)
            node = AgentNode(cfg, args.robot_id, bus, tour, T_map_odom)
        node.start()
        log.info("agent %s running", args.robot_id)
        node.run(source, stop, cfg.agent.replay_max_unacked if args.replay else None)
        node.drain(cfg.agent.drain_timeout_s)
        if args.out:
            node.write_outputs(Path(args.out))
    return 0


def _segment(text: str | None) -> tuple[float | None, float | None]:
    """'START:END' in log time (s); either side may be empty."""
    if not text:
        return None, None
    a, sep, b = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return (float(a) if a else None, float(b) if b else None)
    except ValueError:
        raise ConfigError(f"--segment {text!r}: expected START:END in seconds") from None


def cmd_basestation(args: argparse.Namespace) -> int:
    from basestation.node import BaseStationNode
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers

    cfg = _load_cfg(args)
    scenario = read_scenario(args.scenario) if args.scenario else None
    stop = threading.Event()
    install_signal_handlers(stop)
    with _bus(cfg) as bus:
        node = BaseStationNode(cfg, bus, scenario)
        node.start()
        log.info("base station running (fleet %s)", cfg.fleet)
        node.run(stop)
        node.drain()
        node.write_outputs(Path(args.out))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from collabslam.launcher import Launcher
    from common.shutdown import install_signal_handlers

    cfg = _load_cfg(args)
    out = Path(args.out)
    launcher = Launcher(cfg, args.world, args.robots, out, args.max_sim_time, args.log_level)
    install_signal_handlers(launcher.stop)
    summary = launcher.run()
    print(json.dumps(summary, indent=1))
    print(
        f"\nresults in {out.resolve()}: map.png, map.pgm/.yaml, trajectories/, "
        f"ground_truth/, summary.json, config.toml, logs/"
    )
    return 0


def cmd_eval_relations(args: argparse.Namespace) -> int:
    from common.relations import main_eval_relations

    result = main_eval_relations(args.trajectory, args.relations)
    text = json.dumps(result, indent=1)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text)
    print(text)
    return 0


def cmd_eval_carmen(args: argparse.Namespace) -> int:
    from collabslam.eval_carmen import eval_carmen

    cfg = _load_cfg(args)
    result = eval_carmen(
        cfg, Path(args.log), Path(args.relations), args.robots, Path(args.json), args.log_level
    )
    print(json.dumps(result, indent=1))
    return 0


def _default_data_dir() -> Path:
    """../shared/data next to the repository (where the shared real data lives)."""
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    cfg = _load_cfg(args)
    module = importlib.import_module(f"benchmarks.{args.bench_name.replace('-', '_')}")
    out = Path(args.json)
    result = module.run(cfg, out.parent / out.stem, Path(args.data_dir), **args.bench_kwargs(args))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="collabslam", description=__doc__)
    p.add_argument("--version", action="store_true", help="print versions and check imports")
    p.add_argument("--log-level", default="INFO")
    sub = p.add_subparsers(dest="command")

    def common(sp: argparse.ArgumentParser, zenoh: bool = True) -> None:
        sp.add_argument("--config", help="TOML config file (defaults are built in)")
        sp.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="override one config key, e.g. --set sim.seed=3",
        )
        if zenoh:
            sp.add_argument(
                "--listen",
                action="append",
                metavar="ENDPOINT",
                help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447",
            )
            sp.add_argument(
                "--connect",
                action="append",
                metavar="ENDPOINT",
                help="Zenoh endpoint to connect to",
            )
            sp.add_argument(
                "--zenoh-config",
                metavar="PATH",
                help="Zenoh JSON5 config merged under our endpoints, e.g. the TLS + "
                "access-control files made by deploy/make_zenoh_configs.py",
            )

    sp = sub.add_parser("sim", help="run the simulator process")
    common(sp)
    sp.add_argument("--scenario", required=True)
    sp.add_argument("--out", required=True)
    sp.add_argument("--max-sim-time", type=float, default=300.0)
    sp.set_defaults(func=cmd_sim)

    sp = sub.add_parser("agent", help="run one drone's agent")
    common(sp)
    sp.add_argument("--robot-id", required=True)
    sp.add_argument("--scenario", help="scenario JSON (tour and known start pose)")
    sp.add_argument("--out", help="folder for the agent's statistics")
    sp.add_argument(
        "--replay", metavar="LOG", help="replay a CARMEN .clf/.clf.bz2 log instead of live sensors"
    )
    sp.add_argument("--segment", metavar="START:END", help="with --replay: log time window (s)")
    sp.set_defaults(func=cmd_agent)

    sp = sub.add_parser("basestation", help="run the base-station daemon")
    common(sp)
    sp.add_argument("--scenario", help="scenario JSON (robot roster, known start poses)")
    sp.add_argument("--out", required=True, help="folder for the map and trajectories")
    sp.add_argument(
        "--db",
        metavar="PATH",
        help="SQLite database: persist everything before acknowledging it, and resume "
        "from it after a crash (sets basestation.db_path)",
    )
    sp.set_defaults(func=cmd_basestation)

    sp = sub.add_parser("run", help="simulate a whole team on this machine")
    common(sp, zenoh=False)
    sp.add_argument("--world", default="bshape", help="shipped world name or a PGM+YAML path")
    sp.add_argument("--robots", type=int, default=3)
    sp.add_argument("--out", default="runs/latest")
    sp.add_argument("--max-sim-time", type=float, default=300.0, help="seconds of sim time")
    sp.set_defaults(func=cmd_run)
    sp = sub.add_parser("bench", help="benchmarks (JSON out)")
    bn = sp.add_subparsers(dest="bench_name", required=True)
    b = bn.add_parser(
        "local-slam",
        help="local SLAM speed (sim, 1081 beams) and accuracy (sim drift, Intel/ACES relations)",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file")
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--length", type=float, default=220.0, help="tour length (m)")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.set_defaults(func=cmd_bench, bench_kwargs=lambda a: {"world": a.world, "length_m": a.length})
    b = bn.add_parser(
        "backend",
        help="iSAM2 fed node by node vs. batch LM on 3-robot g2o graphs (M3500, city10000)",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument(
        "--sizes",
        type=lambda text: tuple(int(n) for n in text.split(",")),
        default="500,2000,10000",
        help="comma list of graph sizes in nodes (<= 3500: M3500 prefix, else city10000)",
    )
    b.set_defaults(func=cmd_bench, bench_kwargs=lambda a: {"sizes": a.sizes})
    b = bn.add_parser(
        "exploration",
        help="time to 95 %% explored for 1..N drones: coordinated (ours) vs greedy baseline",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file; runs and plots go next to it")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument(
        "--world",
        default="bshape",
        help="comma list: shipped names, map_server YAML paths, or random:SEED (generated)",
    )
    b.add_argument("--robots", default="1,2,3", help="comma list of team sizes")
    b.add_argument("--seeds", type=int, default=1, help="runs per team size (sim.seed 0..N-1)")
    b.add_argument("--max-sim-time", type=float, default=400.0, help="s of sim time per run")
    b.add_argument("--strategies", default="ours,baseline", help="comma list of ours, baseline")
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {
            "worlds": a.world.split(","),
            "robots": [int(n) for n in a.robots.split(",")],
            "seeds": a.seeds,
            "max_sim_time": a.max_sim_time,
            "strategies": a.strategies.split(","),
        },
    )
    b = bn.add_parser(
        "smoothing",
        help="control-pose steps when loops close, raw vs. smoothed (seed 000 Fig. 1)",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file (runs and PNG next to it)")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
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
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {
            "world": a.world,
            "robots": a.robots,
            "length_m": a.length,
            "max_sim_time": a.max_sim_time,
            "scenarios": a.scenarios,
        },
    )
    b = bn.add_parser(
        "gps",
        help="GPS factors (seed 000 eq. 3-7): georeferenced ATE per weighting, Huber vs. "
        "multipath outliers, iSAM2 update p95 with/without GPS, Fig. 8-like PNG",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file (PNG and TUMs next to it)")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--length", type=float, default=300.0, help="flight length (m)")
    b.add_argument("--seeds", type=int, default=6, help="GNSS noise draws per setting")
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {"world": a.world, "length_m": a.length, "gnss_seeds": a.seeds},
    )
    b = bn.add_parser(
        "soak",
        help="long mission on scripted tours: base-station RSS, outboxes and iSAM2 update "
        "latencies over time (memory flat?)",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file (run/ and PNG next to it)")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument("--world", default="floor30x25")
    b.add_argument("--robots", type=int, default=10)
    b.add_argument("--sim-minutes", type=float, default=30.0, help="mission length (sim min)")
    b.add_argument("--sample-s", type=float, default=5.0, help="wall s between samples")
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {
            "robots": a.robots,
            "sim_minutes": a.sim_minutes,
            "world": a.world,
            "sample_s": a.sample_s,
        },
    )

    b = bn.add_parser(
        "security",
        help="secure base station (mTLS + access control) vs. unauthorized clients and robots",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument("--keyframes", type=int, default=5, help="legitimate keyframes per robot")
    b.add_argument("--base-mode", choices=("router", "peer"), default="router")
    b.add_argument(
        "--agent-seconds",
        type=float,
        default=45.0,
        help="also run a real agent replaying this much of DATA_DIR/carmen/intel.clf.bz2 (0: no)",
    )
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {
            "keyframes": a.keyframes,
            "base_mode": a.base_mode,
            "agent_seconds": a.agent_seconds,
        },
    )

    b = bn.add_parser(
        "faults",
        help="3-robot mission with base-station SIGKILLs, link cuts, duplicated/reordered "
        "keyframes and malformed messages, vs. the same mission undisturbed",
    )
    common(b, zenoh=False)
    b.add_argument("--json", required=True, help="output JSON file")
    b.add_argument("--data-dir", default=str(_default_data_dir()))
    b.add_argument("--world", default="bshape")
    b.add_argument("--robots", type=int, default=3)
    b.add_argument("--restarts", type=int, default=3, help="base-station SIGKILL + restart")
    b.add_argument("--restart-period", type=float, default=15.0, help="s wall between kills")
    b.add_argument("--cut", type=float, default=30.0, help="s each agent's link is cut")
    b.add_argument("--dup-fraction", type=float, default=0.1, help="keyframes re-put")
    b.add_argument("--malformed", type=int, default=10000, help="bad messages injected")
    b.set_defaults(
        func=cmd_bench,
        bench_kwargs=lambda a: {
            "world": a.world,
            "robots": a.robots,
            "restarts": a.restarts,
            "restart_period_s": a.restart_period,
            "cut_s": a.cut,
            "dup_fraction": a.dup_fraction,
            "malformed": a.malformed,
        },
    )

    sp = sub.add_parser("eval", help="score results against references")
    ev = sp.add_subparsers(dest="eval_command", required=True)
    e = ev.add_parser("relations", help="Kuemmerle et al. relation metric of a TUM trajectory")
    e.add_argument("trajectory", help="estimated trajectory (TUM; stamps = the log's)")
    e.add_argument("relations", help="relations file (t1 t2 dx dy dz droll dpitch dyaw)")
    e.add_argument("--json", help="also write the numbers to this file")
    e.set_defaults(func=cmd_eval_relations)
    e = ev.add_parser(
        "carmen",
        help="split a CARMEN log into K robots, run agents and the base "
        "station over Zenoh, score the merged trajectory with a relations file",
    )
    common(e, zenoh=False)
    e.add_argument("log", help="CARMEN .clf or .clf.bz2")
    e.add_argument("--relations", required=True)
    e.add_argument("--robots", type=int, default=3)
    e.add_argument("--json", required=True, help="output JSON; outputs go next to it")
    e.set_defaults(func=cmd_eval_carmen)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from common.logging_setup import setup_logging

    setup_logging(args.log_level, getattr(args, "command", "") or "")
    try:
        if args.version:
            print(_version())
            return 0
        if not args.command:
            parser.print_help()
            return 2
        return int(args.func(args))
    except CollabSlamError as exc:
        log.error("%s", exc)
        return 1
    except Exception:
        log.exception("unexpected error")
        return 1


if __name__ == "__main__":
    sys.exit(main())
