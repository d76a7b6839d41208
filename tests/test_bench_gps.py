"""`collabslam bench gps` on a short flight: JSON shape, files, GPS beats no GPS."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.gps import RunSpec, run
from benchmarks.gps_flight import make_flight
from collabslam.cli import main
from common.config import Config
from common.geometry import se2_between
from common.trajectory_io import read_tum

RUN_KEYS = {"weighting", "a", "b", "huber", "outlier_fraction", "ate_rmse_m"}


def test_flight_has_keyframes_odometry_and_loops(cfg: Config) -> None:
    f = make_flight(cfg, "rooms15", 60.0, seed=0)
    assert len(f.deltas) == len(f.kf_index) - 1 > 100
    se2 = f.kf_truth[:, [0, 1, 3]]
    err = [np.abs(d - se2_between(se2[k], se2[k + 1]))[:2].max() for k, d in enumerate(f.deltas)]
    assert max(err) < 0.01  # odometry is the true motion plus small noise
    assert f.loops, "a 60 m tour of rooms15 comes back to places it saw"
    for i, j, rel, _ in f.loops:
        np.testing.assert_allclose(rel[:2], se2_between(se2[i], se2[j])[:2], atol=0.3)


def test_bench_json_and_outputs(cfg: Config, tmp_path: Path) -> None:
    specs = [
        RunSpec("none"),
        RunSpec("inverse", huber=True),
        RunSpec("inverse", huber=True, outlier_fraction=0.1),
        RunSpec("inverse", 1.0, 0.5),
    ]
    result = run(cfg, tmp_path, tmp_path, "rooms15", length_m=60.0, gnss_seeds=1, specs=specs)
    assert [r["weighting"] for r in result["runs"]] == ["none", "inverse", "inverse", "inverse"]
    for row in result["runs"]:
        assert RUN_KEYS <= set(row) and row["ate_rmse_m"] >= 0.0
    gps = [r for r in result["runs"] if r["weighting"] != "none"]
    assert all(r["gps_factors"] > 30 for r in gps)
    assert max(r["ate_rmse_m"] for r in gps) < result["runs"][0]["ate_rmse_m"]
    assert result["isam2_update_ms_p95_with_gps"] > 0 < result["isam2_update_ms_p95_without_gps"]
    assert (tmp_path / "gps_fig8.png").stat().st_size > 10_000
    gt = read_tum(tmp_path / "ground_truth.tum")
    assert gt.wgs84_origin is not None and len(gt) == result["flight"]["keyframes"]


def test_cli_bench_gps(tmp_path: Path) -> None:
    out = tmp_path / "gps.json"
    argv = ["bench", "gps", "--json", str(out), "--world", "rooms15", "--length", "25"]
    assert main([*argv, "--seeds", "1"]) == 0
    doc = json.loads(out.read_text())
    weightings = {r["weighting"] for r in doc["runs"]}
    assert weightings == {"none", "inverse", "isotropic"}
    eq7 = {(r["a"], r["b"]) for r in doc["runs"] if (r["a"], r["b"]) != (1.0, 0.0)}
    assert len(eq7) == 2
    assert {r["huber"] for r in doc["runs"]} == {False, True}
    assert {r["outlier_fraction"] for r in doc["runs"]} == {0.0, 0.1}
    assert "isam2_update_p95_ratio" in doc
