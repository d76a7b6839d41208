"""`collabslam eval carmen LOG --relations REL --robots K --json OUT`.

Splits a CARMEN log into K consecutive time segments and replays each through
its own agent process (its own `odom` frame; the base station knows no start
pose), with one base-station process over loopback Zenoh. Afterwards every
scan's pose is put in the `map` frame (the base station's optimized keyframe
poses, with the agent's local motion between keyframes), merged into one
trajectory of the whole log (the log's own timestamps) and scored with the
relations. Next to the JSON: the map (PGM+YAML, PNG), `trajectory.tum`, logs.
"""

from __future__ import annotations

import json
import logging
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np

from agent.carmen_log import carmen_time_span
from collabslam.supervisor import ProcessGroup, clear_run_outputs, delete_database, free_port
from common.bus import endpoint
from common.config import Config, dump_config
from common.errors import CollabSlamError
from common.geometry import se2_compose, se2_inverse
from common.relations import Relations, read_relations, score_relations
from common.trajectory_io import Trajectory, read_tum, write_tum

log = logging.getLogger(__name__)
# Log seconds per wall second of each segment's replay (agent.replay_rate; a huge value
# replays as fast as the acks allow, as before).
EVAL_REPLAY_RATE = 3.0
EVAL_HEAD_START_S = 10.0  # s: the processes start (each reads its log) before the replay


def map_frame_trajectory(local: Trajectory, keyframes: Trajectory) -> Trajectory:
    """Every scan pose in `map`: T_map_base(t) = T_map_kf * inv(T_odom_kf) * T_odom_base(t),
    with kf the last keyframe at or before t (scans before the first keyframe use it)."""
    L = local.poses_se2()
    K = keyframes.poses_se2()
    idx_kf_in_local = np.searchsorted(local.stamps, keyframes.stamps)
    idx_kf_in_local = np.clip(idx_kf_in_local, 0, len(L) - 1)
    T_map_odom = se2_compose(K, se2_inverse(L[idx_kf_in_local]))  # per keyframe
    which = np.clip(
        np.searchsorted(keyframes.stamps, local.stamps, side="right") - 1, 0, len(K) - 1
    )
    P = se2_compose(T_map_odom[which], L)
    z = local.positions[:, 2]
    return Trajectory.from_pose4(local.stamps, np.column_stack([P[:, :2], z, P[:, 2]]))


def on_map_relations(rel: Relations, parts: list[Trajectory]) -> Relations:
    """The relations whose two stamps both fall within the time span of a robot on the
    map (the merged trajectory would otherwise interpolate across a segment whose robot
    never joined the map)."""

    def covered(t: np.ndarray) -> np.ndarray:
        return np.any([(p.stamps[0] <= t) & (t <= p.stamps[-1]) for p in parts], axis=0)

    keep = covered(rel.t1) & covered(rel.t2)
    return Relations(rel.t1[keep], rel.t2[keep], rel.delta[keep])


