"""Seed 003 RTE (eq. 8), RRE (eq. 9) and drift percentage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.drift_metrics import drift_percent, relative_rotation_error, relative_translation_error
from common.errors import CollabSlamError
from common.trajectory_io import Trajectory


def straight_line(n: int = 51, length: float = 10.0, yaw_rate: float = 0.0) -> Trajectory:
    """A drone flying `length` m along +x at 2 m height, starting at the origin."""
    stamps = np.linspace(0.0, 5.0, n)
    x = np.linspace(0.0, length, n)
    pose4 = np.column_stack([x, np.zeros(n), np.full(n, 2.0), yaw_rate * stamps])
    return Trajectory.from_pose4(stamps, pose4)


def test_identical_trajectories_have_zero_error() -> None:
    gt = straight_line(yaw_rate=0.3)
    assert relative_translation_error(gt, gt).max == pytest.approx(0.0, abs=1e-12)
    assert relative_rotation_error(gt, gt).max == pytest.approx(0.0, abs=1e-7)
    assert drift_percent(gt, gt) == pytest.approx(0.0, abs=1e-12)


def test_constant_offset() -> None:
    gt = straight_line()
    est = Trajectory(gt.stamps, gt.positions + [0.3, -0.4, 0.0], gt.quats_xyzw)
    rte = relative_translation_error(est, gt)
    np.testing.assert_allclose(rte.values, 0.5)
    assert rte.mean == pytest.approx(0.5) and rte.rmse == pytest.approx(0.5)
    assert drift_percent(est, gt) == pytest.approx(0.5 / 10.0 * 100.0)
    # Aligning the first pose removes a constant offset entirely.
    assert relative_translation_error(est, gt, align_first=True).max == pytest.approx(0, abs=1e-12)


def test_constant_scale() -> None:
    gt = straight_line()
    est = Trajectory(gt.stamps, gt.positions * [1.02, 1.0, 1.0], gt.quats_xyzw)
    rte = relative_translation_error(est, gt)
    np.testing.assert_allclose(rte.values, 0.02 * gt.positions[:, 0], atol=1e-12)
    assert drift_percent(est, gt) == pytest.approx(2.0)


def test_rre_is_frobenius_norm_of_log() -> None:
    gt = straight_line(yaw_rate=0.2)
    err = 0.1  # rad, constant yaw error
    est = Trajectory.from_pose4(
        gt.stamps, np.column_stack([gt.positions, gt.poses_se2()[:, 2] + err])
    )
    rre = relative_rotation_error(est, gt)
    # logm of a rotation by a about z is [[0, -a, 0], [a, 0, 0], [0, 0, 0]]: norm sqrt(2) a.
    np.testing.assert_allclose(rre.values, math.sqrt(2.0) * err, rtol=1e-9)


def test_gt_is_interpolated_at_estimate_stamps() -> None:
    gt = straight_line(n=6)  # 1 s apart, 2 m apart
    stamps = np.array([0.5, 2.25, 4.9, 7.0])  # the last is outside gt's span: dropped
    est = Trajectory.from_pose4(
        stamps, np.column_stack([2 * stamps, 0 * stamps, 0 * stamps + 2, 0 * stamps])
    )
    rte = relative_translation_error(est, gt)
    np.testing.assert_array_equal(rte.stamps, stamps[:3])
    np.testing.assert_allclose(rte.values, 0.0, atol=1e-12)


def test_no_overlap_raises() -> None:
    gt = straight_line()
    est = Trajectory.from_pose4(gt.stamps + 100.0, np.zeros((len(gt), 4)))
    with pytest.raises(CollabSlamError, match="time span"):
        relative_translation_error(est, gt)
