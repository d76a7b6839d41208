"""`collabslam bench backend`: iSAM2 fed node by node vs. batch Levenberg-Marquardt.

Multi-robot graphs with 3 chains: a g2o graph's odometry chain (edges i -> i+1) is
cut into 3 consecutive segments, one robot each (robot k's node 0 is its segment's
first vertex). The robots run at the same time: step s adds node s of r0, r1, r2
in turn, and every new node gets its own ``PoseGraph.update()`` together with every
edge that has just become available (its odometry edge, plus each other edge of the
file, loop closures and the edges across segment cuts, once both of its vertices
exist; all as ``add_constraint(..., robust=None)`` so the problem equals batch's).

Starts: every robot has a known start (``T_map_first``), as in a scenario run. It is
the reference solution (batch LM of the whole single-chain prefix, from the file's
vertices) at the segment's first vertex, so the start priors agree with the rest of
the graph and the optimum is the file's own. (With floating r1/r2 their initial
guesses sit in unrelated frames until the first inter-robot edge, and the timings
would include gauge merges that a scenario run never does.)

Timed per update, as ``BaseStationNode.process`` runs it: ``PoseGraph.update()``
with the base station's settings (``cfg.basestation``: iSAM2 parameters and
``track_changes``, off by default) plus the correction query after it
(``latest_index`` and ``pose`` of each robot's newest node: iSAM2 back-substitution
and three single-pose reads).

Result keys:
- ``sizes``: the first N vertices of M3500 (N <= 3500) or of city10000.
  ``isam2_update_ms_*``: the timed update above, from the feed with the median p50 of
  ``feed_runs`` identical feeds (``FEED_RUNS`` up to ``FEED_RUNS_MAX_NODES`` nodes, else
  one), as batch LM's time is the median of its runs; ``isam2_solve_ms_*``: its iSAM2
  ``update()`` calls alone (``UpdateStats.solve_ms``). iSAM2 defers back-substitution
  to the first estimate query after an update, so the rest is back-substitution,
  the single-pose reads and our Python. ``tracked_update_ms_*``: the same feed with
  ``track_changes=True`` (every update also extracts all n poses and compares them
  with the previous estimate: what ``isam2_update_ms_*`` measured before the base
  station turned tracking off). ``batch_reorders``: updates in which iSAM2
  re-ordered the whole tree (``basestation.adaptive_reorder_threshold``).
  ``batch_ms``: LM on the final graph from the initial guesses iSAM2 got
  (``batch_optimize(graph, start="guess")``; iSAM2's guess for a new node is its
  predecessor's current estimate composed with the odometry), the median of
  ``BATCH_RUNS`` identical runs because one run on a loaded machine varies by 2x;
  ``batch_ms_from_odometry``: one LM run from dead reckoning instead.
  ``*_cpu_ms``, ``ratio_batch_over_isam2_cpu``: the same timings as CPU time of
  the benchmark's thread (gtsam runs single-threaded here). On a machine shared
  with other work a 20 ms LM run is preempted far more often than a 0.2 ms
  update, so the wall-time ratio grows with the load; the CPU-time ratio does not.
  ``ratio_batch_over_isam2`` = ``batch_ms`` / the MEDIAN (p50) per-update iSAM2 time,
  the comparison behind seed 002's "iSAM2 2 ms vs. batch > 600 ms for 500 nodes".
- ``reduced``: the largest size's feed again with the reduced pose graph on from the
  first node (basestation/pose_graph_reduction.py), one entry per ``reduce_distance_m``
  in ``REDUCED_DISTANCES_M``, and a last entry with the base station's own settings
  (``basestation.reduce_distance_m`` from ``basestation.reduce_after_nodes`` nodes on):
  the update timings, ``variables`` and ``factors`` iSAM2 holds at the end, and
  ``offset_from_batch_optimum_m_mean`` / ``_max``: how far the positions end from batch
  LM's optimum of the whole (unreduced) graph, the price of the frozen offsets.
- ``chi2``: final chi2 (sum of squared whitened residuals) of the incrementally fed
  iSAM2 and of batch LM (from the same initial guesses), whole M3500 and Intel.
- ``sim``: a simulated 3-robot run (``simulate_team``): noisy odometry, intra- and
  inter-robot loop closures, known true starts; ``ate_rms_m`` against the truth.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from basestation.batch_solver import BatchResult, batch_optimize
from basestation.pose_graph import PoseGraph
from common.config import Config
from common.errors import CollabSlamError
from common.g2o_io import G2oGraph, read_g2o
from common.geometry import se2_between, se2_compose, wrap_angle
from common.metrics import percentiles

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
ROBOTS = ("r0", "r1", "r2")
M3500_NODES = 3500
BATCH_RUNS = 3  # identical LM runs per graph; batch_ms is their median
# identical feeds per graph, iSAM2's timings from the one with the median p50, as batch's:
# the first feed of a process runs colder than the LM runs after it. Graphs larger than
# FEED_RUNS_MAX_NODES get one feed (city10000's takes over a minute).
FEED_RUNS = 3
FEED_RUNS_MAX_NODES = 3500
# basestation.reduce_distance_m values of the "reduced" entries: 0.5 m, and ones that alias
# one or two grid steps of city10000 (1 m apart)
REDUCED_DISTANCES_M = (0.5, 1.0, 2.0)


class Constraint(NamedTuple):
    key_a: tuple[str, int]
    key_b: tuple[str, int]
    T_a_b: FloatArray  # node b in node a's frame [x, y, yaw]
    covariance: FloatArray  # 3x3, body frame


@dataclass(frozen=True)
class NewNode:
    robot_id: str
    index: int
    delta: FloatArray | None  # T_prev_node; None for index 0
    covariance: FloatArray | None
    constraints: list[Constraint] = field(default_factory=list)  # available from now on


@dataclass(frozen=True)
class Feed:
    """A multi-robot graph in arrival order."""

    starts: dict[str, FloatArray | None]  # robot id -> known T_map_first (None: floating)
    nodes: list[NewNode]  # time order; one iSAM2 update each


@dataclass(frozen=True)
class FeedResult:
    graph: PoseGraph
    update_ms: FloatArray  # per new node: update() + correction query
    solve_ms: FloatArray  # per new node: iSAM2 update() calls only
    update_cpu_ms: FloatArray  # per new node: update_ms as CPU time of this thread
    batch_reorders: int  # updates in which iSAM2 re-ordered the whole tree


def reference_poses(data: G2oGraph, n_nodes: int) -> FloatArray:
    """(n, 3) batch-LM solution of the first n vertices as one chain, from the file's vertices."""
    edges = [e for e in data.edges_se2 if max(e.i, e.j) < n_nodes]
    odometry = {e.j: k for k, e in reversed(list(enumerate(edges))) if e.j == e.i + 1}
    graph = PoseGraph()
    graph.add_robot("ref", data.vertices_se2[0])
    graph.add_node("ref", 0, None, None)
    for j in range(1, n_nodes):
        e = edges[odometry[j]]  # the first i -> i+1 edge, as in split_g2o
        graph.add_node("ref", j, e.measurement, np.linalg.inv(e.information), data.vertices_se2[j])
    used = set(odometry.values())
    for k, e in enumerate(edges):
        if k not in used:
            cov = np.linalg.inv(e.information)
            graph.add_constraint(("ref", e.i), ("ref", e.j), e.measurement, cov, robust=None)
    graph.update()
    return batch_optimize(graph, start="guess").poses["ref"]


