"""What an agent writes at the end of its run (`AgentNode.write_outputs`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from agent.control_log import ControlRecorder, write_control_log
from common.row_spool import RowSpool
from common.trajectory_io import Trajectory, write_tum


def write_agent_outputs(
    out: Path, robot_id: str, stats: dict[str, Any], local: RowSpool, control: ControlRecorder
) -> None:
    """agents/<id>.json (`stats`), local_trajectories/<id>.tum (every scan's T_odom_base,
    the agent's own frame, from `local`: rows of stamp, x, y, z, yaw) and
    control_poses/<id>.csv (every control tick: T_odom_base, raw and applied T_map_odom)."""
    (out / "agents").mkdir(parents=True, exist_ok=True)
    (out / "agents" / f"{robot_id}.json").write_text(json.dumps(stats, indent=1))
    if len(local):
        rows = local.rows()
        path = out / "local_trajectories" / f"{robot_id}.tum"
        write_tum(path, Trajectory.from_pose4(rows[:, 0], rows[:, 1:]))
    if len(control):
        write_control_log(out / "control_poses" / f"{robot_id}.csv", control.log())


def frontend_stats(frontend: Any) -> dict[str, Any]:
    """The local SLAM front end's (or the odometry tracker's) statistics."""
    return {
        "odom_distance_m": frontend.distance_m,
        "scans_rejected": frontend.rejected_scans,
        "scans_too_few_points": frontend.few_point_scans,  # on the odometry's prediction
        "matches_gated": frontend.gated_matches,
        "odometry_resets": frontend.odometry_resets,  # odometry steps the scan refused
        "odometry_rejected": frontend.rejected_odometry,
    }
