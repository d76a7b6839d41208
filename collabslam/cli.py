"""The `collabslam` command line: sim, agent, basestation, run."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any

from collabslam import __version__
from collabslam.bench_cli import add_bench_parsers
from collabslam.cli_options import add_common_args, json_file, load_cfg
from common.errors import CollabSlamError, ConfigError, PersistenceError

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


def _bus(cfg: Any, certificate_name: str | None = None) -> Any:
    """`certificate_name`: the CN the config file's certificate must have, if it has one."""
    from common.bus import Bus
    from common.zenoh_security import check_certificate_name

    if certificate_name and cfg.zenoh.config_file:
        check_certificate_name(cfg.zenoh.config_file, certificate_name)
    return Bus(cfg.zenoh, cfg.fleet, cfg.protocol.max_message_bytes)


def cmd_sim(args: argparse.Namespace) -> int:
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = load_cfg(args)
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


# s a stopping agent waits after its last state before its liveliness token goes: Zenoh
# sends the token's end ahead of data still queued (put and close at once: the state
# came after the token's end 7 times in 10 on loopback; 0 of 10 with 10 ms between)
SIGN_OFF_WAIT_S = 0.2


def cmd_agent(args: argparse.Namespace) -> int:
    import numpy as np

    from agent.node import AgentNode
    from agent.sensor_sources import CarmenReplay, ZenohSensors
    from agent.vehicle import NullVehicle
    from common.memory import limit_malloc_arenas
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers

    cfg = load_cfg(args)
    limit_malloc_arenas(cfg.agent.malloc_arenas)  # before Zenoh starts its threads
    tour, T_map_odom = np.zeros((0, 2)), None
    if args.scenario:
        r = read_scenario(args.scenario).robot(args.robot_id)
        tour = r.tour
        x, y, yaw = r.start_pose
        T_map_odom = np.array([x, y, 0.0, yaw])
    stop = threading.Event()
    install_signal_handlers(stop)
    with _bus(cfg, args.robot_id) as bus:
        if args.replay:
            a = cfg.agent
            source = CarmenReplay(
                args.replay, args.robot_id, _segment(args.segment),
                rate=a.replay_rate, start_unix=a.replay_start_unix,
            )  # fmt: skip
            node = AgentNode(cfg, args.robot_id, bus, tour, T_map_odom, NullVehicle())
        else:
            a = cfg.agent
            source = ZenohSensors(
                bus, args.robot_id, relay_gnss=a.relay_gnss, max_scan_lag_s=a.max_scan_lag_s,
                queue_max=a.sensor_queue_max,
            )  # fmt: skip
            node = AgentNode(cfg, args.robot_id, bus, tour, T_map_odom)
            source.clock = node.clock  # relayed GNSS fixes on the agent's timeline
        node.start(await_base=args.await_base)
        log.info("agent %s running", args.robot_id)
        node.run(source, stop, cfg.agent.replay_max_unacked if args.replay else None)
        if node.drain(cfg.agent.drain_timeout_s):
            node.forget_state()  # stopped, all acknowledged: the next start is afresh
        if node.last_scan_stamp is not None:  # a last state, before its token goes: the base
            node.publish_state(node.last_scan_stamp, "stopped")  # station logs a stop, not a loss
            time.sleep(SIGN_OFF_WAIT_S)
        if args.out:
            node.write_outputs(Path(args.out))
    return 0


def _segment(text: str | None) -> tuple[float | None, float | None]:
    """'START:END' in log time (s); either side may be empty."""
    if not text:
        return None, None
    a, sep, b = text.partition(":")
    try:
        start, end = (float(a) if a else None, float(b) if b else None)
        if not sep or not all(math.isfinite(v) for v in (start, end) if v is not None):
            raise ValueError
    except ValueError:
        raise ConfigError(f"--segment {text!r}: expected START:END in seconds") from None
    if start is not None and end is not None and not start < end:
        raise ConfigError(f"--segment {text!r}: START must come before END")
    return start, end


def arrays_on_disk(arrays_dir: str, db_path: str) -> None:
    """Where the base station keeps its per-keyframe arrays (`basestation.arrays_dir`):
    "memory", in memory; "", in files next to the database, whose folder is made now as
    SQLite would make it (a unit's `--db /var/lib/collabslam/basestation/mission.db`),
    or in the temporary directory without one; else in that directory."""
    from common.growable import keep_on_disk

    if arrays_dir == "memory":
        return
    if not arrays_dir and db_path:
        arrays_dir = str(Path(db_path).resolve().parent)
        try:
            Path(arrays_dir).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"basestation.db_path: cannot make {arrays_dir!r}: {exc}") from None
    keep_on_disk(arrays_dir)


