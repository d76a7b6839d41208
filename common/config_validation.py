"""Range checks on the config tree: ``validate(cfg)`` raises a ConfigError naming the key.

``common.config.load_config`` calls it on every config it builds; code that edits a
loaded config (benchmarks deriving variants) calls it again. Types were checked while
loading; here only values and their relations.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import typing
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any

from common.errors import ConfigError
from common.map_io import EXPLORATION_FREE_THRESH
from protocol.messages import KEYFRAME_VAR_RANGE

if TYPE_CHECKING:  # common.config imports this module
    from common.config import BaseStationConfig, Config

log = logging.getLogger(__name__)


# Numbers that may be negative: biases, offsets and coordinates. Every other number in the
# tree is a length, duration, rate, count, weight or seed and must be >= 0 (stricter
# checks below where 0 means nothing sensible).
SIGNED_KEYS = frozenset(
    {
        "sim.odometry.yaw_rate_bias",
        "sim.imu.gyro_bias",
        "sim.imu.accel_bias",
        "sim.altimeter.bias_m",
        "sim.gnss.bias_east_m",
        "sim.gnss.bias_north_m",
        "sim.gnss.bias_up_m",
        "sim.gnss.vertical_drift_mps",
        "sim.gnss.origin_lat_deg",
        "sim.gnss.origin_lon_deg",
        "sim.gnss.origin_alt_m",
        "basestation.gps.antenna_x_m",
        "basestation.gps.antenna_y_m",
    }
)


def numeric_keys(obj: Any, prefix: str = "") -> Iterator[tuple[str, int | float]]:
    """(dotted key, value) of every int or float leaf of a config dataclass tree."""
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value, hint = getattr(obj, f.name), hints[f.name]
        if dataclasses.is_dataclass(hint):
            yield from numeric_keys(value, f"{prefix}{f.name}.")
        elif hint in (int, float):
            yield f"{prefix}{f.name}", value


INT_MAX = 2**31 - 1  # GTSAM and numpy take C ints (2**70 ended in a TypeError)


def _numbers_in_range(cfg: Config) -> None:
    for key, value in numeric_keys(cfg):
        if value < 0 and key not in SIGNED_KEYS:
            raise ConfigError(f"{key}: expected a value >= 0, got {value}")
        if isinstance(value, int) and abs(value) > INT_MAX:
            raise ConfigError(f"{key}: expected at most {INT_MAX}, got {value}")


IP_LINKS = ("tcp", "udp", "tls", "quic", "ws")  # Zenoh locators of host:port


def _check_endpoint(key: str, endpoint: str) -> None:
    """`proto/host:port` (Zenoh's metadata after `?` or `#` allowed): `--connect
    tcp/127.0.0.1` had been taken, and the agent never connected, without a word."""
    proto, _, address = endpoint.partition("/")
    address = address.split("?")[0].split("#")[0]
    if proto not in IP_LINKS:
        if proto and address:  # another link type (unixsock-stream, serial): Zenoh's
            return
        raise ConfigError(f"{key}: expected proto/host:port, got {endpoint!r}")
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(
            f"{key}: expected {proto}/host:port with a port 1..65535, got {endpoint!r}"
        )


def _positive(key: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(f"{key}: expected a value > 0, got {value}")


def _prob(key: str, value: float) -> None:
    if not 0.0 < value < 1.0:
        raise ConfigError(f"{key}: expected a probability in (0, 1), got {value}")


def _positive_fields(section: str, obj: Any, names: Iterable[str]) -> None:
    """Each ``obj.<name>`` > 0 (keys reported as ``section.name``)."""
    for name in names:
        _positive(f"{section}.{name}", getattr(obj, name))


def _non_negative_fields(section: str, obj: Any, names: Iterable[str]) -> None:
    """Each ``obj.<name>`` >= 0 (keys reported as ``section.name``)."""
    for name in names:
        value = getattr(obj, name)
        if value < 0.0:
            raise ConfigError(f"{section}.{name}: expected a value >= 0, got {value}")


def validate(cfg: Config) -> None:
    """Range checks across the tree; raises ConfigError naming the key."""
    from protocol.keys import Keys  # local: protocol depends on common, not the reverse

    try:
        Keys(cfg.fleet)
    except ConfigError as exc:
        raise ConfigError(f"fleet: {exc}") from None
    for key in ("listen", "connect"):
        for ep in getattr(cfg.zenoh, key):
            _check_endpoint(f"zenoh.{key}", ep)
    if cfg.zenoh.mode not in ("peer", "client", "router"):
        raise ConfigError(f"zenoh.mode: expected peer, client or router, got {cfg.zenoh.mode!r}")
    if cfg.sim.clock not in ("lockstep", "realtime"):
        raise ConfigError(f"sim.clock: expected lockstep or realtime, got {cfg.sim.clock!r}")
    _numbers_in_range(cfg)
    b = cfg.basestation  # (a review's 2-drone rooms15 mission: r1 hovered for good, r0
    if cfg.exploration.enabled and not b.known_start_poses and not b.gps.enabled:  # alone)
        raise ConfigError("basestation.known_start_poses = false needs exploration.enabled "
                          "= false (scripted tours) or basestation.gps.enabled (starts from "
                          "GNSS headings): exploration gives paths only to robots on the map, "
                          "and a robot waiting for its first one hovers where matches cannot "
                          "place it")  # fmt: skip
    _validate_sim(cfg)
    _validate_map(cfg)
    _validate_agent(cfg)
    _validate_backend(cfg.basestation)
    _positive_fields("protocol", cfg.protocol, ("max_message_bytes",))
    _positive_fields(
        "exploration",
        cfg.exploration,
        (
            "period_s", "frontier_radius_m", "planning_time_s", "planning_checks",
            "seen_range_m", "gain_radius_m", "gain_near_m",
        ),
    )  # fmt: skip
    _non_negative_fields(
        "exploration",
        cfg.exploration,
        (
            "seen_cost_m", "seen_fov_deg", "w_own", "own_cap_m", "w_gain", "gain_full_m2",
            "handover_m", "lag_s",
        ),
    )  # fmt: skip
    if cfg.exploration.strategy not in ("coordinated", "greedy"):
        raise ConfigError(
            "exploration.strategy: expected coordinated or greedy, "
            f"got {cfg.exploration.strategy!r}"
        )
    if not cfg.exploration.handover_unknown >= 1.0:
        raise ConfigError(
            "exploration.handover_unknown: expected a factor >= 1, "
            f"got {cfg.exploration.handover_unknown}"
        )
    a, e = cfg.agent, cfg.exploration
    if e.enabled and a.vehicle_radius_m + a.safety_margin_m >= e.inflation_m:
        # paths keep inflation_m from walls: the guard would hold the drone along them
        raise ConfigError(
            "agent.vehicle_radius_m + agent.safety_margin_m: expected less than "
            f"exploration.inflation_m ({e.inflation_m}), got "
            f"{a.vehicle_radius_m} + {a.safety_margin_m}"
        )
    _validate_gps(cfg)


def _validate_sim(cfg: Config) -> None:
    sim, las = cfg.sim, cfg.sim.laser
    _positive_fields(
        "sim",
        sim,
        (
            "rate",
            "lockstep_timeout_s",
            "basestation_timeout_s",
            "sync_wait_s",
            "ground_truth_rate_hz",
        ),
    )
    _positive_fields("sim.laser", las, ("beams", "fov_deg", "range_max_m", "rate_hz"))
    quad = sim.quadrotor
    _positive_fields(
        "sim.quadrotor",
        quad,
        ("max_speed_mps", "max_accel_mps2", "radius_m", "max_vertical_speed_mps",
         "max_yaw_rate_rps"),
    )  # fmt: skip
    _positive("sim.start_timeout_s", sim.start_timeout_s)
    if las.fov_deg > 360.0:
        raise ConfigError(f"sim.laser.fov_deg: expected <= 360, got {las.fov_deg}")
    if not 0 <= las.range_min_m < las.range_max_m:
        raise ConfigError("sim.laser.range_min_m: expected 0 <= range_min_m < range_max_m")
    if sim.start_spacing_m < 2.0 * quad.radius_m:  # (0.3 m: drones started in contact)
        raise ConfigError("sim.start_spacing_m: expected at least twice "
                          "sim.quadrotor.radius_m (drones would start in contact)")  # fmt: skip


# m: exploration's frontier rule works in cells, and on a coarser map no frontier forms
# (0.15 m: drones told to hold for good; 0.2 m: "exploration over" at t = 0)
MAX_EXPLORATION_RESOLUTION_M = 0.1


def _validate_map(cfg: Config) -> None:
    _positive("map.resolution_m", cfg.map.resolution_m)
    if cfg.exploration.enabled and cfg.map.resolution_m > MAX_EXPLORATION_RESOLUTION_M:
        raise ConfigError(f"map.resolution_m: at most {MAX_EXPLORATION_RESOLUTION_M} m with "
                          "exploration on (its frontiers need finer cells), got "
                          f"{cfg.map.resolution_m}")  # fmt: skip
    for key in ("p_hit", "p_miss", "p_min", "p_max", "occupied_thresh", "free_thresh"):
        _prob(f"map.{key}", getattr(cfg.map, key))
    m = cfg.map  # (checked at the first map update, these had stopped the base station)
    if not m.p_min < m.p_miss < 0.5 < m.p_hit < m.p_max:
        raise ConfigError("map.p_min / p_miss / p_hit / p_max: expected "
                          "p_min < p_miss < 0.5 < p_hit < p_max")  # fmt: skip
    if not m.free_thresh < m.occupied_thresh or not m.occupied_thresh > EXPLORATION_FREE_THRESH:
        raise ConfigError(f"map.free_thresh / occupied_thresh: expected free_thresh < "
                          f"occupied_thresh and occupied_thresh > {EXPLORATION_FREE_THRESH} "
                          "(exploration's free threshold)")  # fmt: skip
    _positive("map.rerender_tile_m", cfg.map.rerender_tile_m)
    _positive("map.max_radius_m", cfg.map.max_radius_m)
    if cfg.map.rerender_budget_s < 0.0:
        raise ConfigError("map.rerender_budget_s: expected a value >= 0")
    if cfg.map.rerender_tile_m < 10 * cfg.map.resolution_m:
        raise ConfigError("map.rerender_tile_m: expected at least 10 cells (10 x resolution_m)")
    _positive("basestation.scan_points_cache", cfg.basestation.scan_points_cache)
    _positive("basestation.scan_cache", cfg.basestation.scan_cache)


def _validate_agent(cfg: Config) -> None:
    a, ls = cfg.agent, cfg.agent.local_slam
    _positive_fields(
        "agent",
        a,
        (
            "vehicle_radius_m",
            "blocked_after_s",
            "keyframe_distance_m",
            "keyframe_angle_rad",
            "outbox_max",
            "resend_batch",  # 0 would never resend a keyframe lost on the way
            "resend_timeout_s",
            "replay_max_unacked",
            "cruise_speed_mps",
            "odom_sigma_min",
            "waypoint_tolerance_m",
            "max_accel_mps2",
            "yaw_gain",
            "state_period_s",
            "sensor_queue_max",
        ),
    )
    _non_negative_fields(
        "agent",
        a,
        (
            "max_scan_lag_s",  # 0: no lag limit
            "safety_margin_m",
            "safety_reaction_s",
            "velocity_lag_s",
            "malloc_arenas",
            "neighbour_keep_m",  # 0: no neighbour guard
            "neighbour_max_age_s",
            "neighbour_extrapolation_s",
        ),
    )
    lo, hi = (v**0.5 for v in KEYFRAME_VAR_RANGE)  # (below: every keyframe refused)
    if not lo <= a.odom_sigma_min <= hi:
        raise ConfigError(f"agent.odom_sigma_min: expected {lo:g}..{hi:g} (a keyframe's "
                          f"variances must be within {KEYFRAME_VAR_RANGE})")  # fmt: skip
    if not 0.0 < a.outbox_warn_fraction <= 1.0:
        raise ConfigError("agent.outbox_warn_fraction: expected a value in (0, 1]")
    if not 0.0 <= a.full_speed_off_nose_deg < a.max_off_nose_deg <= 180.0:
        raise ConfigError(
            "agent.full_speed_off_nose_deg / max_off_nose_deg: expected "
            "0 <= full_speed_off_nose_deg < max_off_nose_deg <= 180"
        )
    _positive_fields("agent.smoothing", a.smoothing, ("s", "duration_s"))
    _non_negative_fields("agent.smoothing", a.smoothing, ("t_x_s",))
    sm = a.smoothing  # eq. 2's old weight ~1 at first and ~0 at the end: else the control
    # pose jumps by most of a correction (t_x_s = 10: 0.93 m of 1 m at 7 s)
    first, last = sm.s * math.exp(-sm.t_x_s), sm.s * math.exp(sm.duration_s - sm.t_x_s)
    if sm.enabled and not (first <= 1.0 / 9.0 and last >= 19.0):
        raise ConfigError("agent.smoothing.s / t_x_s / duration_s: expected the old "
                          "correction's weight >= 0.9 at first and <= 0.05 at duration_s "
                          "(s exp(-t_x_s) <= 1/9, s exp(duration_s - t_x_s) >= 19)")  # fmt: skip
    if a.cruise_altitude_m <= ls.floor_margin_m:  # (every tilted scan's points: the floor)
        raise ConfigError("agent.cruise_altitude_m: expected above "
                          "agent.local_slam.floor_margin_m")  # fmt: skip
    if a.neighbour_keep_m > 0.0 and a.neighbour_max_age_s <= 2.0 * a.state_period_s:
        raise ConfigError("agent.neighbour_max_age_s: expected more than twice "
                          "agent.state_period_s (the others' news comes that old)")  # fmt: skip
    _positive_fields(
        "agent.local_slam",
        ls,
        (
            "resolution_m",
            "max_range_m",
            "scans_per_submap",
            "voxel_filter_size_m",
            "adaptive_max_length_m",
            "min_num_points",
        ),
    )
    _non_negative_fields(
        "agent.local_slam", ls, ("max_match_yaw_jump_deg", "grazing_keep_cells")
    )  # 0: off
    if not 0.5 < ls.p_hit < 1.0 or not 0.0 < ls.p_miss < 0.5:
        raise ConfigError("agent.local_slam.p_hit / p_miss: expected 0 < p_miss < 0.5 < p_hit < 1")
    if not 0 <= ls.min_range_m < ls.max_range_m:
        raise ConfigError("agent.local_slam.min_range_m: expected 0 <= min_range_m < max_range_m")
    if ls.max_finished_submaps < 0:
        raise ConfigError("agent.local_slam.max_finished_submaps: expected >= 0")
    if not 0.0 <= ls.min_match_score < 1.0:
        raise ConfigError("agent.local_slam.min_match_score: expected a value in [0, 1)")


def _validate_backend(b: BaseStationConfig) -> None:
    """iSAM2 settings, priors and the constraint builder."""
    _positive_fields(
        "basestation",
        b,
        (
            "prior_sigma_xy_m",
            "prior_sigma_yaw_rad",
            "update_series_period_s",
            "relinearize_threshold",
            "relinearize_skip",
            "reduce_lag",
            "batch_max",  # 0 would never take a keyframe from the inbox
        ),
    )
    if not b.reduce_distance_m >= 0.0:
        raise ConfigError("basestation.reduce_distance_m: expected a value >= 0 (0: off)")
    if b.reduce_after_nodes < 0:
        raise ConfigError("basestation.reduce_after_nodes: expected a value >= 0")
    if not b.reduce_tie_budget >= 0.0:
        raise ConfigError("basestation.reduce_tie_budget: expected a value >= 0 (0: no cap)")
    if b.isam2_rebuild_nodes < 0:
        raise ConfigError("basestation.isam2_rebuild_nodes: expected a value >= 0 (0: never)")
    if b.reduce_tie_degree < 0:
        raise ConfigError("basestation.reduce_tie_degree: expected a value >= 0 (0: keep all)")
    if b.map_history_max_snapshots < 0:
        raise ConfigError("basestation.map_history_max_snapshots: expected >= 0 (0: all)")
    if b.malloc_arenas < 0:
        raise ConfigError("basestation.malloc_arenas: expected >= 0 (0: glibc's default)")
    if b.malloc_mmap_threshold_kb < 0:
        raise ConfigError("basestation.malloc_mmap_threshold_kb: expected >= 0 (0: glibc's)")
    if b.isam2_factorization not in ("CHOLESKY", "QR"):
        raise ConfigError("basestation.isam2_factorization: expected CHOLESKY or QR")
    if b.wildfire_threshold < 0.0:
        raise ConfigError("basestation.wildfire_threshold: expected a value >= 0")
    if b.adaptive_reorder_threshold != 0.0 and not b.adaptive_reorder_threshold > 1.0:
        raise ConfigError("basestation.adaptive_reorder_threshold: expected 0 (off) or > 1")
    cc = b.constraints
    _positive_fields(
        "basestation.constraints",
        cc,
        (
            "max_candidates_per_s",
            "global_candidates",  # (0: every whole-map search raised)
            "global_map_rebuild_nodes",
            "global_query_keyframes",
            "candidate_stride",
            "backfill_max_candidates",
            "search_radius_m",
            "global_search_every",
            "global_pending_per_robot",
            "min_consistent_to_merge",
            "merge_stretch_keyframes",
            "linear_window_m",
            "angular_window_deg",
            "max_corr_dist_m",
            "pcm_chi2",
            "pcm_window",
            "robust_k",
            "max_queue",
        ),
    )
    _non_negative_fields(
        "basestation.constraints", cc, ("inter_redundant_keyframes", "join_check_keyframes")
    )
    for key in ("min_score", "min_overlap", "global_min_score"):  # (> 1 had been taken:
        if not 0.0 <= getattr(cc, key) <= 1.0:  # no match ever; 1: whole-map search off)
            raise ConfigError(f"basestation.constraints.{key}: expected 0 <= value <= 1")
    if not 0.0 <= cc.false_match_fraction < 1.0:
        raise ConfigError("basestation.constraints.false_match_fraction: expected 0 <= f < 1")
    if cc.robust_kernel not in ("huber", "cauchy", "none"):
        raise ConfigError("basestation.constraints.robust_kernel: expected huber, cauchy or none")


def _validate_gps(cfg: Config) -> None:
    g = cfg.sim.gnss
    _positive_fields(
        "sim.gnss",
        g,
        ("rate_hz", "sigma_east_m", "sigma_north_m", "sigma_up_m", "sigma_correlation_s"),
    )
    _non_negative_fields(
        "sim.gnss",
        g,
        ("sigma_variation", "outage_rate_per_min", "outage_duration_s", "outlier_min_m"),
    )
    if not 0.0 <= g.outlier_fraction < 1.0:
        raise ConfigError("sim.gnss.outlier_fraction: expected 0 <= f < 1")
    if g.outlier_max_m < g.outlier_min_m:
        raise ConfigError("sim.gnss.outlier_max_m: expected >= outlier_min_m")
    if not -90.0 <= g.origin_lat_deg <= 90.0 or not -180.0 <= g.origin_lon_deg <= 180.0:
        raise ConfigError("sim.gnss.origin_lat_deg / origin_lon_deg: out of WGS84 range")
    p = cfg.basestation.gps
    if p.weighting == "affine":  # (a config of an earlier version: the same weights)
        log.warning("basestation.gps.weighting = 'affine' is 'inverse' now: a and b "
                    "apply to either weighting")  # fmt: skip
        p.weighting = "inverse"
    elif p.enabled and (p.a, p.b) != (1.0, 0.0):  # (an earlier version's config kept them)
        log.warning("basestation.gps.a = %g, b = %g weight the %s fixes (eq. 7: a / sigma "
                    "+ b); before the 70th session they applied to 'affine' only",
                    p.a, p.b, p.weighting)  # fmt: skip
    if p.weighting not in ("inverse", "isotropic"):
        raise ConfigError(
            f"basestation.gps.weighting: expected inverse or isotropic, got {p.weighting!r}"
        )
    if p.a < 0.0 or p.b < 0.0 or not (p.a > 0.0 or p.b > 0.0):
        raise ConfigError("basestation.gps.a / b: expected a, b >= 0, not both 0")
    _positive_fields(
        "basestation.gps",
        p,
        ("huber_k", "sigma_min_m", "start_sigma_xy_m", "start_sigma_yaw_rad", "max_pending_fixes"),
    )
    if p.batch_period_s < 0.0:
        raise ConfigError("basestation.gps.batch_period_s: expected a value >= 0")
