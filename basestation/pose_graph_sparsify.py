"""Which ties between places a reduced pose graph keeps in iSAM2: a bounded degree.

A reduced pose graph (``pose_graph_reduction``) has one variable per place, and its
ties (odometry and final constraints between two places) grow with the pairs of places
flown between, long after the places stop growing: over the 10-robot, 30-minute soak
the variables grew 11 % from 50,000 to 100,000 keyframes and the ties 30 %, and iSAM2's
memory (the marginal it keeps in every clique, ~ the separator's size squared) 44 %
(a fresh iSAM2 of the graph: 28.8 -> 41.5 MB). So each fresh iSAM2
(``pose_graph_rebuild``) takes a sparser place graph: a spanning forest of these ties
alone, the shortest first, then the shortest others while both their variables have
fewer than ``degree`` ties. Factors that are not ties between settled places (priors,
GPS, the chains' newest stretch, constraints still in PCM's windows) are all kept and
count toward the degree. The ties left out stay in the graph's records (dormant), and
each rebuild chooses again from all of them.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple


class Tie(NamedTuple):
    """A two-variable factor: its id, its variables, their distance (m), and whether it
    may be left out (a tie between settled places)."""

    fid: int
    a: int
    b: int
    length_m: float
    optional: bool


def ties_to_drop(ties: Iterable[Tie], degree: int) -> list[int]:
    """Ids of the optional ties to leave out (see the module doc), in id order. Every
    pair of variables the optional ties joined stays joined by them (whatever becomes of
    the fixed ties later); ``degree`` <= 0: none."""
    ties = list(ties)
    if degree <= 0:
        return []
    parent: dict[int, int] = {}

    def root(k: int) -> int:
        r = parent.setdefault(k, k)
        while r != parent[r]:
            parent[r] = parent[parent[r]]  # path halving
            r = parent[r]
        return r

    count: dict[int, int] = {}
    for t in ties:  # fixed ties count toward the degree but not for joining: a constraint
        if not t.optional:  # still in PCM's window may be removed
            count[t.a] = count.get(t.a, 0) + 1
            count[t.b] = count.get(t.b, 0) + 1
    optional = sorted((t for t in ties if t.optional), key=lambda t: (t.length_m, t.fid))
    rest = []
    for t in optional:  # the spanning forest, shortest first (Kruskal)
        ra, rb = root(t.a), root(t.b)
        if ra == rb:
            rest.append(t)
            continue
        parent[ra] = rb
        count[t.a] = count.get(t.a, 0) + 1
        count[t.b] = count.get(t.b, 0) + 1
    drop = []
    for t in rest:  # then the shortest others, up to the degree at both ends
        if count.get(t.a, 0) < degree and count.get(t.b, 0) < degree:
            count[t.a] = count.get(t.a, 0) + 1
            count[t.b] = count.get(t.b, 0) + 1
        else:
            drop.append(t.fid)
    return sorted(drop)
