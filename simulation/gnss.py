"""Simulated GNSS receiver: WGS84 fixes of a vehicle flying in a world's ENU frame.

The world's ``map`` frame is an ENU frame at the world's WGS84 origin (see
``world_origin``). Each fix (every 1 / ``rate_hz`` s of sim time) reports
latitude, longitude, altitude and per-axis sigmas [east, north, up] (seed 000
eq. 4). Its true error is

    bias + [0, 0, vertical_drift * t] + N(0, diag(sigma_reported)^2) (+ multipath jump)

- reported sigmas: the nominal ones times a log-normal factor per axis whose log
  follows an AR(1) with correlation time ``sigma_correlation_s`` (quality changes
  slowly, and the noise really has the reported sigma);
- outages: Poisson starts (``outage_rate_per_min``), ``outage_duration_s`` each,
  no fix at all meanwhile;
- multipath outliers: with probability ``outlier_fraction`` a fix jumps
  horizontally by ``U(outlier_min_m, outlier_max_m)`` in a random direction while
  still reporting its normal sigmas (what makes it harmful).

Seeded: the same config, origin, seed and trajectory give the same fixes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.config_sim import GnssConfig
from common.errors import CollabSlamError
from common.geodesy import GeoOrigin, enu_to_geodetic, geodetic_to_enu

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GnssFix:
    """One receiver fix (what a real driver reports, plus simulation truth flags)."""

    stamp: float  # s, sim clock
    lla: FloatArray  # (3,) lat deg, lon deg, alt m above the WGS84 ellipsoid
    sigmas_enu: FloatArray  # (3,) reported 1-sigma east, north, up (m)
    outlier: bool = False  # simulation truth: a multipath jump (never used by the estimator)

    def enu(self, origin: GeoOrigin) -> FloatArray:
        """(3,) [east, north, up] of the fix in ``origin``'s ENU frame."""
        return geodetic_to_enu(self.lla, origin)


def world_origin(world_origin_or_none: GeoOrigin | None, cfg: GnssConfig) -> GeoOrigin:
    """The world's WGS84 origin, or the configured default for worlds without one."""
    if world_origin_or_none is not None:
        return world_origin_or_none
    return GeoOrigin(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_alt_m)


class GnssModel:
    """Produces fixes from ground-truth ENU positions; call ``measure`` every tick."""

    def __init__(self, cfg: GnssConfig, origin: GeoOrigin, seed: int = 0) -> None:
        self._cfg = cfg
        self._origin = origin
        self._rng = np.random.default_rng(seed)
        self._nominal = np.array([cfg.sigma_east_m, cfg.sigma_north_m, cfg.sigma_up_m])
        self._bias = np.array([cfg.bias_east_m, cfg.bias_north_m, cfg.bias_up_m])
        self._period = 1.0 / cfg.rate_hz
        self._next_fix: float | None = None  # sim time of the next fix
        self._t_first: float | None = None
        self._log_factor = np.zeros(3)
        self._outage_until = -math.inf
        self.outages = 0  # outages started so far
        self.fixes = 0  # fixes produced so far
        self.outliers = 0  # of which multipath jumps

    @property
    def origin(self) -> GeoOrigin:
        return self._origin

    def measure(self, t: float, true_enu: ArrayLike) -> GnssFix | None:
        """A fix if one is due at sim time ``t`` (s), else None; ``true_enu`` is the
        antenna's true [east, north, up] (m) in the world's ENU frame."""
        if self._next_fix is None:
            self._next_fix, self._t_first = t, t
        if t + 1e-9 < self._next_fix:
            return None
        self._next_fix += self._period * max(1, math.floor((t - self._next_fix) / self._period) + 1)
        return self._fix(t, np.asarray(true_enu, dtype=np.float64).reshape(3))

    def _fix(self, t: float, true_enu: FloatArray) -> GnssFix | None:
        c, rng = self._cfg, self._rng
        # quality (reported sigma) evolves whether or not there is a fix
        rho = math.exp(-self._period / c.sigma_correlation_s)
        self._log_factor = rho * self._log_factor + math.sqrt(1 - rho * rho) * (
            c.sigma_variation * rng.standard_normal(3)
        )
        if t < self._outage_until:
            return None
        p_start = c.outage_rate_per_min / 60.0 * self._period
        if c.outage_duration_s > 0 and rng.random() < p_start:
            self._outage_until = t + c.outage_duration_s
            self.outages += 1
            return None
        sigmas = self._nominal * np.exp(self._log_factor)
        error = self._bias + sigmas * rng.standard_normal(3)
        error[2] += c.vertical_drift_mps * (t - (self._t_first or 0.0))
        # always drawn, so that fixes differ only by their jumps across outlier fractions
        u, angle = rng.random(), rng.uniform(-math.pi, math.pi)
        size = rng.uniform(c.outlier_min_m, c.outlier_max_m)
        outlier = bool(u < c.outlier_fraction)
        if outlier:
            error[:2] += size * np.array([math.cos(angle), math.sin(angle)])
            self.outliers += 1
        self.fixes += 1
        lla = enu_to_geodetic(true_enu + error, self._origin)
        return GnssFix(float(t), lla, sigmas, outlier)


def simulate_fixes(
    cfg: GnssConfig, origin: GeoOrigin, stamps: ArrayLike, true_enu: ArrayLike, seed: int = 0
) -> list[GnssFix]:
    """Fixes along a sampled trajectory ((N,) stamps s, (N, 3) ENU positions m)."""
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(true_enu, dtype=np.float64).reshape(-1, 3)
    if len(t) != len(p):
        raise CollabSlamError(f"{len(t)} stamps but {len(p)} positions")
    model = GnssModel(cfg, origin, seed)
    return [f for ti, pi in zip(t, p, strict=True) if (f := model.measure(float(ti), pi))]
