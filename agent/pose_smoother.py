"""Smoothed pose output for control (seed 000 §II).

The control pose is `T_map_base = T_map_odom · T_odom_base`. The local part
`T_odom_base` is smooth and is never filtered; the correction `T_map_odom`
jumps whenever the base station closes a loop. Instead of applying a new
correction at once, it is blended in over `duration_s` (about 7 s) with the
weight of the old correction given by eq. 2,

    alpha(t) = 1 / (1 + s * exp(t - t_x)),   s = 1.5, t_x = 3 s,

translation linearly (`alpha * p_old + (1 - alpha) * p_new`) and rotation by
quaternion slerp. A correction that arrives mid-blend starts from the value
applied at that moment. After `duration_s` the new correction is applied in full.
A correction equal to the current one (the base station re-sends T_map_odom after
every graph update, most of which do not move it) changes nothing: only an
optimization that moves T_map_odom starts a blend.

Time `t` is the agent's sensor clock (scan stamps, s), counted from the stamp
passed to `on_correction`. Poses are pose7 `[x, y, z, qx, qy, qz, qw]`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from common.config import SmoothingConfig

FloatArray = np.ndarray
SAME_M = 1e-6  # m: corrections closer than this (and SAME_RAD) are the same value
SAME_RAD = 1e-6  # rad
IDENTITY7 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def blend_alpha(t: float, s: float = 1.5, t_x: float = 3.0) -> float:
    """Eq. 2: the weight of the OLD correction `t` seconds after a new one arrived
    (about 0.93 at t = 0, 0.4 at t = t_x, 0.012 at t = 7 s with the defaults)."""
    z = float(t) - t_x
    if z > 700.0:  # exp overflows; alpha is 0 to double precision
        return 0.0
    return 1.0 / (1.0 + s * math.exp(z))


# Quaternions [qx, qy, qz, qw] in plain floats: this runs every control tick, and
# scipy's Rotation costs ~50 us per single-pose call (tests check against it).


def _qmul(a: list[float], b: list[float]) -> list[float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]


def _qrotate(q: list[float], v: list[float]) -> list[float]:
    """v rotated by the unit quaternion q: v + w t + u x t with t = 2 u x v."""
    ux, uy, uz, w = q
    vx, vy, vz = v
    tx, ty, tz = 2.0 * (uy * vz - uz * vy), 2.0 * (uz * vx - ux * vz), 2.0 * (ux * vy - uy * vx)
    return [
        vx + w * tx + uy * tz - uz * ty,
        vy + w * ty + uz * tx - ux * tz,
        vz + w * tz + ux * ty - uy * tx,
    ]


def _qslerp(q0: list[float], q1: list[float], u: float) -> list[float]:
    """Slerp from q0 (u = 0) to q1 (u = 1) along the shorter arc."""
    d = sum(a * b for a, b in zip(q0, q1, strict=True))
    if d < 0.0:  # q1 and -q1 are the same rotation: take the shorter way
        q1, d = [-c for c in q1], -d
    if d > 0.9999995:  # under 1e-3 rad apart: normalized lerp is within 1e-10 of slerp
        w0, w1 = 1.0 - u, u
    else:
        theta = math.acos(d)
        w0 = math.sin((1.0 - u) * theta) / math.sin(theta)
        w1 = math.sin(u * theta) / math.sin(theta)
    return [w0 * a + w1 * b for a, b in zip(q0, q1, strict=True)]


def _pose(t: list[float], q: list[float]) -> FloatArray:
    """pose7 with a unit quaternion, qw >= 0 (q and -q are the same rotation)."""
    n = math.sqrt(sum(c * c for c in q))
    sign = -1.0 if q[3] < 0.0 else 1.0
    return np.array([*t, *(sign * c / n for c in q)], dtype=np.float64)


def pose7_compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> FloatArray:
    """T_a_c = T_a_b · T_b_c for pose7 arrays (3-D rigid transforms)."""
    a = np.asarray(T_a_b, dtype=np.float64).tolist()
    b = np.asarray(T_b_c, dtype=np.float64).tolist()
    r = _qrotate(a[3:7], b[:3])
    return _pose([a[0] + r[0], a[1] + r[1], a[2] + r[2]], _qmul(a[3:7], b[3:7]))


def pose7_interpolate(T_0: ArrayLike, T_1: ArrayLike, u: float) -> FloatArray:
    """The pose a fraction `u` in [0, 1] of the way from T_0 to T_1: translation
    linearly, rotation by quaternion slerp along the shorter arc."""
    p0 = np.asarray(T_0, dtype=np.float64).tolist()
    p1 = np.asarray(T_1, dtype=np.float64).tolist()
    u = min(max(float(u), 0.0), 1.0)
    t = [(1.0 - u) * a + u * b for a, b in zip(p0[:3], p1[:3], strict=True)]
    return _pose(t, _qslerp(p0[3:7], p1[3:7], u))


class PoseSmoother:
    """Blends corrections T_map_odom in over time; call from one thread only.

    `T_map_odom`: the correction known at start (pose7), or None when the
    robot's place on the map is unknown: then the first correction is applied
    at once (there is nothing to blend from).
    """

    def __init__(self, cfg: SmoothingConfig, T_map_odom: ArrayLike | None = None) -> None:
        self.cfg = cfg
        self._target: FloatArray | None = None if T_map_odom is None else _pose7(T_map_odom)
        self._old: FloatArray | None = None  # applied value when the blend started
        self._t0 = 0.0  # s, sensor time the blend started
        self.corrections = 0  # corrections received
        self.restarts = 0  # corrections that arrived while a blend was running

    @property
    def target(self) -> FloatArray | None:
        """The latest (raw) correction, or None before the first one."""
        return None if self._target is None else self._target.copy()

    def blending(self, stamp: float) -> bool:
        """True while a blend runs at sensor time `stamp` (s)."""
        return self._old is not None and stamp - self._t0 < self.cfg.duration_s

    def alpha(self, stamp: float) -> float:
        """Weight of the old correction at sensor time `stamp` (0 when settled)."""
        if not self.blending(stamp):
            return 0.0
        return blend_alpha(max(stamp - self._t0, 0.0), self.cfg.s, self.cfg.t_x_s)

    def on_correction(self, T_map_odom: ArrayLike, stamp: float) -> None:
        """A new correction (pose7) arrived at sensor time `stamp` (s)."""
        new = _pose7(T_map_odom)
        self.corrections += 1
        if self._target is None or not self.cfg.enabled:
            self._target, self._old = new, None
            return
        if _same(new, self._target):
            return
        if self.blending(stamp):
            self.restarts += 1
        self._old, self._target, self._t0 = self.applied(stamp), new, float(stamp)

    def applied(self, stamp: float) -> FloatArray:
        """T_map_odom (pose7) applied to the control pose at sensor time `stamp` (s);
        the identity before any correction is known."""
        if self._target is None:
            return np.array(IDENTITY7)
        if self._old is None:
            return self._target.copy()
        if not self.blending(stamp):
            self._old = None  # settled: the new value in full
            return self._target.copy()
        return pose7_interpolate(self._old, self._target, 1.0 - self.alpha(stamp))

    def pose(self, stamp: float, T_odom_base: ArrayLike) -> FloatArray:
        """The control pose T_map_base (pose7) = applied T_map_odom · T_odom_base (unfiltered)."""
        return pose7_compose(self.applied(stamp), T_odom_base)


def _same(a: FloatArray, b: FloatArray) -> bool:
    """Equal within SAME_M / SAME_RAD (numerical noise of the optimizer)."""
    angle = 2.0 * math.acos(min(1.0, abs(float(np.dot(a[3:7], b[3:7])))))
    return bool(np.linalg.norm(a[:3] - b[:3]) < SAME_M and angle < SAME_RAD)


def _pose7(p: ArrayLike) -> FloatArray:
    a = np.asarray(p, dtype=np.float64).reshape(7).tolist()
    return _pose(a[:3], a[3:7])