def split_g2o(
    data: G2oGraph,
    n_nodes: int,
    robots: Sequence[str] = ROBOTS,
    known_starts: bool = True,
) -> Feed:
    """The first ``n_nodes`` vertices of a g2o graph as consecutive chains, one per
    robot (see the module doc). ``known_starts=False``: only the first robot starts
    at the file's first vertex, the others float until an edge links them."""
    if not 3 * len(robots) <= n_nodes <= len(data.vertices_se2):
        raise CollabSlamError(f"need {3 * len(robots)}..{len(data.vertices_se2)} nodes")
    bounds = np.linspace(0, n_nodes, len(robots) + 1).astype(int)
    owner = np.searchsorted(bounds, np.arange(n_nodes), side="right") - 1
    node_of = [(robots[owner[v]], int(v - bounds[owner[v]])) for v in range(n_nodes)]
    arrival = {v: (node_of[v][1], owner[v]) for v in range(n_nodes)}  # (step, robot)
    odometry: dict[int, tuple[FloatArray, FloatArray]] = {}
    ready: dict[int, list[Constraint]] = {}  # vertex -> constraints available with it
    for e in data.edges_se2:
        if max(e.i, e.j) >= n_nodes:
            continue
        cov = np.linalg.inv(e.information)
        if e.j == e.i + 1 and owner[e.i] == owner[e.j] and e.j not in odometry:
            odometry[e.j] = (e.measurement, cov)
            continue
        last = max(e.i, e.j, key=lambda v: arrival[v])
        ready.setdefault(last, []).append(
            Constraint(node_of[e.i], node_of[e.j], e.measurement, cov)
        )
    missing = [v for v in range(n_nodes) if node_of[v][1] > 0 and v not in odometry]
    if missing:
        raise CollabSlamError(f"no odometry edge into vertices {missing[:5]}")
    starts: dict[str, FloatArray | None]
    if known_starts:
        ref = reference_poses(data, n_nodes)
        starts = {r: ref[bounds[k]] for k, r in enumerate(robots)}
    else:
        starts = {r: data.vertices_se2[0] if k == 0 else None for k, r in enumerate(robots)}
    nodes = []
    for v in sorted(range(n_nodes), key=lambda v: arrival[v]):
        robot_id, index = node_of[v]
        delta, cov = odometry[v] if index else (None, None)
        nodes.append(NewNode(robot_id, index, delta, cov, ready.get(v, [])))
    return Feed(starts, nodes)


