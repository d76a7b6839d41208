"""`collabslam bench` exits 1 when a target is missed: `bench security`, the deployment
check of docs/operations.md, had exited 0 with `legitimate_ok` false, and `bench faults`
with keyframes lost, so a script could not rely on it."""

from __future__ import annotations

from collabslam.bench_cli import bench_exit_code


def test_a_missed_target_or_a_failed_run_exits_one() -> None:
    assert bench_exit_code({"all_rejected": True, "legitimate_ok": True}) == 0
    assert bench_exit_code({"all_rejected": True, "legitimate_ok": False}) == 1
    assert bench_exit_code({"all_rejected": False, "legitimate_ok": True}) == 1
    assert bench_exit_code({"targets_met": {"keyframes_lost == 0": True}}) == 0
    assert bench_exit_code({"targets_met": {"keyframes_lost == 0": False}}) == 1
    assert bench_exit_code({"failed_runs": 2, "ours": []}) == 1
    assert bench_exit_code({"ours": [], "baseline": []}) == 0
