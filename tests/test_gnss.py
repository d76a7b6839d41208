"""Simulated GNSS: rate, error statistics, bias and drift, outages, outliers, seeding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.config import Config, load_config
from common.errors import ConfigError
from common.geodesy import GeoOrigin
from simulation.gnss import GnssModel, simulate_fixes, world_origin

ORIGIN = GeoOrigin(45.8118, 16.0106, 160.0)


def _track(duration_s: float, dt: float = 0.025) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, duration_s, dt)
    p = np.column_stack([np.cos(0.01 * t) * 50, np.sin(0.01 * t) * 50, np.full_like(t, 10.0)])
    return t, p


def test_rate_and_error_statistics(cfg: Config) -> None:
    g = dataclasses.replace(cfg.sim.gnss, outage_rate_per_min=0.0, vertical_drift_mps=0.0)
    t, p = _track(2000.0)
    fixes = simulate_fixes(g, ORIGIN, t, p, seed=1)
    assert len(fixes) == pytest.approx(2000, abs=1)  # 1 Hz
    stamps = np.array([f.stamp for f in fixes])
    np.testing.assert_allclose(np.diff(stamps), 1.0, atol=0.03)
    truth = np.array([p[np.argmin(np.abs(t - s))] for s in stamps])
    err = np.array([f.enu(ORIGIN) for f in fixes]) - truth
    sig = np.array([f.sigmas_enu for f in fixes])
    bias = [g.bias_east_m, g.bias_north_m, g.bias_up_m]
    np.testing.assert_allclose(err.mean(axis=0), bias, atol=0.25)
    # normalised errors are standard normal: the reported sigmas are the true ones
    z = (err - bias) / sig
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.08)
    assert np.median(sig[:, 0]) == pytest.approx(g.sigma_east_m, rel=0.2)
    assert sig[:, 0].std() > 0.1  # per-fix sigmas vary (eq. 5 has something to weigh)


def test_outages_outliers_and_vertical_drift(cfg: Config) -> None:
    g = dataclasses.replace(
        cfg.sim.gnss,
        outage_rate_per_min=2.0,
        outage_duration_s=15.0,
        outlier_fraction=0.1,
        vertical_drift_mps=0.01,
        sigma_variation=0.0,
    )
    t, p = _track(1500.0)
    model = GnssModel(g, ORIGIN, seed=3)
    fixes = [f for ti, pi in zip(t, p, strict=True) if (f := model.measure(float(ti), pi))]
    gaps = np.diff([f.stamp for f in fixes])
    assert model.outages > 10 and gaps.max() >= 15.0  # outages leave gaps
    assert len(fixes) < 1500 - 10 * 14
    frac = np.mean([f.outlier for f in fixes])
    assert frac == pytest.approx(0.1, abs=0.03)
    stamps = np.array([f.stamp for f in fixes])
    truth = np.array([p[np.argmin(np.abs(t - s))] for s in stamps])
    err = np.array([f.enu(ORIGIN) for f in fixes]) - truth
    jumps = np.linalg.norm(err[:, :2], axis=1)
    outl = np.array([f.outlier for f in fixes])
    assert jumps[outl].min() > g.outlier_min_m - 4 * g.sigma_east_m
    assert np.median(jumps[~outl]) < 3.0
    slope = np.polyfit(stamps, err[:, 2], 1)[0]
    assert slope == pytest.approx(0.01, abs=0.003)  # slow vertical drift


def test_seeded_and_world_origin(cfg: Config) -> None:
    t, p = _track(30.0)
    a = simulate_fixes(cfg.sim.gnss, ORIGIN, t, p, seed=7)
    b = simulate_fixes(cfg.sim.gnss, ORIGIN, t, p, seed=7)
    c = simulate_fixes(cfg.sim.gnss, ORIGIN, t, p, seed=8)
    assert [f.lla.tolist() for f in a] == [f.lla.tolist() for f in b]
    assert [f.lla.tolist() for f in a] != [f.lla.tolist() for f in c]
    assert world_origin(None, cfg.sim.gnss).lat_deg == cfg.sim.gnss.origin_lat_deg
    assert world_origin(ORIGIN, cfg.sim.gnss) is ORIGIN


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="sim.gnss.rate_hz"):
        load_config(overrides={"sim.gnss.rate_hz": 0.0})
    with pytest.raises(ConfigError, match="basestation.gps.weighting"):
        load_config(overrides={"basestation.gps.weighting": "median"})
    with pytest.raises(ConfigError, match="outlier_fraction"):
        load_config(overrides={"sim.gnss.outlier_fraction": 1.0})
    with pytest.raises(ConfigError, match="a / b"):
        load_config(overrides={"basestation.gps.a": 0.0, "basestation.gps.b": 0.0})
