"""A lock-step simulation repeats exactly, however loaded the machine is: two
`collabslam run` missions with the same seed, run at the same time (each slows the
other down, unevenly), fly the same trajectories to the last bit (simulator, base
station and agents as separate processes over loopback Zenoh; basestation/lockstep.py,
agent/downlink_gate.py)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.e2e


def _start(out: Path) -> subprocess.Popen[str]:
    args = ["--world", "bshape", "--robots", "3", "--out", str(out), "--max-sim-time", "8"]
    return subprocess.Popen(
        [sys.executable, "-m", "collabslam.cli", "run", *args, "--set", "sim.seed=3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_two_lockstep_missions_at_once_fly_the_same(tmp_path: Path) -> None:
    outs = [tmp_path / "a", tmp_path / "b"]
    procs = [_start(out) for out in outs]
    try:
        for p in procs:
            _, err = p.communicate(timeout=300)
            assert p.returncode == 0, err[-3000:]
    finally:  # a stuck or failed mission: its processes must not outlive the test
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)  # `run` stops its children in order
                try:
                    p.wait(60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    a, b = outs
    for rid in ("r0", "r1", "r2"):
        for kind in ("ground_truth", "trajectories"):  # the world's, the base station's
            ta = np.loadtxt(a / kind / f"{rid}.tum")
            tb = np.loadtxt(b / kind / f"{rid}.tum")
            assert ta.shape == tb.shape and np.array_equal(ta, tb), (kind, rid)
        flown = np.loadtxt(a / "ground_truth" / f"{rid}.tum")[:, 1:3]
        assert np.linalg.norm(flown[-1] - flown[0]) > 0.5, rid  # exploring, not hovering
    sa, sb = (json.loads((out / "basestation.json").read_text()) for out in outs)
    assert sa["exploration"]["paths_sent"] == sb["exploration"]["paths_sent"] > 3
    assert (a / "map.pgm").read_bytes() == (b / "map.pgm").read_bytes()
    for out in outs:
        sim = json.loads((out / "simulator.json").read_text())
        assert sim["basestation_syncs"] >= 8 and sim["basestation_sync_timeouts"] == 0
