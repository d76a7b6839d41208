"""Config: shipped defaults, TOML round trip, errors naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.config import Config, dump_config, load_config
from common.errors import ConfigError


def test_defaults_are_the_papers() -> None:
    c = load_config()
    assert c.sim.laser.beams == 1081 and c.sim.laser.fov_deg == 270.0
    assert c.sim.laser.rate_hz == 40.0 and c.sim.laser.range_max_m == 30.0
    assert c.agent.keyframe_distance_m == 0.2 and c.agent.keyframe_angle_rad == 0.1
    assert c.agent.local_keyframe_period_s == 0.25


def test_round_trip(tmp_path: Path) -> None:
    c = load_config(overrides={"sim.seed": 7, "zenoh.connect": ["tcp/127.0.0.1:1"]})
    dump_config(c, tmp_path / "c.toml")
    assert load_config(tmp_path / "c.toml") == c
    assert isinstance(c, Config)


@pytest.mark.parametrize(
    "overrides, key",
    [
        ({"sim.laser.beamz": 3}, "sim.laser.beamz"),
        ({"sim.laser.beams": -1}, "sim.laser.beams"),
        ({"sim.laser.beams": "many"}, "sim.laser.beams"),
        ({"sim.clock": "fast"}, "sim.clock"),
        ({"map.p_hit": 1.5}, "map.p_hit"),
        ({"fleet": "a/b"}, "fleet"),
        ({"zenoh.listen": "tcp/x"}, "zenoh.listen"),
        ({"zenoh.connect": ["tcp/127.0.0.1"]}, "zenoh.connect"),  # had been taken silently
        ({"zenoh.connect": ["tcp/127.0.0.1:99999"]}, "zenoh.connect"),
        ({"zenoh.connect": ["127.0.0.1:7447"]}, "zenoh.connect"),
        ({"agent.outbox_max": 1.5}, "agent.outbox_max"),
        ({"basestation.isam2_factorization": "LU"}, "basestation.isam2_factorization"),
        ({"basestation.adaptive_reorder_threshold": 0.5}, "basestation.adaptive_reorder"),
        ({"basestation.relinearize_skip": 0}, "basestation.relinearize_skip"),
        ({"sim.sync_wait_s": 0.0}, "sim.sync_wait_s"),
        ({"basestation.malloc_arenas": -1}, "basestation.malloc_arenas"),
        ({"basestation.malloc_mmap_threshold_kb": -1}, "basestation.malloc_mmap_threshold_kb"),
        ({"agent.malloc_arenas": -2}, "agent.malloc_arenas"),
        ({"agent.max_off_nose_deg": 200.0}, "agent.full_speed_off_nose_deg"),
        ({"agent.odom_sigma_min": 5e-6}, "agent.odom_sigma_min"),  # every keyframe refused
        ({"agent.local_slam.max_match_yaw_jump_deg": -1.0}, "agent.local_slam.max_match_yaw"),
        ({"agent.resend_batch": 0}, "agent.resend_batch"),
        ({"agent.safety_margin_m": 0.3}, "agent.vehicle_radius_m + agent.safety_margin_m"),
        # taken, these had stopped the base station at its first map update
        ({"map.occupied_thresh": 0.45}, "map.free_thresh / occupied_thresh"),
        ({"map.free_thresh": 0.7}, "map.free_thresh / occupied_thresh"),
        ({"map.p_min": 0.45}, "map.p_min / p_miss / p_hit / p_max"),
        ({"map.p_max": 0.6}, "map.p_min / p_miss / p_hit / p_max"),
        # a score or overlap above 1 had turned every loop closure off without a word
        ({"basestation.constraints.min_score": 1.5}, "basestation.constraints.min_score"),
        ({"basestation.constraints.min_overlap": 1.2}, "basestation.constraints.min_overlap"),
        ({"basestation.constraints.global_min_score": 2}, "basestation.constraints.global_min"),
        # taken, these had quietly wrecked a mission (the 71st session's config review):
        # no frontier on a 0.15 m map, every whole-map search raising, a control pose
        # jumping by most of a correction, every tilted scan's points taken for the
        # floor, the neighbour guard blind, drones started in contact
        ({"map.resolution_m": 0.15}, "map.resolution_m"),
        ({"basestation.constraints.global_candidates": 0}, "constraints.global_candidates"),
        ({"agent.smoothing.t_x_s": 10.0}, "agent.smoothing.s / t_x_s / duration_s"),
        ({"agent.smoothing.duration_s": 2.0}, "agent.smoothing.s / t_x_s / duration_s"),
        ({"agent.cruise_altitude_m": 0.15}, "agent.cruise_altitude_m"),
        ({"agent.state_period_s": 1.0}, "agent.neighbour_max_age_s"),
        ({"sim.start_spacing_m": 0.3}, "sim.start_spacing_m"),
        # exploration with unknown starts: a drone waiting for its first path never moved
        ({"basestation.known_start_poses": False}, "basestation.known_start_poses"),
    ],  # (global_min_score 1.0 turns the whole-map search off, and 0 takes anything: taken)
)
def test_bad_values_name_the_key(overrides: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.").replace("+", r"\+")):
        load_config(overrides=overrides)


def test_bad_toml(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text("[sim\nseed = 1")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(p)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_no_number_takes_a_negative_unless_signed() -> None:
    """Every numeric key refuses -1 (naming it) except biases, offsets and coordinates,
    and every integer key 2**70."""
    from common.config_validation import SIGNED_KEYS, numeric_keys

    keys = dict(numeric_keys(Config()))
    assert len(keys) > 150 and SIGNED_KEYS <= set(keys)
    for key, value in keys.items():
        bad = {key: type(value)(-1)}
        if key in SIGNED_KEYS:
            assert dict(numeric_keys(load_config(overrides=bad)))[key] == -1
            continue
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            load_config(overrides=bad)
    for key, value in keys.items():  # C ints: 2**70 had ended in a TypeError in GTSAM
        if isinstance(value, int):
            with pytest.raises(ConfigError, match=key.replace(".", r"\.") + ": expected at most"):
                load_config(overrides={key: 2**70})


def test_a_config_written_by_an_earlier_version_is_taken(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A run's config.toml (copied to /etc/collabslam as operations.md says) lists every
    key of its version: one retired since (it did nothing) had every unit refuse to
    start. It is ignored with a warning; a key that never was stays an error."""
    path = tmp_path / "old.toml"
    dump_config(Config(), path)
    text = path.read_text().replace(
        "[agent.local_slam]\n", "[agent.local_slam]\nmatch_sigma_per_m = 0.005\n"
    )
    path.write_text(text)
    with caplog.at_level("WARNING"):
        assert load_config(path) == Config()
    assert "agent.local_slam.match_sigma_per_m is no longer used" in caplog.text
    # a retired value: the GPS weighting `affine` is `inverse` (a, b apply to either)
    with caplog.at_level("WARNING"):
        old_gps = load_config(overrides={"basestation.gps.weighting": "affine"})
    assert old_gps.basestation.gps.weighting == "inverse" and "'affine' is 'inverse'" in caplog.text
    with caplog.at_level("WARNING"):  # a, b kept with another weighting: they count now
        gps = {"basestation.gps.enabled": True, "basestation.gps.weighting": "isotropic"}
        load_config(overrides={**gps, "basestation.gps.a": 2.0})
    assert "a = 2, b = 0 weight the isotropic fixes" in caplog.text
    path.write_text(text.replace("match_sigma_per_m", "match_sigma_typo"))
    with pytest.raises(ConfigError, match="unknown config key agent.local_slam.match_sigma_typo"):
        load_config(path)