def new_pose_graph(
    cfg: Config,
    track_changes: bool | None = None,
    reduce_distance_m: float = 0.0,
    reduce_after_nodes: int = 0,
) -> PoseGraph:
    """A PoseGraph set up as BaseStationNode sets up its own (``track_changes`` None: the
    base station's setting), except that every node stays a variable
    (``reduce_distance_m`` 0: batch and iSAM2 are compared on the file's whole graph) or,
    with ``reduce_distance_m`` > 0, that the reduction runs from ``reduce_after_nodes``
    nodes on (0: from the first node)."""
    b = dataclasses.replace(
        cfg.basestation,
        reduce_distance_m=reduce_distance_m,
        reduce_after_nodes=reduce_after_nodes,
    )
    return PoseGraph.from_config(b, track_changes)


def feed_pose_graph(
    cfg: Config,
    feed: Feed,
    track_changes: bool | None = None,
    reduce_distance_m: float = 0.0,
    reduce_after_nodes: int = 0,
) -> FeedResult:
    """Feed node by node, one update each, timing update() and the correction query
    (``track_changes`` None: the base station's setting; ``reduce_*``: see
    ``new_pose_graph``)."""
    graph = new_pose_graph(cfg, track_changes, reduce_distance_m, reduce_after_nodes)
    for robot_id, start in feed.starts.items():
        graph.add_robot(robot_id, start)
    update_ms, solve_ms, cpu_ms, reorders = [], [], [], 0
    for node in feed.nodes:
        graph.add_node(node.robot_id, node.index, node.delta, node.covariance)
        for c in node.constraints:
            graph.add_constraint(c.key_a, c.key_b, c.T_a_b, c.covariance, robust=None)
        c0, t0 = time.thread_time(), time.perf_counter()
        stats = graph.update()
        for robot_id in graph.robots():  # as BaseStationNode.publish_corrections
            latest = graph.latest_index(robot_id)
            if latest is not None:
                graph.pose(robot_id, latest)
        update_ms.append((time.perf_counter() - t0) * 1e3)
        cpu_ms.append((time.thread_time() - c0) * 1e3)
        solve_ms.append(stats.solve_ms)
        reorders += stats.batch_reordered
    return FeedResult(graph, np.array(update_ms), np.array(solve_ms), np.array(cpu_ms), reorders)


