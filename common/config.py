"""The one typed configuration tree, loaded from TOML and validated in one place.

Every parameter has a name, a unit in its comment and a default (from the papers
where they give one). `load_config()` reads a TOML file and/or dotted overrides,
rejects unknown keys and wrong types with a `ConfigError` that names the key, and checks
ranges (`common.config_validation.validate`). `dump_config()` writes the config used.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from common.config_constraints import ConstraintConfig
from common.config_sim import SimConfig
from common.config_validation import validate
from common.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class ZenohConfig:
    mode: str = "peer"  # peer | client | router
    listen: list[str] = field(default_factory=list)  # e.g. ["tcp/127.0.0.1:7447"]
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False  # off by default: explicit endpoints only
    # Learn other peers' endpoints from the peers one is connected to (and connect to
    # them). Off: only the configured endpoints (e.g. a drone behind a radio relay).
    gossip_scouting: bool = True
    # optional Zenoh JSON5 config (deploy/); its settings come first, and with one the two
    # scouting keys above are not used: the file's own scouting section decides
    config_file: str = ""


@dataclass
class LocalSlamConfig:
    """The agent's 2.5-D local SLAM (Cartographer local trajectory builder defaults)."""

    enabled: bool = True  # false: odometry integration only
    min_range_m: float = 0.1  # m, closer returns dropped
    max_range_m: float = 30.0  # m, farther returns dropped (UTM-30LX range)
    missing_data_ray_length_m: float = 5.0  # m, no-return beams clear free space this far
    voxel_filter_size_m: float = 0.025  # m, points inserted into submaps
    adaptive_max_length_m: float = 0.5  # m, adaptive voxel filter for matching
    adaptive_min_num_points: int = 200
    min_num_points: int = 20  # fewer usable points: the scan is not matched
    resolution_m: float = 0.05  # m, submap cells
    scans_per_submap: int = 90  # local keyframes per submap (Cartographer num_range_data)
    # Finished submaps kept in memory (oldest dropped). Local SLAM matches only against
    # the active ones; keeping all grew an agent by ~3.5 MB per sim minute (bench soak).
    max_finished_submaps: int = 0
    p_hit: float = 0.55
    p_miss: float = 0.49
    # A hit ray's end within this many cells of the surface it grazes is not cleared
    # (agent/probability_grid.py); 0: Cartographer's insertion. 2 (was 0): a plain 3 m
    # corridor, 40 m, -19.9 % -> -0.2 %; local SLAM only, Intel 0.1465 -> 0.1305 m, ACES
    # 0.085 -> 0.051 m, sim drift 0.041 -> 0.023 %. 1.5: ACES 0.145 m; 3: Intel 0.177 m.
    grazing_keep_cells: float = 2.0
    # Real-time correlative search before refinement; off as in Cartographer's 2-D default.
    # On the CARMEN logs it picked far-off near-ties (yaw jumps of 10-20 deg on ACES) and
    # added jitter: Intel 1.8 m -> 0.19 m, ACES 1.0 m -> 0.06-0.16 m mean relation error off.
    use_correlative: bool = False
    linear_search_window_m: float = 0.3  # m
    angular_search_window_deg: float = 20.0  # deg
    # Refiner prior weights toward the odometry prediction; 3 (was 0.1), relations < 2 s,
    # local SLAM only: ACES 0.0362 -> 0.0332 m, Intel 0.0123 -> 0.0115 m; sim drift 0.034 ->
    # 0.026 %; ACES 3 robots 0.0384 -> 0.0348 m. rotation_weight 1 or 10: no better / worse.
    translation_weight: float = 3.0  # refiner prior weight (1/m)
    rotation_weight: float = 0.1  # refiner prior weight (1/rad)
    min_match_score: float = 0.3  # mean cell probability below which a match is rejected
    max_match_yaw_jump_deg: float = 15.0  # deg from the odometry's prediction: rejected (0: off)
    motion_filter_min_distance_m: float = 0.05  # m since the last local keyframe ...
    motion_filter_min_angle_deg: float = 1.0  # deg ...
    motion_filter_max_time_s: float = 5.0  # s ... or this long: insert anyway
    use_odometry: bool = True  # predict with odometry (else constant velocity)
    use_imu_attitude: bool = True  # project the planar scan with the IMU's roll and pitch
    floor_margin_m: float = 0.2  # m: projected points this close to the floor are dropped


