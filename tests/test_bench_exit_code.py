"""`collabslam bench` exits 1 when a target is missed: `bench security`, the deployment
check of docs/operations.md, had exited 0 with `legitimate_ok` false, and `bench faults`
with keyframes lost, so a script could not rely on it."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

from collabslam.bench_cli import bench_exit_code


def test_a_missed_target_or_a_failed_run_exits_one() -> None:
    assert bench_exit_code({"all_rejected": True, "legitimate_ok": True}) == 0
    assert bench_exit_code({"all_rejected": True, "legitimate_ok": False}) == 1
    assert bench_exit_code({"all_rejected": False, "legitimate_ok": True}) == 1
    assert bench_exit_code({"targets_met": {"keyframes_lost == 0": True}}) == 0
    assert bench_exit_code({"targets_met": {"keyframes_lost == 0": False}}) == 1
    assert bench_exit_code({"failed_runs": 2, "ours": []}) == 1
    assert bench_exit_code({"ours": [], "baseline": []}) == 0
    assert bench_exit_code({"interrupted": True, "ours": []}) == 130


def test_an_interrupted_exploration_bench_reports_the_runs_it_finished(tmp_path: Path) -> None:
    """Ctrl-C in a long `bench exploration` had lost every run finished (no JSON): now
    the report holds them, says `interrupted`, and the bench exits 130."""
    out = tmp_path / "bench.json"
    cmd = [sys.executable, "-m", "collabslam.cli", "bench", "exploration", "--kinematic",
           "--world", "bshape", "--robots", "3", "--seeds", "200", "--strategies", "ours",
           "--json", str(out)]  # fmt: skip
    with subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True) as p:
        assert p.stderr is not None
        for line in p.stderr:  # the first run's line, then Ctrl-C
            if "time_to_95" in line:
                break
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err[-2000:]
    report = json.loads(out.read_text())
    assert report["interrupted"] is True and 1 <= len(report["ours"]) < 200
    assert all(row["time_to_95_s"] is not None for row in report["ours"])
