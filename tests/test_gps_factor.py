"""GPS factor (seed 000 eq. 3) and weights (eq. 5-7): residual, Jacobians, weights."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from basestation.gps_factor import (
    GpsWeighting,
    gps_noise,
    gps_residual,
    gps_weights,
    interpolation_factor,
    make_gps_factor,
)
from basestation.gps_fixes import GpsFix, GpsFixQueue
from common.errors import CollabSlamError

KI, KJ = gtsam.symbol("a", 3), gtsam.symbol("a", 4)


def _values(pi: tuple[float, float, float], pj: tuple[float, float, float]) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(KI, gtsam.Pose2(*pi))
    v.insert(KJ, gtsam.Pose2(*pj))
    return v


def _unit_noise() -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Unit.Create(2)


def test_residual_is_zero_on_a_straight_line_through_the_fix() -> None:
    # Straight line at constant speed: p(t) = p0 + v t; nodes at t = 2 and 3.5 s.
    p0, v = np.array([10.0, -4.0]), np.array([1.2, 0.7])
    ti, tj, tk = 2.0, 3.5, 2.9
    pi, pj = p0 + v * ti, p0 + v * tj
    yaw = float(np.arctan2(v[1], v[0]))
    beta = interpolation_factor(ti, tj, tk)
    fix = p0 + v * tk
    factor = make_gps_factor(KI, KJ, beta, fix, _unit_noise())
    values = _values((*pi, yaw), (*pj, yaw))
    np.testing.assert_allclose(factor.unwhitenedError(values), 0.0, atol=1e-12)
    assert factor.error(values) == pytest.approx(0.0, abs=1e-20)
    # and off the line the residual is the offset
    off = make_gps_factor(KI, KJ, beta, fix + [0.3, -0.2], _unit_noise())
    np.testing.assert_allclose(off.unwhitenedError(values), [-0.3, 0.2], atol=1e-12)


def test_residual_with_lever_arm_matches_numpy_reference() -> None:
    arm = (0.3, -0.1)
    pi, pj = (1.0, 2.0, 0.4), (1.5, 2.2, 0.9)
    factor = make_gps_factor(KI, KJ, 0.25, [1.0, 2.0], _unit_noise(), arm)
    expected = gps_residual(pi, pj, 0.25, [1.0, 2.0], arm)
    np.testing.assert_allclose(factor.unwhitenedError(_values(pi, pj)), expected, atol=1e-12)


@pytest.mark.parametrize("arm", [(0.0, 0.0), (0.3, -0.15)])
@pytest.mark.parametrize("beta", [0.0, 0.37, 1.0])
def test_jacobians_match_numerical_differentiation(arm: tuple[float, float], beta: float) -> None:
    pi, pj = gtsam.Pose2(3.0, -1.0, 0.8), gtsam.Pose2(3.4, -0.7, 1.1)
    factor = make_gps_factor(KI, KJ, beta, [3.1, -0.8], _unit_noise(), arm)
    values = _values((pi.x(), pi.y(), pi.theta()), (pj.x(), pj.y(), pj.theta()))
    linear = factor.linearize(values)  # whitened with unit noise: A = d(residual)/d(xi)
    A, _ = linear.jacobian()
    eps = 1e-6
    numeric = np.zeros((2, 6))
    for col, (key, pose) in enumerate([(KI, pi), (KJ, pj)]):
        for d in range(3):
            xi = np.zeros(3)
            xi[d] = eps
            plus, minus = gtsam.Values(values), gtsam.Values(values)
            plus.update(key, pose.retract(xi))
            minus.update(key, pose.retract(-xi))
            diff = factor.unwhitenedError(plus) - factor.unwhitenedError(minus)
            numeric[:, 3 * col + d] = diff / (2 * eps)
    np.testing.assert_allclose(A, numeric, atol=1e-7)


def test_weights_match_equations_5_6_7() -> None:
    sig = np.array([0.8, 1.6, 3.2])
    np.testing.assert_allclose(gps_weights(sig, GpsWeighting("inverse")), 1 / sig)  # eq. 5
    np.testing.assert_allclose(gps_weights(sig, GpsWeighting("isotropic")), [1 / 3.2] * 3)
    eq7 = GpsWeighting("inverse", a=2.0, b=0.5)  # eq. 7: a diag(sigma)^-1 + b I
    np.testing.assert_allclose(gps_weights(sig, eq7), [2 / 0.8 + 0.5, 2 / 1.6 + 0.5, 2 / 3.2 + 0.5])
    # eq. 6 with eq. 7: a and b apply to the worst sigma (they had done nothing here)
    eq67 = GpsWeighting("isotropic", a=2.0, b=0.5)
    np.testing.assert_allclose(gps_weights(sig, eq67), [2 / 3.2 + 0.5] * 3)
    floor = GpsWeighting("inverse", sigma_min_m=1.0)
    np.testing.assert_allclose(gps_weights(sig, floor), [1.0, 1 / 1.6, 1 / 3.2])


def test_noise_model_whitens_with_the_weights() -> None:
    sig = np.array([0.8, 1.6, 3.2])
    for weighting in (GpsWeighting("inverse", huber_k=None), GpsWeighting("inverse", 2, 0.5, None)):
        noise = gps_noise(sig, weighting)
        r = np.array([0.5, -0.25])
        np.testing.assert_allclose(noise.whiten(r), gps_weights(sig, weighting)[:2] * r)
    robust = gps_noise(sig, GpsWeighting("inverse", huber_k=1.345))
    assert isinstance(robust, gtsam.noiseModel.Robust)


def test_huber_bounds_the_cost_of_an_outlier() -> None:
    values = _values((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    sig = [1.5, 1.5, 3.0]
    far = [0.5, 30.0]  # a 30 m multipath jump
    plain = make_gps_factor(KI, KJ, 0.5, far, gps_noise(sig, GpsWeighting(huber_k=None)))
    huber = make_gps_factor(KI, KJ, 0.5, far, gps_noise(sig, GpsWeighting(huber_k=1.345)))
    assert huber.error(values) < 0.2 * plain.error(values)


def test_bad_inputs_raise() -> None:
    with pytest.raises(CollabSlamError):
        GpsWeighting("median")
    with pytest.raises(CollabSlamError):
        GpsWeighting("inverse", a=0.0, b=0.0)
    with pytest.raises(CollabSlamError):
        gps_weights([1.0, 0.0, 1.0], GpsWeighting())
    with pytest.raises(CollabSlamError):
        interpolation_factor(1.0, 2.0, 2.5)
    with pytest.raises(CollabSlamError):
        make_gps_factor(KI, KI, 0.5, [0, 0], _unit_noise())


def _fix(t: float) -> GpsFix:
    return GpsFix(t, np.zeros(2), np.ones(3))


def test_fix_queue_waits_for_bracketing_nodes() -> None:
    q = GpsFixQueue(max_pending=3)
    q.add("r", _fix(0.5))  # before the first node: dropped once nodes exist
    q.add("r", _fix(1.25))
    q.add("r", _fix(2.0))
    assert q.ready("r", [1.0]) == []  # one node brackets nothing
    assert q.dropped_before_start == 1
    ready = q.ready("r", [1.0, 1.5])
    assert [(b.i, b.j, b.beta) for b in ready] == [(0, 1, 0.5)]
    assert q.pending("r") == 1
    ready = q.ready("r", [1.0, 1.5, 2.0])  # exactly on a node: beta = 1 on the earlier pair
    assert [(b.i, b.j, b.beta) for b in ready] == [(1, 2, 1.0)]
    for t in (3.0, 4.0, 5.0, 6.0):
        q.add("r", _fix(t))
    assert q.pending("r") == 3 and q.dropped_overflow == 1


def test_fix_queue_names_drops_without_a_line_per_fix(caplog) -> None:  # noqa: ANN001
    """A hovering drone adds no nodes: its 10 Hz fixes overflowed the queue with one
    warning per fix (2,000 in 300 s). Fixes all before the chain's first node (another
    clock) had been dropped without a word."""
    q = GpsFixQueue(max_pending=10)
    for k in range(2010):
        q.add("r", _fix(1000.0 + 0.1 * k))
    assert q.dropped_overflow == 2000
    assert 3 <= caplog.text.count("too many GPS fixes wait") <= 6
    q.add("s", _fix(0.5))
    assert q.ready("s", [100.0, 101.0]) == [] and q.dropped_before_start == 1
    assert "before its first keyframe" in caplog.text and "another clock" in caplog.text