@dataclass
class SmoothingConfig:
    """Smoothed pose output for control (seed 000 §II, eq. 2): a new correction
    T_map_odom is blended in with alpha(t) = 1 / (1 + s * exp(t - t_x)), the weight of
    the old one (t in s of sensor time since the correction arrived)."""

    enabled: bool = True  # false: the control pose jumps with every correction
    s: float = 1.5  # eq. 2 scale (dimensionless)
    t_x_s: float = 3.0  # s, eq. 2 time at which alpha = 1 / (1 + s)
    duration_s: float = 7.0  # s, after this the new correction is applied in full


@dataclass
class AgentConfig:
    keyframe_distance_m: float = 0.2  # m, seed 002: new base-station keyframe every 0.2 m
    keyframe_angle_rad: float = 0.1  # rad, ... or every 0.1 rad
    local_keyframe_period_s: float = 0.25  # s, seed 002: local-map keyframes
    odom_sigma_per_m: float = 0.01  # m (keyframe deltas: the graph's odometry; docs)
    odom_sigma_yaw_per_rad: float = 0.004  # rad
    odom_sigma_yaw_per_m: float = 0.001  # rad
    odom_sigma_min: float = 1e-3  # floor on every std (m or rad)
    outbox_max: int = 20000  # keyframes kept until acknowledged
    outbox_warn_fraction: float = 0.8  # warn when the outbox is this full
    # acknowledged keyframes kept on disk (agent/keyframe_history.py) for a base station
    # that has lost them (a new laptop): the latest half at least; 0: none
    keyframe_history: int = 20000
    # with a folder: the agent's state and keyframes kept there, so that an agent
    # restarted mid-mission goes on where it was (agent/resume.py); a state older than
    # resume_within_s is another mission's, deleted
    state_dir: str = ""
    resume_within_s: float = 60.0  # s (systemd restarts a dead agent after 2 s)
    resend_timeout_s: float = 1.0  # s wall without ack before resending from the oldest
    resend_batch: int = 50  # keyframes resent per timeout
    waypoint_tolerance_m: float = 0.3  # m
    cruise_speed_mps: float = 1.0  # m/s
    cruise_altitude_m: float = 1.0  # m above ground
    max_accel_mps2: float = 1.0  # m/s^2, used to slow down before the last waypoint
    yaw_gain: float = 1.5  # 1/s, heading controller gain
    full_speed_off_nose_deg: float = 60.0  # deg: flies at full speed this far off the nose
    max_off_nose_deg: float = 105.0  # deg: turns first beyond (keep within the laser's view)
    # Safety guard on every command (agent/safety_guard.py): the drone must be able to stop
    # with its disc vehicle_radius_m + safety_margin_m clear of every live scan point.
    vehicle_radius_m: float = 0.25  # m, the drone's collision disc
    safety_margin_m: float = 0.05  # m, keep below exploration.inflation_m - vehicle_radius_m
    safety_reaction_s: float = 0.3  # s of travel before braking: latency + velocity lag
    velocity_lag_s: float = 0.2  # s, the vehicle's velocity time constant (guard's model)
    blocked_after_s: float = 2.0  # s held still by the guard: report "blocked" (replan)
    # Neighbour guard (the same): other drones' centres, relayed by the base station in
    # answer to each RobotState, kept neighbour_keep_m away (the 1 m target + what
    # news 0.2-0.4 s old and the vehicle's lag cost: 1.1 m gave 0.8 m in greedy runs),
    # each drone braking within half the gap; positions moved on at their velocity for
    # up to neighbour_extrapolation_s, ignored once neighbour_max_age_s old.
    neighbour_keep_m: float = 1.3  # m between centres
    neighbour_max_age_s: float = 1.0  # s sim time
    neighbour_extrapolation_s: float = 0.5  # s
    # Scripted tours (exploration.enabled = false) are planned without the others: the
    # guard would hold drones meeting in a corridor for good (a 10-drone 30-min soak flew
    # 5-18 % of its distance). On for exploration only, unless this is true.
    neighbour_guard_tours: bool = False
    state_period_s: float = 0.2  # s sim time between RobotState messages (and Neighbours)
    # pass the drone driver's GnssFix on to the base station (a Zenoh peer routes nothing
    # between its links): on for a real drone whose driver sends fixes (the systemd unit
    # sets it); off in simulation, where the simulator reaches the base station itself
    relay_gnss: bool = False
    drain_timeout_s: float = 15.0  # s wall: on shutdown wait this long for acks
    # a live drone's sensor queue (agent/sensor_sources.py): local SLAM falling behind its
    # laser drops the scans waiting this far (sensor time) behind the newest, and holds
    # at most sensor_queue_max messages (the newest dropped past it); 0: no lag limit
    max_scan_lag_s: float = 1.0
    sensor_queue_max: int = 100_000
    replay_max_unacked: int = 200  # --replay: pause the log while this many keyframes wait
    # --replay: log seconds per wall second (0: as fast as the acks allow), from the wall
    # clock time replay_start_unix (0: when the agent starts). Replays sharing a start
    # and a rate fly their log segments in step, as a team does live.
    replay_rate: float = 0.0
    replay_start_unix: float = 0.0
    malloc_arenas: int = 2  # glibc malloc arenas of the agent process (0: glibc's default)
    local_slam: LocalSlamConfig = field(default_factory=LocalSlamConfig)
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)


