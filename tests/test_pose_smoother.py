"""The smoothed control pose (seed 000 §II, eq. 2) and the control-pose log."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from agent.control_log import ControlLog, read_control_log, write_control_log
from agent.pose_smoother import PoseSmoother, blend_alpha, pose7_compose, pose7_interpolate
from common.config import Config, load_config
from common.errors import ConfigError, FileFormatError
from common.geometry import pose4_compose, pose4_to_pose7, pose7_to_pose4, quat_to_yaw


def P(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    return pose4_to_pose7([x, y, z, yaw])


def assert_pose_close(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> None:
    np.testing.assert_allclose(a[:3], b[:3], atol=tol)
    dot = abs(float(np.dot(a[3:7], b[3:7])))  # q and -q are the same rotation
    assert dot == pytest.approx(1.0, abs=tol)


def test_alpha_follows_eq2(cfg: Config) -> None:
    s, t_x = cfg.agent.smoothing.s, cfg.agent.smoothing.t_x_s
    assert (s, t_x) == (1.5, 3.0)  # the paper's constants are the defaults
    assert blend_alpha(0.0, s, t_x) == pytest.approx(0.930, abs=0.002)
    assert blend_alpha(3.0, s, t_x) == pytest.approx(0.4, abs=1e-12)
    assert blend_alpha(7.0, s, t_x) < 0.03
    ts = np.linspace(0.0, 10.0, 101)
    a = np.array([blend_alpha(t, s, t_x) for t in ts])
    assert np.all(np.diff(a) < 0) and np.all((a > 0) & (a < 1))
    assert blend_alpha(1e6) == 0.0  # no overflow far out


def test_blend_endpoints_and_translation_is_linear(cfg: Config) -> None:
    old, new = P(0, 0, 1, 0.2), P(2.0, -1.0, 1.5, 0.2)
    sm = PoseSmoother(cfg.agent.smoothing, old)
    assert_pose_close(sm.applied(5.0), old)
    sm.on_correction(new, 10.0)
    assert sm.blending(10.0) and sm.target is not None
    for t in (0.0, 1.0, 3.0, 5.0, 6.9):
        a = blend_alpha(t)
        np.testing.assert_allclose(sm.applied(10.0 + t)[:3], a * old[:3] + (1 - a) * new[:3])
    assert sm.alpha(13.0) == pytest.approx(0.4)
    assert_pose_close(sm.applied(17.0), new)  # after duration_s: the new value in full
    assert not sm.blending(17.0) and sm.alpha(17.0) == 0.0
    assert_pose_close(sm.applied(100.0), new)


def test_first_correction_without_a_known_start_is_applied_at_once(cfg: Config) -> None:
    sm = PoseSmoother(cfg.agent.smoothing)
    assert_pose_close(sm.applied(0.0), P(0, 0, 0, 0))
    sm.on_correction(P(5, 5, 0, 1.0), 1.0)
    assert_pose_close(sm.applied(1.0), P(5, 5, 0, 1.0))
    assert not sm.blending(1.0)


def test_a_repeated_correction_does_not_restart_the_blend(cfg: Config) -> None:
    sm = PoseSmoother(cfg.agent.smoothing, P(0, 0, 0, 0))
    sm.on_correction(P(1.0, 0, 0, 0.1), 0.0)
    expected = sm.applied(3.0)
    sm.on_correction(P(1.0, 0, 0, 0.1), 2.0)  # the same value, next graph update
    assert sm.restarts == 0
    assert_pose_close(sm.applied(3.0), expected)
    sm.on_correction(P(1.0, 0.01, 0, 0.1), 3.0)  # it moved: a new blend
    assert sm.restarts == 1


def test_disabled_is_raw(cfg: Config) -> None:
    off = dataclasses.replace(cfg.agent.smoothing, enabled=False)
    sm = PoseSmoother(off, P(0, 0, 0, 0))
    sm.on_correction(P(1, 2, 0, 0.5), 3.0)
    assert_pose_close(sm.applied(3.0), P(1, 2, 0, 0.5))
    assert sm.alpha(3.0) == 0.0


def test_mid_blend_correction_starts_from_the_applied_value(cfg: Config) -> None:
    sm = PoseSmoother(cfg.agent.smoothing, P(0, 0, 0, 0))
    sm.on_correction(P(1.0, 0, 0, 0), 0.0)
    before = sm.applied(2.0)
    assert 0.05 < before[0] < 0.95  # mid-blend
    sm.on_correction(P(1.0, 2.0, 0, 0), 2.0)
    assert sm.restarts == 1
    after = sm.applied(2.0)
    # The new blend starts at `before`, not at either correction: the step is only
    # (1 - alpha(0)) of the remaining gap.
    gap = np.array([1.0, 2.0, 0.0]) - before[:3]
    np.testing.assert_allclose(after[:3] - before[:3], (1 - blend_alpha(0.0)) * gap, atol=1e-12)
    np.testing.assert_allclose(sm.applied(2.0 + 3.0)[:3], before[:3] + 0.6 * gap, atol=1e-12)
    assert_pose_close(sm.applied(9.0), P(1.0, 2.0, 0, 0))


def test_rotation_slerps_the_short_way_across_pi(cfg: Config) -> None:
    old, new = P(0, 0, 0, np.deg2rad(170.0)), P(0, 0, 0, np.deg2rad(-170.0))
    sm = PoseSmoother(cfg.agent.smoothing, old)
    sm.on_correction(new, 0.0)
    t_half = 3.0 - np.log(1.5)  # alpha = 0.5
    yaw_half = float(quat_to_yaw(sm.applied(t_half)[3:7]))
    assert abs(abs(yaw_half) - np.pi) < 1e-6
    stamps = np.arange(t_half, 8.0, 0.025)
    yaws = np.unwrap([float(quat_to_yaw(sm.applied(t)[3:7])) for t in stamps])
    # 20 deg the short way through 180, never the 340 deg way through 0.
    assert np.all(np.abs(yaws - np.pi) <= np.deg2rad(10.0) + 1e-9)
    steps = np.abs(np.diff(yaws))
    # |d alpha / dt| <= 0.25 / s per tick, and the final snap at 7 s is alpha(7) < 0.013.
    assert steps.max() <= 0.013 * np.deg2rad(20.0)
    u = 0.25  # pose7_interpolate agrees with the smoother's slerp
    mid = pose7_interpolate(old, new, u)
    assert float(quat_to_yaw(mid[3:7])) == pytest.approx(np.deg2rad(175.0))


def test_control_pose_composes_the_unfiltered_local_pose(cfg: Config) -> None:
    C = np.array([3.0, -1.0, 0.2, 0.7])
    sm = PoseSmoother(cfg.agent.smoothing, pose4_to_pose7(C))
    for L in ([0.0, 0.0, 1.0, 0.0], [1.5, 2.0, 1.1, -2.5], [-4.0, 0.3, 0.9, 3.0]):
        got = sm.pose(1.0, pose4_to_pose7(L))
        np.testing.assert_allclose(pose7_to_pose4(got), pose4_compose(C, L), atol=1e-12)
    q = pose7_compose(P(0, 0, 0, 0), P(1, 2, 3, 0.1))
    assert_pose_close(q, P(1, 2, 3, 0.1))


def test_step_per_tick_is_a_small_fraction_of_the_jump(cfg: Config) -> None:
    """The property `bench smoothing` measures: a 1 m, 10 deg jump seen at 40 Hz."""
    sm = PoseSmoother(cfg.agent.smoothing, P(0, 0, 0, 0))
    stamps = np.arange(0.0, 12.0, 0.025)
    applied = []
    for i, t in enumerate(stamps):
        if i == 40:
            sm.on_correction(P(1.0, 0, 0, np.deg2rad(10.0)), t)
        applied.append(sm.applied(t))
    steps = np.linalg.norm(np.diff(np.array(applied)[:, :3], axis=0), axis=1)
    assert steps.max() <= 0.071  # 1 - alpha(0) = 0.0698 of the jump, then smaller
    assert_pose_close(applied[-1], P(1.0, 0, 0, np.deg2rad(10.0)))


def test_quaternion_math_agrees_with_scipy() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        a, b = Rotation.random(2, random_state=rng).as_quat()
        ta, tb = rng.normal(size=3), rng.normal(size=3)
        u = float(rng.uniform())
        got = pose7_compose(np.r_[ta, a], np.r_[tb, b])
        ra = Rotation.from_quat(a)
        assert_pose_close(got, np.r_[ta + ra.apply(tb), (ra * Rotation.from_quat(b)).as_quat()])
        mid = pose7_interpolate(np.r_[ta, a], np.r_[tb, b], u)
        ref = Slerp([0.0, 1.0], Rotation.from_quat([a, b]))([u]).as_quat()[0]
        assert_pose_close(mid, np.r_[(1 - u) * ta + u * tb, ref])
    near = Rotation.from_rotvec([0.0, 0.0, 1e-5]).as_quat()  # nearly equal rotations
    mid = pose7_interpolate(np.r_[0, 0, 0, 0, 0, 0, 1.0], np.r_[0, 0, 0, near], 0.5)
    assert_pose_close(mid, np.r_[0, 0, 0, Rotation.from_rotvec([0, 0, 5e-6]).as_quat()])


def test_smoothing_config_is_validated() -> None:
    assert load_config(overrides={"agent.smoothing.enabled": False}).agent.smoothing.s == 1.5
    with pytest.raises(ConfigError, match="agent.smoothing.s"):
        load_config(overrides={"agent.smoothing.s": 0.0})
    with pytest.raises(ConfigError, match="agent.smoothing.duration_s"):
        load_config(overrides={"agent.smoothing.duration_s": -1.0})
    with pytest.raises(ConfigError, match="agent.smoothing.t_x_s"):
        load_config(overrides={"agent.smoothing.t_x_s": -0.5})


def test_control_log_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 5
    poses = [
        np.array([P(*rng.normal(size=3), rng.uniform(-3, 3)) for _ in range(n)]) for _ in range(3)
    ]
    log = ControlLog(np.arange(n) * 0.025, *poses)
    write_control_log(tmp_path / "c.csv", log)
    back = read_control_log(tmp_path / "c.csv")
    np.testing.assert_allclose(back.rows(), log.rows(), atol=1e-8)
    (tmp_path / "bad.csv").write_text("stamp,x\n1,2\n")
    with pytest.raises(FileFormatError, match="header"):
        read_control_log(tmp_path / "bad.csv")
    with pytest.raises(FileFormatError, match="not found"):
        read_control_log(tmp_path / "missing.csv")