def batch_median(graph: PoseGraph, runs: int = BATCH_RUNS) -> tuple[BatchResult, float]:
    """LM ``runs`` times on the same graph from the same guesses: the run with the
    median wall time, and the median CPU time (ms)."""
    results = [batch_optimize(graph, start="guess") for _ in range(runs)]
    cpu_ms = float(np.median([r.cpu_ms for r in results]))
    return sorted(results, key=lambda r: r.wall_ms)[len(results) // 2], cpu_ms


def dead_reckoning(feed: Feed) -> dict[str, FloatArray]:
    """Each robot's start composed with its odometry deltas: (N, 3) per robot."""
    poses: dict[str, list[FloatArray]] = {r: [] for r in feed.starts}
    for node in feed.nodes:
        chain = poses[node.robot_id]
        chain.append(
            feed.starts[node.robot_id] if not chain else se2_compose(chain[-1], node.delta)
        )
    return {r: np.array(p) for r, p in poses.items()}


def batch_from_odometry(cfg: Config, feed: Feed) -> BatchResult:
    """Batch LM on the same graph, started from dead reckoning instead of iSAM2's guesses."""
    graph = new_pose_graph(cfg, track_changes=False)
    guesses = dead_reckoning(feed)
    for robot_id, start in feed.starts.items():
        graph.add_robot(robot_id, start)
    for node in feed.nodes:
        guess = guesses[node.robot_id][node.index]
        graph.add_node(node.robot_id, node.index, node.delta, node.covariance, guess)
        for c in node.constraints:
            graph.add_constraint(c.key_a, c.key_b, c.T_a_b, c.covariance, robust=None)
    graph.update()
    return batch_optimize(graph, start="guess")


def _ate_rms(poses: dict[str, FloatArray], truth: dict[str, FloatArray]) -> float:
    err = np.concatenate([poses[r][:, :2] - truth[r][:, :2] for r in truth])
    return float(np.sqrt((err**2).sum(axis=1).mean()))


def bench_feed(
    cfg: Config,
    feed: Feed,
    out_file: Path | None = None,
    tracked: bool = True,
    truth: dict[str, FloatArray] | None = None,
) -> dict[str, Any]:
    """Timings and chi2 of iSAM2 (fed node by node) and of batch LM on the same graph.

    ``out_file``: where to save the per-update times (ms, one a line); ``tracked``: also
    time the same feed with ``track_changes=True``; ``truth``: true poses per robot,
    for position errors (m, RMS over all nodes).
    """
    runs = FEED_RUNS if len(feed.nodes) <= FEED_RUNS_MAX_NODES else 1
    feeds = sorted(
        (feed_pose_graph(cfg, feed) for _ in range(runs)),
        key=lambda f: float(np.percentile(f.update_ms, 50)),
    )
    fed = feeds[len(feeds) // 2]
    batch, batch_cpu_ms = batch_median(fed.graph)
    from_odometry = batch_from_odometry(cfg, feed)
    if out_file is not None:
        np.savetxt(
            out_file,
            np.column_stack([fed.update_ms, fed.solve_ms]),
            fmt="%.4f",
            header="update_ms solve_ms (one line per new node)",
        )
    p50 = float(np.percentile(fed.update_ms, 50))
    cpu_p50 = float(np.percentile(fed.update_cpu_ms, 50))
    result: dict[str, Any] = {
        "nodes": len(feed.nodes),
        "feed_runs": runs,
        "constraints": sum(len(n.constraints) for n in feed.nodes),
        **percentiles("isam2_update_ms", fed.update_ms),
        "batch_ms": batch.wall_ms,
        "ratio_batch_over_isam2": batch.wall_ms / p50,
        **percentiles("isam2_update_cpu_ms", fed.update_cpu_ms),
        "batch_cpu_ms": batch_cpu_ms,
        "ratio_batch_over_isam2_cpu": batch_cpu_ms / cpu_p50,
        **percentiles("isam2_solve_ms", fed.solve_ms),
        "batch_reorders": fed.batch_reorders,
        "isam2_total_s": float(fed.update_ms.sum() / 1e3),
        "batch_iterations": batch.iterations,
        "batch_ms_from_odometry": from_odometry.wall_ms,
        "batch_iterations_from_odometry": from_odometry.iterations,
        "chi2_isam2": fed.graph.chi2(),
        "chi2_batch": batch.chi2,
        "chi2_batch_from_odometry": from_odometry.chi2,
    }
    if tracked:
        tracked_fed = feed_pose_graph(cfg, feed, track_changes=True)
        result.update(percentiles("tracked_update_ms", tracked_fed.update_ms))
    if truth is not None:
        estimate = {r: fed.graph.poses(r) for r in truth}
        result["ate_rms_m"] = {
            "odometry": _ate_rms(dead_reckoning(feed), truth),
            "isam2": _ate_rms(estimate, truth),
            "batch": _ate_rms(batch.poses, truth),
        }
    return result


def bench_reduced(
    cfg: Config, data: G2oGraph, n_nodes: int, distances_m: Sequence[float]
) -> list[dict[str, Any]]:
    """The same 3-robot feed with the reduced pose graph on from the first node (one
    entry per ``reduce_distance_m``), then as the base station runs it (its own
    ``reduce_distance_m`` from its ``reduce_after_nodes`` nodes on): update timings, what
    iSAM2 holds, and how far the positions end from batch LM's optimum of the whole
    graph (m, mean and max)."""
    feed = split_g2o(data, n_nodes)
    optimum = reference_poses(data, n_nodes)
    b = cfg.basestation
    settings = [(d, 0) for d in distances_m] + [(b.reduce_distance_m, b.reduce_after_nodes)]
    entries = []
    for distance, after in settings:
        fed = feed_pose_graph(cfg, feed, reduce_distance_m=distance, reduce_after_nodes=after)
        poses = np.concatenate([fed.graph.poses(r) for r in feed.starts])
        off = np.linalg.norm(poses[:, :2] - optimum[:, :2], axis=1)
        stats = fed.graph.reduction_stats()
        entries.append(
            {
                "nodes": n_nodes,
                "reduce_distance_m": distance,
                "reduce_after_nodes": after,
                "variables": stats["variables"],
                "factors": stats["factors"],
                **percentiles("isam2_update_ms", fed.update_ms),
                **percentiles("isam2_update_cpu_ms", fed.update_cpu_ms),
                "offset_from_batch_optimum_m_mean": float(off.mean()),
                "offset_from_batch_optimum_m_max": float(off.max()),
            }
        )
    return entries


# ----- simulated team ---------------------------------------------------------------
HEADINGS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # unit steps for yaw k * pi/2


def _grid_tour(
    rng: np.random.Generator, start: tuple[int, int, int], n: int, grid: int, area: int
) -> FloatArray:
    """(n, 3) true poses of 1 m steps along the lines of a square grid (m, rad)."""
    x, y, h = start
    poses = []
    for _ in range(n):
        poses.append([x, y, h * np.pi / 2])
        if x % grid == 0 and y % grid == 0:  # at a crossing: turn left, right or not
            options = [(h + t) % 4 for t in (0, 1, 3)]
            options = [k for k in options if 0 <= x + grid * HEADINGS[k][0] <= area]
            options = [k for k in options if 0 <= y + grid * HEADINGS[k][1] <= area]
            h = int(rng.choice(options))
        x, y = x + int(HEADINGS[h][0]), y + int(HEADINGS[h][1])
    poses_arr = np.array(poses, dtype=np.float64)
    poses_arr[:, 2] = wrap_angle(poses_arr[:, 2])
    return poses_arr


def simulate_team(
    nodes_per_robot: int = 500,
    seed: int = 0,
    grid_m: int = 4,
    area_m: int = 40,
    odo_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.01),  # m, m, rad per keyframe
    loop_sigmas: tuple[float, float, float] = (0.1, 0.1, 0.02),  # m, m, rad
    loop_probability: float = 0.2,  # per new node that revisits a place
    min_loop_gap: int = 20,  # same-robot loops only to nodes at least this much older
) -> tuple[Feed, dict[str, FloatArray]]:
    """Three robots on a grid of corridors (1 m keyframes), known true starts.

    A new node that revisits a place (same cell as an earlier node of any robot) gets
    one loop closure to a random such node with ``loop_probability``. Returns the feed
    and the true poses per robot.
    """
    rng = np.random.default_rng(seed)
    starts = {"r0": (0, 0, 0), "r1": (area_m, 0, 1), "r2": (0, area_m, 3)}
    truth = {r: _grid_tour(rng, s, nodes_per_robot, grid_m, area_m) for r, s in starts.items()}
    odo_cov, loop_cov = np.diag(np.square(odo_sigmas)), np.diag(np.square(loop_sigmas))
    visited: dict[tuple[int, int], list[tuple[str, int]]] = {}
    nodes = []
    for i in range(nodes_per_robot):
        for r in starts:
            T = truth[r][i]
            delta = None
            if i:
                true_delta = se2_between(truth[r][i - 1], T)
                delta = se2_compose(true_delta, rng.normal(0.0, odo_sigmas))
            cell = (int(round(T[0])), int(round(T[1])))
            earlier = [k for k in visited.get(cell, []) if k[0] != r or k[1] <= i - min_loop_gap]
            constraints = []
            if earlier and rng.random() < loop_probability:
                a = earlier[rng.integers(len(earlier))]
                T_a_b = se2_compose(se2_between(truth[a[0]][a[1]], T), rng.normal(0, loop_sigmas))
                constraints.append(Constraint(a, (r, i), T_a_b, loop_cov))
            visited.setdefault(cell, []).append((r, i))
            nodes.append(NewNode(r, i, delta, odo_cov if i else None, constraints))
    return Feed({r: truth[r][0].copy() for r in starts}, nodes), truth


# ----- entry point --------------------------------------------------------------------
def _g2o_source(n_nodes: int) -> str:
    return "M3500" if n_nodes <= M3500_NODES else "city10000"


def run(
    cfg: Config,
    out_dir: Path,
    data_dir: Path,
    sizes: Sequence[int] = (500, 2000, 10000),
    chi2_max_nodes: int | None = None,  # None: whole graphs; a prefix length for quick tests
    sim_nodes_per_robot: int = 500,
    reduced_distances_m: Sequence[float] = REDUCED_DISTANCES_M,
) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    g2o_dir = data_dir / "g2o"
    graphs: dict[str, G2oGraph] = {}

    def graph(name: str) -> G2oGraph:
        if name not in graphs:
            graphs[name] = read_g2o(g2o_dir / f"{name}.g2o")
        return graphs[name]

    result: dict[str, Any] = {"sizes": [], "chi2": {}}
    for n in sizes:
        name = _g2o_source(n)
        entry = bench_feed(cfg, split_g2o(graph(name), n), out_dir / f"{name}_{n}_update_ms.txt")
        result["sizes"].append({"source": f"{name}.g2o[:{n}]", **entry})
        log.info("%d nodes: %s", n, result["sizes"][-1])
    if reduced_distances_m:
        n = max(sizes)
        result["reduced"] = bench_reduced(cfg, graph(_g2o_source(n)), n, reduced_distances_m)
        log.info("reduced pose graph, %d nodes: %s", n, result["reduced"])
    for name in ("M3500", "intel"):
        data = graph(name)
        n = min(len(data.vertices_se2), chi2_max_nodes or len(data.vertices_se2))
        fed = feed_pose_graph(cfg, split_g2o(data, n), track_changes=False)  # same estimates
        batch = batch_optimize(fed.graph, start="guess")
        result["chi2"][name] = {"nodes": n, "isam2": fed.graph.chi2(), "batch": batch.chi2}
        log.info("chi2 %s: %s", name, result["chi2"][name])
    feed, truth = simulate_team(sim_nodes_per_robot, seed=cfg.sim.seed)
    inter = sum(c.key_a[0] != c.key_b[0] for n in feed.nodes for c in n.constraints)
    result["sim"] = {
        "robots": len(feed.starts),
        "inter_robot_constraints": inter,
        **bench_feed(cfg, feed, out_dir / "sim_update_ms.txt", truth=truth),
    }
    log.info("sim: %s", result["sim"])
    return result