@dataclass
class MapConfig:
    resolution_m: float = 0.05  # m per cell
    p_hit: float = 0.7
    p_miss: float = 0.4
    p_min: float = 0.12
    p_max: float = 0.97
    occupied_thresh: float = 0.65  # map_server convention
    free_thresh: float = 0.35  # free after two looks (0.4 -> 0.31), not four (0.196): docs
    max_free_range_m: float = 10.0  # m, no-return beams clear free space up to here
    pose_moved_m: float = 0.02  # m: a keyframe that moved more than this forces a re-render
    pose_moved_rad: float = 0.005  # rad: likewise for heading
    # After a correction the moved region is redrawn tile by tile (tiles of this side, a
    # multiple of resolution_m), most-moved first, at most rerender_budget_s of the main
    # thread per map refresh (basestation/map_builder.py); outputs finish every tile.
    rerender_tile_m: float = 12.0  # m (8: 1.7x the CPU of 12 for a full redraw; 16: 0.9x)
    rerender_budget_s: float = 0.1  # s wall per map refresh
    # m: keyframes farther than this from the first are not drawn, and the map goes no
    # farther (a 1 km square at most: 2 GB at 0.05 m); one far GNSS fix had allocated TiB
    max_radius_m: float = 500.0


@dataclass
class GpsConfig:
    """GPS position factors in the pose graph (seed 000 §III, eq. 3-7); map = ENU."""

    enabled: bool = False
    weighting: str = "inverse"  # inverse (eq. 5) | isotropic (eq. 6, worst sigma)
    a: float = 1.0  # eq. 7: weight = a / sigma + b (either weighting's sigma), 1/m
    b: float = 0.0  # eq. 7, 1/m
    huber: bool = True  # Huber loss on the whitened GPS residual
    huber_k: float = 1.345  # Huber width in whitened units
    sigma_min_m: float = 0.05  # m, floor on reported sigmas
    antenna_x_m: float = 0.0  # m, GPS antenna lever arm in the body frame (forward)
    antenna_y_m: float = 0.0  # m (left)
    # Virtual ENU-origin trajectory (seed 000 §III-C): the first node gets a prior at the
    # first fix with the autopilot's heading; loose in position, as firm as a compass in yaw.
    start_sigma_xy_m: float = 100.0  # m
    start_sigma_yaw_rad: float = 0.1  # rad, magnetometer heading
    max_pending_fixes: int = 1000  # per robot: fixes waiting for their bracketing nodes
    # s of keyframe time between GPS batches into iSAM2 (seed 000: at the periodic
    # optimizations, once a minute); every GPS update moves the whole trajectory.
    batch_period_s: float = 30.0