def cmd_basestation(args: argparse.Namespace) -> int:
    from basestation.node import BaseStationNode
    from common.memory import fix_mmap_threshold, limit_malloc_arenas
    from common.scenario import read_scenario
    from common.shutdown import install_signal_handlers
    from common.zenoh_security import BASESTATION_CN

    cfg = load_cfg(args)
    b = cfg.basestation
    limit_malloc_arenas(b.malloc_arenas)  # before Zenoh starts its threads
    fix_mmap_threshold(b.malloc_mmap_threshold_kb)
    arrays_on_disk(b.arrays_dir, b.db_path)
    scenario = read_scenario(args.scenario) if args.scenario else None
    stop = threading.Event()
    install_signal_handlers(stop)
    with _bus(cfg, BASESTATION_CN) as bus:
        node = BaseStationNode(cfg, bus, scenario, lockstep=args.lockstep)
        node.start()
        log.info("base station running (fleet %s)", cfg.fleet)
        try:
            node.run(stop)
            node.drain()
        except PersistenceError:  # nothing unstored was acked; keep what it has
            node.write_outputs(Path(args.out))
            raise
        node.write_outputs(Path(args.out))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from collabslam.launcher import Launcher
    from common.shutdown import install_signal_handlers

    cfg = load_cfg(args)
    out = Path(args.out)
    launcher = Launcher(cfg, args.world, args.robots, out, args.max_sim_time, args.log_level)
    install_signal_handlers(launcher.stop)
    summary = launcher.run()
    print(json.dumps(summary, indent=1))
    print(
        f"\nresults in {out.resolve()}: map.png, map.pgm/.yaml, trajectories/, "
        f"ground_truth/, summary.json, config.toml, logs/"
    )
    return 130 if launcher.stop.is_set() else 0  # (interrupted: outputs written, not done)


def cmd_eval_relations(args: argparse.Namespace) -> int:
    from common.relations import main_eval_relations

    if args.json:
        json_file(args.json, beside=False)  # (writes no folder beside it)
    result = main_eval_relations(args.trajectory, args.relations)
    text = json.dumps(result, indent=1)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text)
    print(text)
    return 0


def cmd_eval_carmen(args: argparse.Namespace) -> int:
    from collabslam.eval_carmen import eval_carmen

    cfg = load_cfg(args)
    result = eval_carmen(
        cfg, Path(args.log), Path(args.relations), args.robots, Path(args.json), args.log_level
    )
    print(json.dumps(result, indent=1))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="collabslam", description=__doc__)
    p.add_argument("--version", action="store_true", help="print versions and check imports")
    p.add_argument(
        "--log-level",
        default="INFO",
        type=str.upper,
        choices=["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"],
    )
    sub = p.add_subparsers(dest="command")

    sp = sub.add_parser("sim", help="run the simulator process")
    add_common_args(sp)
    sp.add_argument("--scenario", required=True)
    sp.add_argument("--out", required=True)
    sp.add_argument("--max-sim-time", type=float, default=300.0)
    sp.set_defaults(func=cmd_sim)

    sp = sub.add_parser("agent", help="run one drone's agent")
    add_common_args(sp)
    sp.add_argument("--robot-id", required=True)
    sp.add_argument("--scenario", help="scenario JSON (tour and known start pose)")
    sp.add_argument("--out", help="folder for the agent's statistics")
    sp.add_argument(
        "--replay", metavar="LOG", help="replay a CARMEN .clf/.clf.bz2 log instead of live sensors"
    )
    sp.add_argument("--segment", metavar="START:END", help="with --replay: log time window (s)")
    sp.add_argument(
        "--await-base",
        action="store_true",
        help="an exploring simulator's agent: wait (sim.sync_wait_s at most) for the base "
        "station before starting (`collabslam run` sets it; a live agent flies on at once)",
    )
    sp.set_defaults(func=cmd_agent)

    sp = sub.add_parser("basestation", help="run the base-station daemon")
    add_common_args(sp)
    sp.add_argument("--scenario", help="scenario JSON (robot roster, known start poses)")
    sp.add_argument("--out", required=True, help="folder for the map and trajectories")
    sp.add_argument(
        "--db",
        metavar="PATH",
        help="SQLite database: persist everything before acknowledging it, and resume "
        "from it after a crash (sets basestation.db_path)",
    )
    sp.add_argument(
        "--lockstep",
        action="store_true",
        help="a lock-step simulator with exploration drives it: everything happens when its "
        "clock asks, so runs repeat exactly (`collabslam run` sets it)",
    )
    sp.set_defaults(func=cmd_basestation)

    sp = sub.add_parser("run", help="simulate a whole team on this machine")
    add_common_args(sp, zenoh=False)
    sp.add_argument("--world", default="bshape", help="shipped world name or a PGM+YAML path")
    sp.add_argument("--robots", type=int, default=3)
    sp.add_argument("--out", default="runs/latest")
    sp.add_argument("--max-sim-time", type=float, default=300.0, help="seconds of sim time")
    sp.set_defaults(func=cmd_run)
    add_bench_parsers(sub)

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
    add_common_args(e, zenoh=False)
    e.add_argument("log", help="CARMEN .clf or .clf.bz2")
    e.add_argument("--relations", required=True)
    e.add_argument("--robots", type=int, default=3)
    e.add_argument(
        "--json", required=True, help="output JSON; the rest in a folder beside it, of its name"
    )
    e.set_defaults(func=cmd_eval_carmen)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from common.logging_setup import setup_logging
    from common.shutdown import stop_with_supervisor

    setup_logging(args.log_level, getattr(args, "command", "") or "")
    stop_with_supervisor()
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
    except KeyboardInterrupt:  # where no signal handler is in place (start-up, bench, eval)
        log.error("interrupted")
        return 130
    except Exception:
        log.exception("unexpected error")
        return 1


if __name__ == "__main__":
    sys.exit(main())
