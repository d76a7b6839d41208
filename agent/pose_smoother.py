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
from scipy.spatial.transform import Rotation, Slerp

from common.config import SmoothingConfig

FloatArray = np.ndarray
SAME_M = 1e-6  # m: corrections closer than this (and SAME_RAD) are the same value
SAME_RAD = 1e-6  # rad


def blend_alpha(t: float, s: float = 1.5, t_x: float = 3.0) -> float:
    """Eq. 2: the weight of the OLD correction `t` seconds after a new one arrived
    (about 0.93 at t = 0, 0.4 at t = t_x, 0.012 at t = 7 s with the defaults)."""
    z = float(t) - t_x
    if z > 700.0:  # exp overflows; alpha is 0 to double precision
        return 0.0
    return 1.0 / (1.0 + s * math.exp(z))


def pose7_compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> FloatArray:
    """T_a_c = T_a_b · T_b_c for pose7 arrays (3-D rigid transforms)."""
    a = np.asarray(T_a_b, dtype=np.float64)
    b = np.asarray(T_b_c, dtype=np.float64)
    r_a = Rotation.from_quat(a[3:7])
    t = a[:3] + r_a.apply(b[:3])
    q = (r_a * Rotation.from_quat(b[3:7])).as_quat()
    return np.concatenate([t, _canonical(q)])


def pose7_interpolate(T_0: ArrayLike, T_1: ArrayLike, u: float) -> FloatArray:
    """The pose a fraction `u` in [0, 1] of the way from T_0 to T_1: translation
    linearly, rotation by slerp along the shorter arc."""
    p0 = np.asarray(T_0, dtype=np.float64)
    p1 = np.asarray(T_1, dtype=np.float64)
    slerp = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([p0[3:7], p1[3:7]])))
    return _blend(p0, p1, slerp, u)


def _blend(p0: FloatArray, p1: FloatArray, slerp: Slerp, u: float) -> FloatArray:
    u = min(max(float(u), 0.0), 1.0)
    q = slerp([u]).as_quat()[0]
    return np.concatenate([(1.0 - u) * p0[:3] + u * p1[:3], _canonical(q)])


def _canonical(q: FloatArray) -> FloatArray:
    """Unit quaternion with qw >= 0 (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


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
        self._slerp: Slerp | None = None
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
            self._target, self._old, self._slerp = new, None, None
            return
        if _same(new, self._target):
            return
        if self.blending(stamp):
            self.restarts += 1
        start = self.applied(stamp)
        self._old, self._target, self._t0 = start, new, float(stamp)
        self._slerp = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([start[3:7], new[3:7]])))

    def applied(self, stamp: float) -> FloatArray:
        """T_map_odom (pose7) applied to the control pose at sensor time `stamp` (s);
        the identity before any correction is known."""
        if self._target is None:
            return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        if self._old is None or self._slerp is None:
            return self._target.copy()
        if not self.blending(stamp):
            self._old = self._slerp = None  # settled: the new value in full
            return self._target.copy()
        return _blend(self._old, self._target, self._slerp, 1.0 - self.alpha(stamp))

    def pose(self, stamp: float, T_odom_base: ArrayLike) -> FloatArray:
        """The control pose T_map_base (pose7) = applied T_map_odom · T_odom_base (unfiltered)."""
        return pose7_compose(self.applied(stamp), T_odom_base)


def _same(a: FloatArray, b: FloatArray) -> bool:
    """Equal within SAME_M / SAME_RAD (numerical noise of the optimizer)."""
    angle = 2.0 * math.acos(min(1.0, abs(float(np.dot(a[3:7], b[3:7])))))
    return bool(np.linalg.norm(a[:3] - b[:3]) < SAME_M and angle < SAME_RAD)


def _pose7(p: ArrayLike) -> FloatArray:
    a = np.asarray(p, dtype=np.float64).reshape(7)
    return np.concatenate([a[:3], _canonical(a[3:7])])