@dataclass
class BaseStationConfig:
    # iSAM2 (gtsam ISAM2Params), chosen with the 3-robot feeds of `collabslam bench backend`
    # (M3500[:500], city10000[:3000] and [:10000], CPU time per update; docs/architecture.md
    # "Back end"); every choice below kept chi2 within 0.1% of batch LM.
    relinearize_threshold: float = 0.1  # rad or m: a larger delta step relinearizes a variable
    # Updates between relinearization checks (gtsam's default); 1 back-substitutes all deltas
    relinearize_skip: int = 10  # each update first: same chi2, +5-30% CPU at 500 nodes
    wildfire_threshold: float = 0.001  # rad or m: back-substitution stops below (gtsam's;
    # 0.01 queried 1.5x faster but cost +2% chi2 on city10000[:3000])
    isam2_factorization: str = "CHOLESKY"  # QR: 1.5-2x slower, same chi2
    cache_linearized_factors: bool = True  # False: 10-20% slower
    # Every robot's newest node at the root of the Bayes tree (iSAM2 constrainedKeys), not
    # only the new factors' keys: the next node of any robot re-eliminates the root only.
    # M3500[:500]: -40% CPU per update (p50); city10000: -15% p50, same p95.
    heads_last: bool = True
    # Re-order the whole Bayes tree (a batch elimination, 0.3 s at 10,000 nodes) once its
    # fill-in exceeds this x the last ordering's; 0: never. city10000 at 1.5: +8% CPU: off.
    adaptive_reorder_threshold: float = 0.0
    track_changes: bool = False  # O(n) UpdateStats.changed_robots per update (not needed)
    # Reduced pose graph (basestation/pose_graph_reduction.py): from reduce_after_nodes
    # nodes on, a node reduce_lag keyframes old becomes an alias of a variable within
    # reduce_distance_m (0: never) of its robot or of one it shares several inter-robot
    # constraints with: variables grow with the area, not the time flown. Below 2,000 nodes
    # an update stays under ~1 ms unreduced and frozen offsets cost accuracy (Intel: 0.0151
    # m unreduced, 0.0162 m reduced from the first node; city10000: docs/results.md).
    reduce_distance_m: float = 0.5
    reduce_lag: int = 20
    reduce_after_nodes: int = 2000
    reduce_tie_budget: float = 0.5  # final-constraint ties per variable, then folded (0: no cap)
    isam2_rebuild_nodes: int = 1000  # reducing: a fresh iSAM2 per this many nodes (0: never)
    reduce_tie_degree: int = 3  # at a rebuild, ties kept per place (+ a spanning forest; 0: all)
    prior_sigma_xy_m: float = 0.01  # m, known start pose
    prior_sigma_yaw_rad: float = 0.001  # rad
    map_update_period_s: float = 2.0  # s wall between global map refreshes
    batch_max: int = 200  # keyframes per processing batch
    reorder_window: int = 1000  # out-of-order keyframes held per robot waiting for a gap
    # Keyframes whose scan points (for matching, ~5 kB each) stay in memory, most recently
    # used first; older ones are made again from their scans (~0.1 ms) when asked for.
    scan_points_cache: int = 3000
    # With a database (db_path): keyframes whose scans (2.2 kB each) stay in memory, most
    # recently used first; older ones are read back from the database (~35 us) when a
    # loop closure or a map redraw needs them. Without a database all stay in memory.
    scan_cache: int = 5000
    known_start_poses: bool = True  # use the scenario's start poses (false: find by matching)
    # With no known start at all, this robot's first keyframe defines `map` (its odom frame
    # there); the others float until matched to it. Empty: whichever robot sends first.
    map_frame_robot: str = ""
    # Keyframe intake pauses while more candidates than this wait for verification
    # (0: never). Acks then wait too, which paces a log replay to what the verifier
    # keeps up with; live robots keep flying and their outboxes hold the keyframes.
    pause_intake_backlog: int = 0
    drain_timeout_s: float = 60.0  # s wall: at shutdown, finish pending verifications this long
    # SQLite file for crash recovery (basestation/persistence.py): every admitted keyframe,
    # match, epoch and path is written there before it is acknowledged or published, and
    # a restart with the same file resumes the mission. Empty: no persistence.
    db_path: str = ""
    update_series_period_s: float = 10.0  # s wall per row of iSAM2 latencies over time
    # glibc malloc arenas of the base station process (0: glibc's default, 8 per core; its
    # threads' arenas kept free memory that grew with the mission: common/memory.py)
    malloc_arenas: int = 2
    # KiB from which malloc maps a block on its own and unmaps it when freed (0: glibc's
    # threshold, rising up to 32 MB): per-update arrays over all keyframes leave the heap
    malloc_mmap_threshold_kb: int = 256
    # Where the per-keyframe arrays live (~150 bytes a keyframe; common/growable.py):
    # memory-mapped temporary files in this directory ("": the database's directory, or
    # the system's temporary one without a database; not a tmpfs) or "memory"
    arrays_dir: str = ""
    # Map snapshots kept for coverage over time (exploration): beyond this many, every
    # other one is dropped and the sync stride doubles (~40 kB each for 30 x 25 m; 0: all).
    map_history_max_snapshots: int = 1000
    constraints: ConstraintConfig = field(default_factory=ConstraintConfig)
    gps: GpsConfig = field(default_factory=GpsConfig)