def eval_carmen(
    cfg: Config,
    log_path: Path,
    rel_path: Path,
    robots: int,
    json_out: Path,
    log_level: str = "INFO",
    timeout_s: float = 3600.0,
) -> dict[str, Any]:
    if robots < 1:
        raise CollabSlamError("--robots must be at least 1")
    rel = read_relations(rel_path)  # fail early on a bad file
    t0_log, t1_log = carmen_time_span(log_path)
    in_log = (rel.t1 >= t0_log) & (rel.t2 >= t0_log) & (rel.t1 <= t1_log) & (rel.t2 <= t1_log)
    if not in_log.any():  # (another log's: it had run the mission, then written NaN)
        raise CollabSlamError(
            f"{rel_path}: none of its {len(rel)} relations falls within the scans of "
            f"{log_path} ({t0_log:.3f} to {t1_log:.3f} s): the relations of another log?"
        )
    edges = np.linspace(t0_log, t1_log, robots + 1)
    edges[-1] += 1.0
    out = json_out.parent / json_out.stem
    out.mkdir(parents=True, exist_ok=True)
    clear_run_outputs(out)
    # A replay runs many times faster than the robots drove: pace it to what the
    # verifier keeps up with (the base station delays acks, the agents wait), as a
    # live run at sensor rate would be, instead of dropping candidates.
    cfg.exploration.enabled = False  # replayed robots fly nothing
    # the first segment defines `map`, whichever agent's first keyframe arrives first
    b = cfg.basestation
    b.map_frame_robot = b.map_frame_robot or "seg0"
    b.pause_intake_backlog = b.pause_intake_backlog or 20
    # ... and every global search of a robot not on the map yet runs, as at sensor rate
    b.constraints.global_pending_per_robot = max(b.constraints.global_pending_per_robot, 10**6)
    b.drain_timeout_s = max(b.drain_timeout_s, 600.0)
    # agents wait for every ack too (a loaded machine may be minutes behind the log)
    cfg.agent.drain_timeout_s = max(cfg.agent.drain_timeout_s, 600.0)
    # ... and the segments fly in step, as a team does live: each at the log's pace times
    # EVAL_REPLAY_RATE from one start. Unpaced (each as fast as its acks allow), they
    # drift apart in log time on a loaded machine, and a segment searches a map the first
    # one has not flown yet (ACES: 3 of 5 right unpaced; 4 of 4 paced at 3x).
    cfg.agent.replay_rate = cfg.agent.replay_rate or EVAL_REPLAY_RATE
    # (this run's wall time: the one in an earlier run's config.toml, used again, had every
    # segment behind its start, unpaced, without a word: ACES 2 of 3 robots on the map)
    cfg.agent.replay_start_unix = time.time() + EVAL_HEAD_START_S
    if b.db_path:  # an eval scores this run alone (supervisor.delete_database)
        delete_database(b.db_path)
    dump_config(cfg, out / "config.toml")
    ep = endpoint(free_port())
    group = ProcessGroup(out, log_level)
    ids = [f"seg{k}" for k in range(robots)]
    t_wall = time.monotonic()
    try:
        base = group.spawn(
            "basestation",
            [
                "basestation",
                "--config",
                str(out / "config.toml"),
                "--out",
                str(out),
                "--listen",
                ep,
            ],
        )
        agents = [
            group.spawn(
                rid,
                [
                    "agent",
                    "--config",
                    str(out / "config.toml"),
                    "--robot-id",
                    rid,
                    "--replay",
                    str(log_path),
                    "--segment",
                    f"{float(edges[k])!r}:{float(edges[k + 1])!r}",
                    "--connect",
                    ep,
                    "--out",
                    str(out),
                ],
            )
            for k, rid in enumerate(ids)
        ]
        group.wait_all_or_fail(agents, [base], timeout_s)
        base.proc.send_signal(signal.SIGINT)
        group.wait([base], 600.0)
    finally:
        group.terminate_all()
    wall = time.monotonic() - t_wall
    base_stats = json.loads((out / "basestation.json").read_text())
    parts = []
    on_map = []
    for rid in ids:
        info = base_stats["robots"].get(rid, {})
        kf_path = out / "trajectories" / f"{rid}.tum"
        if not info.get("anchored") or not kf_path.is_file():
            log.warning("%s never joined the map: its scans are not scored", rid)
            continue
        on_map.append(rid)
        parts.append(
            map_frame_trajectory(
                read_tum(out / "local_trajectories" / f"{rid}.tum"), read_tum(kf_path)
            )
        )
    if not parts:
        raise CollabSlamError("no robot made it onto the map")
    stamps = np.concatenate([p.stamps for p in parts])
    order = np.argsort(stamps, kind="stable")
    traj = Trajectory(
        stamps[order],
        np.concatenate([p.positions for p in parts])[order],
        np.concatenate([p.quats_xyzw for p in parts])[order],
    )
    write_tum(out / "trajectory.tum", traj)
    err = score_relations(traj, on_map_relations(rel, parts))
    if err.n_relations == 0:
        raise CollabSlamError(f"no relation of {rel_path} could be scored (robots on the "
                              f"map: {sorted(on_map)})")  # fmt: skip
    result = {
        "log": str(log_path),
        "relations": str(rel_path),
        "robots": robots,
        "robots_on_map": len(on_map),
        **err.as_dict(),  # (with Cartographer's formula's, to compare with its numbers)
        "n_relations_skipped": len(rel) - err.n_relations,  # not on the map, or no pose
        "loop_closures": base_stats.get("loop_closures", 0),
        "inter_robot_constraints": base_stats.get("inter_robot_constraints", 0),
        "rejected_candidates": base_stats.get("rejected_candidates", 0),
        "rejected_by_pcm": base_stats.get("rejected_by_pcm", 0),
        "false_match_fraction": cfg.basestation.constraints.false_match_fraction,
        "false_matches_injected": base_stats.get("false_matches_injected", 0),
        "false_matches_accepted": base_stats.get("false_matches_accepted", 0),
        "wall_s": wall,
        "candidates_dropped": sum(
            v
            for k, v in base_stats.get("constraint_builder", {}).items()
            if k.startswith("dropped_")
        ),
        "outputs": str(out),
    }
    json_out.parent.mkdir(parents=True, exist_ok=True)
    json_out.write_text(json.dumps(result, indent=1, allow_nan=False))
    return result
