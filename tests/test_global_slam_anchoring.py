"""Which robot defines `map` when no start pose is known."""

from __future__ import annotations

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation.global_slam import GlobalSlam
from common.config import Config

ZERO = np.zeros(3)


def _first_keyframes(cfg: Config, order: list[str]) -> GlobalSlam:
    slam = GlobalSlam(cfg)
    for rid in order:
        assert slam.admit(synthetic_keyframe(rid, 0, ZERO, ZERO)) == 1
    slam.optimize()
    return slam


def test_the_first_robot_to_send_defines_map_by_default() -> None:
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    slam = _first_keyframes(cfg, ["b", "a"])
    assert slam.graph.is_anchored("b") and not slam.graph.is_anchored("a")


def test_map_frame_robot_defines_map_even_when_it_sends_last() -> None:
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    cfg.basestation.map_frame_robot = "a"
    slam = _first_keyframes(cfg, ["b", "c", "a"])
    assert slam.graph.is_anchored("a")
    assert not slam.graph.is_anchored("b") and not slam.graph.is_anchored("c")
    np.testing.assert_allclose(slam.T_map_odom("a"), 0.0, atol=1e-9)


def test_converge_reaches_the_batch_optimum_after_a_loop_closure() -> None:
    """Between updates iSAM2 relinearizes only now and then: after a loop closure the
    estimate is a step toward the optimum; converge() finishes the way (batch LM's chi2)."""
    from basestation.batch_solver import batch_optimize

    cfg = Config()
    cfg.basestation.constraints.enabled = False
    slam = GlobalSlam(cfg)
    step = np.array([1.0, 0.0, np.pi / 10 + 0.02])  # a 20-gon, its heading drifting
    pose = ZERO.copy()
    for i in range(21):
        assert slam.admit(synthetic_keyframe("a", i, pose, pose)) == 1
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = pose + np.array([c * step[0], s * step[0], step[2]])
        slam.optimize()
    tight = np.diag([0.01**2, 0.01**2, 0.001**2])
    slam.graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), tight, robust=None)
    slam.optimize()
    before = slam.graph.chi2()
    slam.converge()
    best = batch_optimize(slam.graph, start="guess").chi2
    assert slam.graph.chi2() == pytest.approx(best, rel=1e-3)
    assert before > 1.01 * best  # one update had not got there