@dataclass
class ExplorationConfig:
    """Autonomous exploration (seed 002 §1.2): the base station sends frontier paths."""

    enabled: bool = True  # false: robots fly the scenario's scripted tours instead
    # coordinated: joint eq. 3 assignment, distinct goals, paths around the other robots;
    # greedy: the baseline, every robot to its own nearest frontier (explore_lite style)
    strategy: str = "coordinated"
    period_s: float = 1.0  # s wall between exploration steps of the base station
    frontier_radius_m: float = 0.3  # r of the frontier rule (Fig. 4)
    min_frontier_cells: int = 8  # smaller frontier groups are noise
    w_distance: float = 1.0  # w1 of eq. 3, per m
    w_heading: float = 0.5  # w2, per rad
    w_previous: float = 0.5  # w3, per m from the previous goal
    # Spreading (coordinated only): a frontier within spread_radius_m of a goal another
    # robot is flying to costs w_spread per m inside (that robot will likely see it).
    w_spread: float = 1.0  # per m
    spread_radius_m: float = 5.0  # m
    # ... and one in line of sight of the rest of its path, within seen_range_m and the
    # laser's field of view around its flight direction, costs seen_cost_m (0: off).
    seen_range_m: float = 6.0  # m
    seen_fov_deg: float = 270.0  # deg
    seen_cost_m: float = 5.0  # m of travel
    # Own ground: a frontier closer to a robot than to every other (those flying: from
    # their goals) costs it w_own per m of that lead less, up to own_cap_m (0: off).
    w_own: float = 0.5
    own_cap_m: float = 10.0  # m
    tours: bool = True  # goals from the robot's own min-max tour only (frontier_tours.py)
    handover_m: float = 2.0  # m: a free robot this much nearer another's goal competes for it
    handover_unknown: float = 3.0  # x per m through unknown space in that travel distance
    w_gain: float = 0.25  # information (0: off): m per m^2 in view short of gain_full_m2
    gain_full_m2: float = 25.0  # m^2
    gain_near_m: float = 5.0  # m of travel: the cost x min(1, travel / gain_near_m)
    gain_radius_m: float = 4.0  # m
    inflation_m: float = 0.35  # m, no-collision zone around obstacles
    robot_clearance_m: float = 1.0  # m, disc around other robots and their paths
    lag_s: float = 0.6  # s the others are judged behind/ahead of their schedules (docs)
    # RRT* work per path in validity checks (~0.2 s here): plans do not depend on load
    planning_checks: int = 40000
    planning_time_s: float = 1.0  # s, caps the CPU time of one path (not in simulation)


@dataclass
class ProtocolConfig:
    max_message_bytes: int = 8 * 1024 * 1024  # bytes; larger payloads are dropped


@dataclass
class Config:
    fleet: str = "default"
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    map: MapConfig = field(default_factory=MapConfig)
    basestation: BaseStationConfig = field(default_factory=BaseStationConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)

    def base_sync_period_s(self) -> float:
        """Sim s between a lock-step simulator's clock handshakes with the base station,
        which explores only then (0: none; it paces itself by the wall clock)."""
        e, s = self.exploration, self.sim
        return e.period_s if e.enabled and s.sync_basestation and s.clock == "lockstep" else 0.0


# --- loading -------------------------------------------------------------------------------


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Shipped defaults <- TOML file <- dotted overrides ({"sim.seed": 3}); validated."""
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {path}") from None
        except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, not text
            raise ConfigError(f"{path}: cannot read the config file: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: {exc}") from None
    for dotted, value in (overrides or {}).items():
        node = data
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{dotted}: {p} is not a table")
        node[leaf] = value
    cfg = _build(Config, data, "")
    validate(cfg)
    return cfg


# keys that did something in an earlier version: a config written then (a run's
# config.toml copied to /etc/collabslam) is taken with a warning, not refused
RETIRED_KEYS = frozenset({
    "agent.local_slam.match_sigma_per_m",  # bench gps's own noise model (69th session)
    "agent.local_slam.match_sigma_yaw_per_m",
})  # fmt: skip


def _build(cls: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    retired = {k[len(prefix) :] for k in RETIRED_KEYS if k.rpartition(".")[0] + "." == prefix}
    for old in sorted(set(data) & retired):
        log.warning("config key %s%s is no longer used: ignored", prefix, old)
    data = {k: v for k, v in data.items() if k not in retired}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key {prefix}{unknown[0]} (known keys here: {', '.join(sorted(names))})"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}{name}"
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = _build(hint, value, key + ".")
        else:
            kwargs[name] = _coerce(hint, value, key)
    return cls(**kwargs)


def _coerce(hint: Any, value: Any, key: str) -> Any:
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if typing.get_origin(hint) is list:
        (item,) = typing.get_args(hint)
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [_coerce(item, v, f"{key}[{i}]") for i, v in enumerate(value)]
    raise ConfigError(f"{key}: unsupported type {hint}")  # pragma: no cover


def dump_config(cfg: Config, path: str | Path) -> None:
    """Write the config actually used as TOML."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(tomli_w.dumps(dataclasses.asdict(cfg)))
