"""Keeps wrong loop closures and inter-robot constraints out of the graph.

Every verified match becomes a measurement in the group of its robot pair
(a robot with itself for loop closures). After each new measurement the group's
largest pairwise-consistent set is updated (incremental PCM, Mangelson et al.
2018, see `basestation.pcm.IncrementalPcm`):
measurements in it enter iSAM2 with a robust kernel; a measurement that drops
out of it is removed from the graph again. Each group keeps only its last
`pcm_window` matches (PCM's sliding window): an older match's state is final and
its record is dropped here (an accepted one keeps its factor). Two robots whose maps are not yet
connected are joined only when `min_consistent_to_merge` mutually consistent
matches from places at least `merge_min_spread_m` apart (of each robot) agree, so one lucky
match (and the matches it leads to nearby) cannot fuse two maps. The matches a
robot has with other robots of the same map count too when they put it in the
same place (within `merge_agree_m` / `merge_agree_rad` at their own nodes): a
robot turning on one spot may see robot A from there and robot B, on A's map,
from a few metres on (ACES: 9 agreeing matches with one robot from within 1.9 m
and 2 with another from 5 m away; the third robot never joined).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from basestation.pcm import IncrementalPcm, LoopMeasurement
from basestation.pose_graph import PoseGraph
from common.config import ConstraintConfig
from common.errors import CollabSlamError
from common.geometry import se2_between, se2_compose, se2_inverse, wrap_angle
from common.growable import Rows

log = logging.getLogger(__name__)

NodeKey = tuple[str, int]


def invert_with_covariance(T_a_b: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_b_a and its covariance (right-perturbation convention, as gtsam's Pose2)."""
    x, y, th = T_a_b
    c, s = np.cos(th), np.sin(th)
    adj = np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])
    return se2_inverse(T_a_b), adj @ cov @ adj.T


@dataclass
class _Group:
    pcm: IncrementalPcm
    measurements: dict[int, LoopMeasurement] = field(default_factory=dict)
    kinds: dict[int, str] = field(default_factory=dict)  # measurement id -> kind
    in_graph: dict[int, int] = field(default_factory=dict)  # measurement id -> factor id
    left_out: set[int] = field(default_factory=set)  # ids kept out when the maps were joined


