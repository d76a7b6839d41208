"""The global-SLAM statistics the base station writes to basestation.json."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from basestation.global_slam import GlobalSlam


def slam_stats(slam: GlobalSlam) -> dict[str, Any]:
    """Per-robot keyframe counts, iSAM2 latencies, match counts, the verifier's and
    PCM's statistics, and GPS's: the global-SLAM part of basestation.json."""
    upd = np.array(slam.update_ms) if slam.update_ms else np.zeros(1)  # the latest ones
    out: dict[str, Any] = {
        "robots": {
            rid: {
                "keyframes_in_graph": slam.graph.num_nodes(rid)
                if rid in slam.graph.robots()
                else 0,
                "duplicates": r.duplicates,
                "id_conflicts": r.id_conflicts,
                "another_source": r.foreign,  # its later keyframes refused
                "held_out_of_order": len(r.held),
                "keyframe_chain": r.chain,  # and keyframes of other chains, dropped:
                "chain_drops": {
                    "older": r.stale_chain,
                    "unchecked": r.unchecked_chain,
                    "conflicts": r.chain_conflicts,
                },  # fmt: skip
                "anchored": rid in slam.graph.robots() and slam.graph.is_anchored(rid),
                **slam.join_check.stats(rid),  # joins to the map found wrong (join_check.py)
            }
            for rid, r in slam.store.robots.items()
        },
        "isam2_updates": slam.updates,
        "isam2_update_ms_p50": float(np.percentile(upd, 50)),
        "isam2_update_ms_p95": float(np.percentile(upd, 95)),
        "isam2_update_ms_series": slam.update_series.to_json(),
        "pose_graph": {
            **slam.graph.reduction_stats(),
            "rebuilds": slam.graph.num_rebuilds,
            "dormant_ties": slam.graph.num_dormant,  # left out of iSAM2 by the last rebuild
        },
        **slam.loops.counts(),
        "pcm": slam.loops.pcm_stats(),
        "scans": slam.store.scan_archive.stats(),
        "map_frame": slam.map_frame.stats(),  # robots that cannot be joined to it, and why
    }
    failed = 0
    if slam.builder is not None:
        out["constraint_builder"] = dict(slam.builder.stats)
        failed = sum(v for k, v in slam.builder.stats.items() if k.startswith("failed_"))
    # candidates that failed scan-match verification or the consistency check
    out["rejected_candidates"] = out["rejected_by_pcm"] + failed
    if slam.gps_enabled:
        out["gps"] = {**slam.graph.gps_stats(), "fixes_ignored": slam.gps_fixes_ignored}
    return out
