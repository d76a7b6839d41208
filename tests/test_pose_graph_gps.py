"""PoseGraph with GPS fixes: waiting for bracketing nodes, georeferencing, Huber, batches."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.gps_factor import GpsWeighting
from basestation.pose_graph import PoseGraph
from common.errors import CollabSlamError
from common.geometry import se2_between, se2_compose

SIG = np.array([1.5, 1.5, 3.0])


def _truth(n: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A 0.2 m-step loop-free L-shaped path in ENU, one node per 0.2 s."""
    stamps = 0.2 * np.arange(n)
    poses = [np.array([100.0, -50.0, 0.3])]
    for k in range(1, n):
        turn = 0.02 if 80 <= k < 160 else 0.0
        poses.append(se2_compose(poses[-1], [0.2, 0.0, turn]))
    return stamps, np.array(poses)


def _graph(
    truth: np.ndarray, heading_error: float, weighting: GpsWeighting | None = None, **kw: float
) -> PoseGraph:
    g = PoseGraph(gps_weighting=weighting, factorization="QR", **kw)
    start = truth[0] + [4.0, -3.0, heading_error]  # first fix and a compass heading
    g.add_robot("r", start, (100.0, 100.0, 0.1))
    return g


def _feed(g: PoseGraph, stamps: np.ndarray, truth: np.ndarray, fixes: list) -> None:
    cov = np.diag([1e-4, 1e-4, 1e-5])
    nf = 0
    for k, t in enumerate(stamps):
        if k == 0:
            g.add_node("r", 0, None, None, stamp=float(t))
        else:
            g.add_node("r", k, se2_between(truth[k - 1], truth[k]), cov, stamp=float(t))
        while nf < len(fixes) and fixes[nf][0] <= t:
            g.add_gps_fix("r", *fixes[nf])
            nf += 1
        g.update()
    g.flush_gps()
    g.update(extra_iterations=5)


def _fixes(stamps: np.ndarray, truth: np.ndarray, rng: np.random.Generator, outliers: float = 0):
    out = []
    for t in np.arange(0.5, stamps[-1], 1.0):  # 1 Hz, between nodes
        xy = np.array([np.interp(t, stamps, truth[:, i]) for i in (0, 1)])
        xy += rng.normal(0.0, SIG[:2])
        if rng.random() < outliers:
            xy += [25.0, -20.0]
        out.append((float(t), xy, SIG))
    return out


def test_fix_waits_for_the_node_after_it() -> None:
    stamps, truth = _truth(5)
    g = _graph(truth, 0.0)
    g.add_node("r", 0, None, None, stamp=0.0)
    assert g.add_gps_fix("r", 0.1, truth[0, :2], SIG) == 0  # no node after 0.1 s yet
    assert g.gps_stats()["gps_pending"] == 1
    g.add_node("r", 1, [0.2, 0.0, 0.0], np.eye(3) * 1e-4, stamp=0.2)  # brackets it now
    assert g.gps_stats()["gps_factors"] == 1 and g.gps_stats()["gps_pending"] == 0
    assert g.add_gps_fix("r", -1.0, truth[0, :2], SIG) == 0  # older than the chain
    assert g.gps_stats()["gps_dropped_before_start"] == 1
    g.update()


def test_gps_georeferences_the_chain() -> None:
    stamps, truth = _truth()
    fixes = _fixes(stamps, truth, np.random.default_rng(0))
    g = _graph(truth, heading_error=0.08)
    _feed(g, stamps, truth, fixes)
    err = np.hypot(*(g.poses("r")[:, :2] - truth[:, :2]).T)
    assert g.gps_stats()["gps_factors"] == len(fixes)
    assert np.sqrt(np.mean(err**2)) < 0.6  # the start was 5 m and 0.08 rad off
    assert abs(g.poses("r")[0, 2] - truth[0, 2]) < 0.03
    # without GPS the loose start prior is all there is
    g0 = _graph(truth, heading_error=0.08)
    _feed(g0, stamps, truth, [])
    assert np.hypot(*(g0.poses("r")[0, :2] - truth[0, :2])) > 4.0


def test_huber_resists_multipath_outliers() -> None:
    stamps, truth = _truth()
    rng = np.random.default_rng(1)
    fixes = _fixes(stamps, truth, rng, outliers=0.15)
    ate = {}
    for k in (None, 1.345):
        g = _graph(truth, 0.0, GpsWeighting(huber_k=k))
        _feed(g, stamps, truth, fixes)
        ate[k] = float(np.sqrt(np.mean(np.sum((g.poses("r")[:, :2] - truth[:, :2]) ** 2, 1))))
    assert ate[1.345] < 0.7 * ate[None]


def test_batches_release_fixes_periodically() -> None:
    stamps, truth = _truth(60)
    g = _graph(truth, 0.0, gps_batch_period_s=5.0)
    g.add_node("r", 0, None, None, stamp=0.0)
    released, total = [], 0
    for k in range(1, 60):
        g.add_node("r", k, se2_between(truth[k - 1], truth[k]), np.eye(3) * 1e-4, stamp=stamps[k])
        g.add_gps_fix("r", stamps[k] - 0.1, truth[k, :2], SIG)
        released.append(g.gps_stats()["gps_factors"] - total)
        total += released[-1]
    counts = [c for c in released if c]
    # doubling while few fixes are in, then one batch per 5 s of nodes (fixes at 5 Hz)
    assert counts == [1, 1, 2, 4, 8, 16, 24]
    assert g.gps_stats()["gps_pending"] > 0
    g.flush_gps()
    assert g.gps_stats()["gps_pending"] == 0 and g.gps_stats()["gps_factors"] == 59
    g.update()


def test_unstamped_chains_cannot_take_gps() -> None:
    g = PoseGraph()
    g.add_robot("r", [0.0, 0.0, 0.0])
    g.add_node("r", 0, None, None)
    with pytest.raises(CollabSlamError, match="unstamped"):
        g.add_gps_fix("r", 1.0, [0.0, 0.0], SIG)
    g2 = PoseGraph()
    g2.add_robot("r", [0.0, 0.0, 0.0])
    g2.add_node("r", 0, None, None, stamp=1.0)
    with pytest.raises(CollabSlamError, match="increase"):
        g2.add_node("r", 1, [0.1, 0, 0], np.eye(3), stamp=1.0)
    with pytest.raises(CollabSlamError, match="start_sigmas"):
        PoseGraph().add_robot("x", None, (1.0, 1.0, 0.1))