class LoopClosureManager:
    def __init__(
        self,
        graph: PoseGraph,
        cfg: ConstraintConfig,
        chain_covariance: Callable[[str, np.ndarray, np.ndarray], np.ndarray],
    ) -> None:
        """chain_covariance(robot, I, J): (n, 3, 3) uncertainties of nodes J relative to
        nodes I along the robot's chain (index arrays)."""
        self.graph = graph
        self.cfg = cfg
        self.chain_covariance = chain_covariance
        self.groups: dict[tuple[str, str], _Group] = {}
        self._next_id = 0
        self._start_misfit_pairs: set[tuple[str, str]] = set()  # (warned once a pair)
        self.accepted: set[int] = set()
        self.offered: Counter[str] = Counter()  # matches offered, by kind
        self.accepted_kinds: Counter[str] = Counter()  # of them in the graph now
        # accepted inter-robot constraints per robot pair: rows [measurement id, index_a,
        # index_b] (an array, not a dict: one is kept for every such constraint)
        self.links: dict[tuple[str, str], Rows] = {}
        # Since the last take_journal(): new measurements, and in-graph changes (id -> in).
        self.journal: list[tuple[LoopMeasurement, str]] = []
        self.changes: dict[int, bool] = {}

    def add(
        self,
        a: NodeKey,
        b: NodeKey,
        T_a_b: np.ndarray,
        cov: np.ndarray,
        kind: str,
        measurement_id: int | None = None,
    ) -> None:
        """Offer a verified match; `measurement_id` (replay from the database) must not
        be below the next free id."""
        if measurement_id is not None:
            if measurement_id < self._next_id:
                raise CollabSlamError(f"measurement id {measurement_id} is already used")
            self._next_id = measurement_id
        if a[0] > b[0] or (a[0] == b[0] and a[1] > b[1]):
            (a, b), (T_a_b, cov) = (b, a), invert_with_covariance(T_a_b, cov)
        m = LoopMeasurement(
            self._next_id, a[0], a[1], b[0], b[1], np.asarray(T_a_b, float), 0.5 * (cov + cov.T)
        )
        self.offered[kind] += 1
        self._next_id += 1
        self.journal.append((m, kind))
        group = self.groups.get((a[0], b[0]))
        if group is None:
            pcm = IncrementalPcm(self.cfg.pcm_chi2, window=self.cfg.pcm_window)
            group = self.groups[(a[0], b[0])] = _Group(pcm)
        group.measurements[m.id] = m
        group.kinds[m.id] = kind
        poses: dict[str, np.ndarray] = {}

        def batch(robot: str, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if robot not in poses:
                poses[robot] = self.graph.poses(robot)
            P = poses[robot]
            return se2_between(P[i], P[j]), self.chain_covariance(robot, i, j)

        def odometry(robot: str, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
            T, C = batch(robot, np.array([i]), np.array([j]))
            return T[0], C[0]

        consistent = group.pcm.add(m, odometry, batch)
        if len(consistent) <= 1:  # no two agree: one alone only if it fits the estimate
            consistent = self._lone(group, consistent)
        self._settle(group)
        log.debug(
            "match %d (%s) %s:%d -> %s:%d at %s: %d of %d consistent, in: %s",
            m.id, kind, m.robot_a, m.index_a, m.robot_b, m.index_b,
            np.round(m.T_a_b, 2), len(consistent), len(group.measurements),
            m.id in consistent,
        )  # fmt: skip
        self._reconcile(group, consistent)

    def _settle(self, group: _Group) -> None:
        """Forget the matches that left the group's PCM window: their state is final (an
        accepted one keeps its factor in the graph, finalized, and its id in `accepted`)."""
        if len(group.measurements) <= group.pcm.window:
            return
        window = group.pcm.ids
        for mid in [i for i in group.measurements if i not in window]:
            del group.measurements[mid], group.kinds[mid]
            fid = group.in_graph.pop(mid, None)
            if fid is not None:  # never removed now: the graph may fuse it with its peers
                self.graph.finalize_constraint(fid)

    def _reconcile(self, group: _Group, consistent: set[int]) -> None:
        m0 = next(iter(group.measurements.values()))
        separate = m0.robot_a != m0.robot_b and not any(
            m0.robot_a in c and m0.robot_b in c for c in self.graph.components()
        )
        consistent = consistent - group.left_out
        if separate and self.graph.is_anchored(m0.robot_a) and self.graph.is_anchored(m0.robot_b):
            # both on `map` already (known starts, as sure as `basestation.prior_sigma_*`
            # say): the estimate can tell a wrong alignment (a corridor's period)
            fit = {
                i for i in consistent if self._misfit(group.measurements[i]) <= self.cfg.pcm_chi2
            }
            if consistent - fit and (m0.robot_a, m0.robot_b) not in self._start_misfit_pairs:
                self._start_misfit_pairs.add((m0.robot_a, m0.robot_b))
                log.warning("matches between %s and %s disagree with their known starts: left "
                            "out (starts measured by hand: set basestation.prior_sigma_xy_m and "
                            "prior_sigma_yaw_rad to how well)", m0.robot_a, m0.robot_b)  # fmt: skip
            consistent = fit
        if separate:
            outliers, T_a_b = self._far_from_the_rest([group.measurements[i] for i in consistent])
            if not self._enough_to_merge(group, consistent - outliers):
                if outliers:
                    log.debug("%d of the agreeing matches far from the rest", len(outliers))
                return  # wait for more agreeing matches before joining two maps
            consistent -= outliers
            group.left_out |= outliers
            # the floating map first turns and shifts to where the matches put it
            if T_a_b is not None and not self.graph.move_floating(m0.robot_b, T_a_b):
                self.graph.move_floating(m0.robot_a, se2_inverse(T_a_b))
            log.info(
                "maps of %s and %s joined by %d agreeing matches (%d offered, %d left out: "
                "far from where the rest put them)",
                m0.robot_a, m0.robot_b, len(consistent), len(group.measurements), len(outliers),
            )  # fmt: skip
        robust = None if self.cfg.robust_kernel == "none" else self.cfg.robust_kernel
        changed = (consistent - group.in_graph.keys()) | (group.in_graph.keys() - consistent)
        for mid in sorted(changed):
            m = group.measurements[mid]
            if mid in consistent and mid not in group.in_graph:
                group.in_graph[mid] = self.graph.add_constraint(
                    (m.robot_a, m.index_a),
                    (m.robot_b, m.index_b),
                    m.T_a_b,
                    m.covariance,
                    robust=robust,
                    robust_k=self.cfg.robust_k,
                )
                self.accepted.add(mid)
                self.accepted_kinds[group.kinds[mid]] += 1
                self.changes[mid] = True
                if m.robot_a != m.robot_b:
                    pair = self.links.get((m.robot_a, m.robot_b))
                    if pair is None:
                        pair = Rows(3, np.int64, memory=True)  # per constraint
                        self.links[(m.robot_a, m.robot_b)] = pair
                    pair.append((mid, m.index_a, m.index_b))
            elif mid not in consistent and mid in group.in_graph:
                self._take_out(group, mid)
                log.info("constraint %d (%s) no longer consistent: removed", mid, group.kinds[mid])
        if separate:  # other pairs the join put on one map use their agreeing matches now
            comps = self.graph.components()
            for other in list(self.groups.values()):
                m1 = next(iter(other.measurements.values()), None)
                if other is group or m1 is None or m1.robot_a == m1.robot_b:
                    continue
                same = any(m1.robot_a in c and m1.robot_b in c for c in comps)
                if not same and not all(map(self.graph.is_anchored, (m1.robot_a, m1.robot_b))):
                    continue
                accepted = other.pcm.accepted - other.in_graph.keys()
                far = self._far_from_the_estimate([other.measurements[i] for i in accepted])
                other.left_out |= far  # the join has just placed both: check against it
                accepted = other.pcm.accepted - other.left_out
                if accepted - other.in_graph.keys():
                    self._reconcile(
                        other, accepted if len(accepted) > 1 else self._lone(other, accepted)
                    )

    def _take_out(self, group: _Group, mid: int) -> None:
        """Match `mid` of `group` leaves the graph."""
        m = group.measurements[mid]
        self.graph.remove_constraint(group.in_graph.pop(mid))
        self.accepted.discard(mid)
        self.accepted_kinds[group.kinds[mid]] -= 1
        self.changes[mid] = False
        pair = self.links.get((m.robot_a, m.robot_b))
        if pair is not None and len(hit := np.flatnonzero(pair.view()[:, 0] == mid)):
            pair.drop(int(hit[0]))

    def unlink(self, robot: str, measurement_id: int | None = None) -> int | None:
        """Take `robot`'s inter-robot constraints out of the graph and forget its matches
        with other robots (its join was wrong: basestation/join_check.py); the number
        taken out, or None (nothing changed) if one of them is final (left PCM's window).
        Journaled as a match of kind "unlink" (`measurement_id`: its id, on replay)."""
        pairs = [p for p in self.groups if robot in p and p[0] != p[1]]
        if any(len(self.links.get(p, ())) > len(self.groups[p].in_graph) for p in pairs):
            return None
        self._next_id = self._next_id if measurement_id is None else measurement_id
        mark = LoopMeasurement(self._next_id, robot, 0, robot, 0, np.zeros(3), np.eye(3))
        self.journal.append((mark, "unlink"))  # (a restart undoes the join too)
        self._next_id, n = self._next_id + 1, 0
        for p in pairs:
            group = self.groups.pop(p)
            for mid in sorted(group.in_graph):
                self._take_out(group, mid)
                n += 1
            self.links.pop(p, None)
        return n

    def _far_from_the_estimate(self, ms: list[LoopMeasurement]) -> set[int]:
        """Ids of the matches that put robot b's node more than `merge_outlier_m` from its
        estimate, given robot a's. For the matches of another robot pair that a join has
        just put on one map (the moved floating map is in place): PCM only tested them
        against each other (ACES replay: two wrong matches between the second and third
        segments, 22 m off, entered with the third segment's join and bent the map)."""
        if not ms:
            return set()
        Pa = self.graph.poses(ms[0].robot_a)[[m.index_a for m in ms]]
        Pb = self.graph.poses(ms[0].robot_b)[[m.index_b for m in ms]]
        put = se2_compose(Pa, np.array([m.T_a_b for m in ms]))
        off = np.hypot(*(put[:, :2] - Pb[:, :2]).T) > self.cfg.merge_outlier_m
        return {m.id for m, far in zip(ms, off, strict=True) if far}

    def _far_from_the_rest(self, ms: list[LoopMeasurement]) -> tuple[set[int], np.ndarray | None]:
        """Ids of the matches, between two maps about to be joined, that put robot b's
        node more than `merge_outlier_m` from where the largest group of matches puts it
        (each match aligns b's map to a's; the alignment most others agree with, at
        their own nodes, is the reference, returned too: b's frame in a's). PCM tests
        matches against each other through the chains' covariance, which grows with the
        distance between the matched nodes: a wrong match hundreds of keyframes from the
        others passes it (ACES replay: one of 28 put a segment's node 35 m from where the
        other 27 did, each within 0.4 m of the rest, and bent that segment by 50
        degrees)."""
        if not ms:
            return set(), None
        Pa = self.graph.poses(ms[0].robot_a)[[m.index_a for m in ms]]
        Pb = self.graph.poses(ms[0].robot_b)[[m.index_b for m in ms]]
        A = se2_compose(se2_compose(Pa, np.array([m.T_a_b for m in ms])), se2_inverse(Pb))
        placed = se2_compose(A[:, None], Pb[None])  # [k, l]: node of match l by match k
        own = np.diagonal(placed, axis1=0, axis2=1).T  # where match l puts its own node
        d = np.hypot(*(placed[..., :2] - own[None, :, :2]).transpose(2, 0, 1))
        near = d <= self.cfg.merge_outlier_m
        ref = int(np.argmax(near.sum(axis=1)))
        if len(ms) < 3:  # too few to tell an outlier
            return set(), A[ref]
        return {m.id for m, ok in zip(ms, near[ref], strict=True) if not ok}, A[ref]

    def _lone(self, group: _Group, consistent: set[int], last: int = 10) -> set[int]:
        """The match to use when no two of the group agree (PCM's clique has one member,
        any of them): PCM tests matches only against each other, so a lone one would enter
        untested. Of PCM's pick and the group's `last` newest, the one that agrees best
        with the current estimate (`_misfit` within `pcm_chi2`), or none: wait for a
        second match consistent with one of them. Between robots on different maps the
        merge rule decides instead."""
        ids = sorted(group.pcm.ids)[-last:]
        m0 = group.measurements[ids[-1]]
        ra, rb = m0.robot_a, m0.robot_b
        if ra != rb and not any(ra in c and rb in c for c in self.graph.components()):
            return consistent
        fits = {i: self._misfit(group.measurements[i]) for i in {*ids, *consistent}}
        best = min(fits, key=lambda i: fits[i])
        if fits[best] > self.cfg.pcm_chi2:
            log.debug("group %s-%s: no lone match agrees with the estimate: none used", ra, rb)
            return set()
        return {best}

    def _misfit(self, m: LoopMeasurement) -> float:
        """Mahalanobis distance^2 of a match from the estimated relative pose of its nodes,
        under the match's covariance plus the chain's (one robot) or both nodes'
        marginals (two robots; correlations left out, which only makes it more lenient)."""
        a, b = (m.robot_a, m.index_a), (m.robot_b, m.index_b)
        T_est = se2_between(self.graph.pose(*a), self.graph.pose(*b))
        if a[0] == b[0]:  # stored with index_a < index_b (add): T_a_b along the chain
            cov = m.covariance + self.chain_covariance(a[0], np.array([a[1]]), np.array([b[1]]))[0]
        else:
            marginal_a = self.graph.marginal_covariance(*a)
            _, cov_a = invert_with_covariance(se2_inverse(T_est), marginal_a)
            cov = m.covariance + cov_a + self.graph.marginal_covariance(*b)
        r = se2_between(T_est, m.T_a_b)
        return float(r @ np.linalg.solve(cov, r))

    def _enough_to_merge(self, group: _Group, consistent: set[int]) -> bool:
        """`min_consistent_to_merge` agreeing matches, seen from places of each robot at
        least `merge_min_spread_m` apart: in look-alike rooms one wrong match and the
        matches searched near where it put the robot can agree; a few metres on, the
        likeness usually breaks. The robot's accepted matches with other robots of the
        other map count too if they put it where this group's do (module doc).
        Matches of the pair that disagree with them are evidence for another
        placement (a corridor seen both ways): the agreeing ones must outnumber them
        by `min_consistent_to_merge`, or with matches from elsewhere, be the majority.
        The agreeing matches must also come from `min_consistent_to_merge` stretches of
        the chain of each robot whose start is unknown (`_stretches`)."""
        ms = [group.measurements[i] for i in sorted(consistent)]
        if not ms:
            return False
        disagreeing = len(group.measurements) - len(ms)
        floating = [  # the matched nodes of each robot whose start is unknown
            [m.index_a if m.robot_a == r else m.index_b for m in ms]
            for r in (ms[0].robot_a, ms[0].robot_b)
            if not self.graph.is_anchored(r)
        ]
        stretches = min((self._stretches(nodes) for nodes in floating), default=len(ms))
        n_min = self.cfg.min_consistent_to_merge
        if (
            len(ms) - disagreeing >= n_min
            and stretches >= n_min
            and self._spread_enough(ms[0].robot_b, [m.index_b for m in ms])
            and self._spread_enough(ms[0].robot_a, [m.index_a for m in ms])
        ):
            return True  # seen from places of both robots apart
        log.debug(
            "%s-%s wait: %d agreeing against %d, %d stretches",
            ms[0].robot_a, ms[0].robot_b, len(ms), disagreeing, stretches,
        )  # fmt: skip
        if disagreeing >= len(ms):
            return False
        for x, y in ((ms[0].robot_b, ms[0].robot_a), (ms[0].robot_a, ms[0].robot_b)):
            extra = self._agreeing_elsewhere(x, y, ms)  # seen from more places of x?
            own = [m.index_b if x == m.robot_b else m.index_a for m in ms]
            if (
                extra
                and self._spread_enough(x, own + extra)
                and (self.graph.is_anchored(x) or self._stretches(own + extra) >= n_min)
            ):
                return True
        return False

    def _stretches(self, nodes: list[int]) -> int:
        """How many of a robot's matched nodes are `merge_stretch_keyframes` apart along its
        chain: matches from overlapping stretches share their scans (an ACES replay: 4
        whole-map matches of one segment, 5 keyframes apart and each over its 20 newest
        scans, 1 against, agreed on a corridor seen the other way round and joined the
        segment 20 m off)."""
        count, last = 0, None
        for i in sorted(nodes):
            if last is None or i - last >= self.cfg.merge_stretch_keyframes:
                count, last = count + 1, i
        return count

    def _spread_enough(self, robot: str, nodes: list[int]) -> bool:
        """At least `min_consistent_to_merge` nodes of `robot`, the farthest two at least
        `merge_min_spread_m` apart."""
        if len(nodes) < self.cfg.min_consistent_to_merge:
            return False
        P = self.graph.poses(robot)[nodes, :2]
        spread = float(np.max(np.hypot(*(P[:, None] - P[None]).transpose(2, 0, 1))))
        return spread >= self.cfg.merge_min_spread_m

    def _agreeing_elsewhere(self, x: str, y: str, ms: list[LoopMeasurement]) -> list[int]:
        """Nodes of robot `x` in its accepted matches with robots sharing `y`'s frame
        (other than `y`) that put them where `ms` (matches of x with y) puts them."""
        comps = self.graph.components()
        frame = next((c for c in comps if y in c), [y])
        anchored = self.graph.is_anchored(y)
        others = {
            r for r in self.graph.robots()
            if r not in (x, y) and (r in frame or (anchored and self.graph.is_anchored(r)))
        }  # fmt: skip
        if not others:
            return []
        X = self.graph.poses(x)
        # x's frame into y's, from this group's matches: mean of their alignments
        A = np.array([self._align(m, x, X) for m in ms])
        yaw = float(np.arctan2(np.sin(A[:, 2]).mean(), np.cos(A[:, 2]).mean()))
        ref = np.array([*A[:, :2].mean(axis=0), yaw])
        out = []
        for (ra, rb), g in self.groups.items():
            if {ra, rb} & others and x in (ra, rb) and ra != rb:
                for mid in g.pcm.accepted:
                    m = g.measurements.get(mid)
                    if m is None:
                        continue
                    i = m.index_b if x == m.robot_b else m.index_a
                    here = se2_compose(self._align(m, x, X), X[i])
                    there = se2_compose(ref, X[i])
                    if (
                        np.hypot(*(here[:2] - there[:2])) <= self.cfg.merge_agree_m
                        and abs(wrap_angle(here[2] - there[2])) <= self.cfg.merge_agree_rad
                    ):
                        out.append(i)
        return out

    def _align(self, m: LoopMeasurement, x: str, X: np.ndarray) -> np.ndarray:
        """The transform from robot `x`'s frame into its partner's that match `m` implies."""
        if x == m.robot_b:
            at = se2_compose(self.graph.pose(m.robot_a, m.index_a), m.T_a_b)
            return se2_compose(at, se2_inverse(X[m.index_b]))
        at = se2_compose(self.graph.pose(m.robot_b, m.index_b), se2_inverse(m.T_a_b))
        return se2_compose(at, se2_inverse(X[m.index_a]))

    def covered(self, a: NodeKey, b: NodeKey) -> bool:
        """Whether robots a[0] and b[0] have an accepted constraint whose two ends are
        each within `inter_redundant_keyframes` of nodes a and b along their chains: the
        two stretches of trajectory are tied already (odometry holds along a stretch), so
        one more tie adds little information, but each adds fill-in to iSAM2 (a
        Bayes-tree clique spanning both robots). Closeness in space alone is not enough:
        a robot that comes back to a place it was tied at has drifted since."""
        if a[0] > b[0]:
            a, b = b, a
        links, k = self.links.get((a[0], b[0])), self.cfg.inter_redundant_keyframes
        if links is None or not len(links) or k <= 0:
            return False
        ends = links.view()[:, 1:]
        return bool(np.any((np.abs(ends[:, 0] - a[1]) <= k) & (np.abs(ends[:, 1] - b[1]) <= k)))

    def take_journal(self) -> tuple[list[tuple[LoopMeasurement, str]], dict[int, bool]]:
        """New measurements (with kind) and in-graph changes since the last call."""
        out = (self.journal, self.changes)
        self.journal, self.changes = [], {}
        return out

    def pending_links(self) -> list[LoopMeasurement]:
        """For each robot pair whose maps are still separate (waiting for
        `min_consistent_to_merge` agreeing matches), the newest match of PCM's largest
        consistent set (the placement most matches agree on), or the newest match: more
        matches are looked for where it says. (ACES: a corridor that looks alike 20 m on
        gave a segment 7 wrong matches besides 10 right ones; searching where the newest
        match said, a wrong one, the segment never joined.)"""
        comps = self.graph.components()
        out = []
        for (ra, rb), g in self.groups.items():
            if ra == rb or not g.measurements or any(ra in c and rb in c for c in comps):
                continue
            lead = [i for i in g.pcm.accepted if i in g.measurements] or list(g.measurements)
            out.append(g.measurements[max(lead)])
        return out

    def pcm_stats(self) -> dict[str, int]:
        """Groups, matches in their PCM windows (largest), matches settled out of them."""
        windows = [len(g.pcm.measurements) for g in self.groups.values()]
        return {
            "groups": len(windows),
            "largest_window": max(windows, default=0),
            "settled": sum(g.pcm.settled for g in self.groups.values()),
        }

    def counts(self) -> dict[str, int]:
        loops = self.accepted_kinds["loop"]
        false, false_in = self.offered["false"], self.accepted_kinds["false"]
        total = self.offered.total() - false
        real_accepted = self.accepted_kinds.total() - false_in
        out = {
            "loop_closures": loops,
            "inter_robot_constraints": real_accepted - loops,
            "rejected_by_pcm": total - real_accepted,
        }
        if false:
            out |= {"false_matches_injected": false, "false_matches_accepted": false_in}
        return out
