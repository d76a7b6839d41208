"""`basestation.constraints` of the configuration tree (common/config.py): loop
closures and inter-robot constraints, whole-map searches, outlier rejection and the
rules for joining two robots' maps."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ConstraintConfig:
    """Loop closures and inter-robot constraints (seed 002 §1.1, eq. 2)."""

    enabled: bool = True
    search_radius_m: float = 10.0  # r_t, m
    search_angle_rad: float = 1.5707963267948966  # r_theta, rad (pi/2)
    loop_min_index_gap: int = 30  # d_thresh, keyframes between a node and a loop candidate
    # A loop candidate also needs this much travel (m) since the target, and at least twice
    # the straight distance: the robot went away and came back (not just drove on).
    loop_min_travel_m: float = 10.0
    # the whole-map search target is rebuilt once the map grew by a quarter, at least
    # global_query_keyframes and at most this many nodes
    global_map_rebuild_nodes: int = 200
    global_query_keyframes: int = 20  # recent keyframes matched against the map at once
    candidate_stride: int = 3  # keyframes of a robot between candidates against one robot
    # An inter-robot candidate is not verified when the two robots have a constraint with
    # both ends within this many keyframes of its own (0: off): fill-in, little else.
    inter_redundant_keyframes: int = 10
    # When two robots' maps are joined, the earlier nodes of the one with fewer nodes are
    # searched against the other (every candidate_stride-th with a candidate), at most this many.
    backfill_max_candidates: int = 200
    target_neighbours: int = 3  # keyframes on each side of the target node form its "submap"
    linear_window_m: float = 1.5  # m, correlative search half-width around the guess
    angular_window_deg: float = 30.0  # deg
    min_score: float = 0.55  # mean cell probability of the matched points
    min_overlap: float = 0.5  # fraction of points with a neighbour within max_corr_dist
    max_corr_dist_m: float = 0.2  # m, ICP correspondence distance
    max_candidates_per_s: float = 30.0  # verification budget of the worker (wall time)
    max_queue: int = 500  # pending candidates per kind (newest served first); no new ones beyond
    robust_kernel: str = "huber"  # huber | cauchy | none
    robust_k: float = 1.345
    pcm_chi2: float = 11.345  # chi2(3 dof, 0.99): pairwise consistency threshold
    # Matches per robot pair (or robot's loops) PCM keeps and tests a new one against; one
    # leaving this window keeps its state (accepted: stays in the graph). Bounds PCM's
    # consistency matrix to pcm_window^2 float64 per pair (80 kB at 100).
    pcm_window: int = 100
    min_consistent_to_merge: int = 3  # consistent matches needed to join two robots' maps
    merge_min_spread_m: float = 2.0  # m between the places those matches were seen from
    # ... and from that many stretches of both robots' chains this many keyframes long: a
    # whole-map search matches a robot's 20 newest scans (global_query_keyframes).
    merge_stretch_keyframes: int = 20
    # A robot's matches with other robots of the same map count toward the merge when they
    # put it where the pair's matches do, within this (at the matched node; m, rad).
    merge_agree_m: float = 1.0
    merge_agree_rad: float = 0.2
    # A match of a join that puts the robot's node this far (m) from where most of the
    # join's matches put it is left out of the graph for good (LoopClosureManager).
    merge_outlier_m: float = 5.0
    global_search_every: int = 5  # keyframes of an unanchored robot between global searches
    # ... and of a robot joined to the map by matches, for this many keyframes after the
    # join (0: off): a join the searches contradict is undone (basestation/join_check.py)
    join_check_keyframes: int = 300
    # Global searches a robot may have waiting; older ones are dropped (live: only the
    # newest scan is worth it). A replay sets it high: every search runs, as at sensor rate.
    global_pending_per_robot: int = 1
    global_min_score: float = 0.65  # stricter score for a whole-map search
    # Coarse optima of a whole-map search refined and tested (distinct places; the best
    # that passes is kept). ACES replays with 3 found more matches, wrong ones among them
    # (docs/architecture.md, "Candidates").
    global_candidates: int = 1
    # Evaluation only (robustness benchmarks): after each verified match, inject a wrong
    # one with probability f / (1 - f) so that a fraction f of all matches is false.
    false_match_fraction: float = 0.0
    false_match_seed: int = 0
