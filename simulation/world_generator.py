"""Procedural floor plans for the simulator, and the shipped worlds.

A plan is drawn in "building metres" (x right, y up, the building's lower-left
corner at (0, 0)) as a union of FREE shapes: rectangles and thick polylines.
Walls are then everything within `wall_m` of free space that is not free, so
two free rectangles left `partition_m` apart get a partition wall between them,
and a small free rectangle across that gap is a door. What lies further away
(outside the building, solid blocks inside it) stays UNKNOWN (-1), like a
prior floor plan. Solid boxes (pillars, furniture) are occupied cells inside
free space. The grid origin puts building (0, 0) at map (0, 0).

Shipped worlds (seed 002 experiments): `bshape` (Fig. 8), `rooms15` (Fig. 10),
`floor30x25` (Fig. 9). `random_floor` (`simulation/random_floor.py`) makes
rooms-and-corridors floors that no test has seen; the plan, rasterization and
validation live in `simulation/floor_plan.py`. Every generated world passes
`validate_world`: one 4-connected free region, and one region for the centre of a
drone of radius 0.25 m with a 0.1 m margin.

CLI: `python -m simulation.world_generator --out simulation/worlds` rewrites the
shipped worlds.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from common.errors import CollabSlamError, ConfigError
from common.geodesy import GeoOrigin
from common.logging_setup import setup_logging
from common.map_io import GridMap, write_map
from simulation.floor_plan import (
    RESOLUTION_M,
    SHIPPED_KINDS,
    Plan,
    furnish,
    rasterize,
    validate_world,
)
from simulation.random_floor import random_floor

logger = logging.getLogger(__name__)

__all__ = [
    "SHIPPED_KINDS",
    "generate_world",
    "random_floor",
    "validate_world",
    "main",
]


def _bshape_plan() -> Plan:
    """Seed 002 Fig. 8: an upright letter B, 13.5 x 20 m, 2.5 m corridors looping around
    two solid blocks; the spine and the middle bar are shared by both loops."""
    p = Plan(13.5, 20.0)
    p.free_rects += [
        (0.0, 0.0, 2.5, 20.0),  # spine
        (0.0, 17.5, 9.0, 20.0),  # top bar
        (0.0, 8.75, 10.0, 11.25),  # middle bar
        (0.0, 0.0, 9.5, 2.5),  # bottom bar
    ]
    upper = [(8.0, 18.75), (9.5, 18.75), (11.25, 17.0), (11.25, 12.75), (9.5, 10.0), (8.0, 10.0)]
    lower = [(8.0, 10.0), (10.5, 10.0), (12.25, 8.25), (12.25, 3.0), (10.5, 1.25), (8.0, 1.25)]
    p.polylines += [(np.array(upper), 2.5), (np.array(lower), 2.5)]
    # Shallow alcoves (1 m wide, 0.5 m deep) break the symmetry of the long corridors.
    p.free_rects += [(-0.5, 4.0, 0.0, 5.0), (-0.5, 14.0, 0.0, 15.0), (5.0, 20.0, 6.0, 20.5)]
    p.free_rects += [(5.5, -0.5, 6.5, 0.0), (2.5, 13.0, 3.0, 14.2), (6.0, 2.5, 7.0, 3.0)]
    return p


def _rooms15_plan() -> Plan:
    """Seed 002 Fig. 10: a 15 x 15 m room set, six rooms off a 2 m corridor."""
    p = Plan(15.0, 15.0)
    p.free_rects.append((0.0, 6.5, 15.0, 8.5))  # corridor
    top, bottom = (8.6, 15.0), (0.0, 6.4)
    for x0, x1 in ((0.0, 4.45), (4.55, 9.45), (9.55, 15.0)):
        p.room(x0, top[0], x1, top[1])
    for x0, x1 in ((0.0, 5.95), (6.05, 9.95), (10.05, 15.0)):
        p.room(x0, bottom[0], x1, bottom[1])
    for xc in (2.0, 7.5, 11.0):
        p.door_y(8.5, xc)  # corridor -> top rooms
    for xc in (4.5, 8.3, 13.5):
        p.door_y(6.4, xc)  # corridor -> bottom rooms
    p.door_x(4.45, 13.0)  # top-left <-> top-middle
    p.door_x(9.95, 2.0)  # bottom-middle <-> bottom-right
    return p


def _floor30x25_plan() -> Plan:
    """Seed 002 Fig. 9: a 30 x 25 m office floor: a corridor loop, offices, an open hall
    with pillars and two labs."""
    p = Plan(30.0, 25.0)
    p.free_rects += [
        (0.0, 11.5, 21.0, 13.5),  # main corridor (H)
        (19.0, 0.0, 21.0, 25.0),  # cross corridor (V)
        (0.0, 5.0, 19.0, 7.0),  # lower corridor (L)
        (0.0, 7.0, 2.0, 11.5),  # left connector closing the loop H-V-L
    ]
    # Offices above H: two deep labs and two split offices.
    p.room(0.0, 13.6, 4.65, 25.0)
    p.room(4.75, 13.6, 9.45, 19.2)
    p.room(4.75, 19.3, 9.45, 25.0)
    p.room(9.55, 13.6, 14.2, 19.2)
    p.room(9.55, 19.3, 14.2, 25.0)
    p.room(14.3, 13.6, 18.9, 25.0)
    for xc in (2.3, 7.0, 12.0, 16.5):
        p.door_y(13.5, xc)
    p.door_y(19.2, 6.0)
    p.door_y(19.2, 12.8)
    p.door_x(18.9, 22.0)  # top-right office -> V corridor
    # Offices between L and H (doors alternate).
    p.room(2.1, 7.1, 7.7, 11.4)
    p.room(7.8, 7.1, 13.3, 11.4)
    p.room(13.4, 7.1, 18.9, 11.4)
    p.door_y(11.4, 5.0)
    p.door_y(7.0, 10.5)
    p.door_y(11.4, 16.0)
    p.door_x(7.7, 9.0)
    # Offices below L.
    for i, (x0, x1) in enumerate(((0.0, 4.65), (4.75, 9.45), (9.55, 14.2), (14.3, 18.9))):
        p.room(x0, 0.0, x1, 4.9)
        p.door_y(4.9, (x0 + x1) / 2 + (0.8 if i % 2 else -0.8))
    # Open hall right of V with a wide opening and pillars.
    p.room(21.1, 13.6, 30.0, 25.0)
    p.door_x(21.0, 18.0, width=4.0)
    for px in (24.0, 27.2):
        for py in (16.5, 19.5, 22.5):
            p.solids.append((px - 0.2, py - 0.2, px + 0.2, py + 0.2))
    # Two labs below the hall, each reachable from V, joined by an internal door.
    p.room(21.1, 7.1, 30.0, 13.5)
    p.room(21.1, 0.0, 30.0, 7.0)
    p.door_x(21.0, 10.0)
    p.door_x(21.0, 3.0)
    p.door_y(7.0, 27.0)
    p.door_y(13.5, 28.5)  # lab -> hall
    return p


def _corridor_plan() -> Plan:
    """A plain corridor, 88 x 3 m, walls only: where local SLAM has nothing to go by along
    the way (`collabslam bench local-slam`'s corridor run; not a shipped world)."""
    p = Plan(88.0, 3.0)
    p.free_rects.append((0.0, 0.0, 88.0, 3.0))
    return p


def generate_world(
    kind: str,
    seed: int = 0,
    *,
    resolution: float = RESOLUTION_M,
    width_m: float = 24.0,
    height_m: float = 18.0,
    furniture_per_room: float = 0.7,
) -> GridMap:
    """A world of `kind` ('bshape', 'rooms15', 'floor30x25', 'corridor' or 'random'),
    deterministic per seed. For the shipped kinds the layout is fixed and the seed only
    places furniture (bshape and corridor have none); width_m and height_m are used by
    'random' only."""
    if not (resolution > 0.0 and math.isfinite(resolution)):
        raise ConfigError(f"resolution must be > 0, got {resolution}")
    if kind == "random":
        grid = random_floor(
            seed, width_m, height_m, resolution=resolution, furniture_per_room=furniture_per_room
        )
        grid.wgs84_origin = WGS84_ORIGINS["bshape"]
        return grid
    plans = {
        "bshape": _bshape_plan,
        "rooms15": _rooms15_plan,
        "floor30x25": _floor30x25_plan,
        "corridor": _corridor_plan,
    }
    if kind not in plans:
        raise ConfigError(f"unknown world kind {kind!r}; expected one of {[*plans, 'random']}")
    plan = plans[kind]()
    if plan.rooms and furniture_per_room > 0.0:
        furnish(plan, np.random.default_rng(seed), furniture_per_room, resolution)
    grid = rasterize(plan, resolution)
    validate_world(grid)
    grid.wgs84_origin = WGS84_ORIGINS.get(kind, WGS84_ORIGINS["bshape"])
    return grid


# Every shipped world is georeferenced: the WGS84 point at its map (0, 0, 0) (ENU origin).
# Spread over Zagreb's Borongaj campus, seed 000's test site; random worlds get the first.
WGS84_ORIGINS = {
    "bshape": GeoOrigin(45.8118, 16.0106, 160.0),
    "rooms15": GeoOrigin(45.8125, 16.0120, 160.0),
    "floor30x25": GeoOrigin(45.8110, 16.0095, 160.0),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Regenerate the shipped worlds (map_server YAML + PGM) into --out."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--kinds", nargs="+", default=list(SHIPPED_KINDS), help="worlds to write")
    parser.add_argument("--seed", type=int, default=0, help="furniture / random-floor seed")
    args = parser.parse_args(argv)
    setup_logging("INFO", "world_generator")
    try:
        for kind in args.kinds:
            grid = generate_world(kind, args.seed)
            name = kind if kind != "random" else f"random_{args.seed}"
            write_map(grid, args.out / f"{name}.yaml")
            free_m2 = np.count_nonzero(grid.free_mask()) * grid.resolution**2
            logger.info(
                "wrote %s: %d x %d cells (%.1f x %.1f m), %.0f m^2 free",
                args.out / f"{name}.yaml",
                grid.width,
                grid.height,
                grid.width * grid.resolution,
                grid.height * grid.resolution,
                free_m2,
            )
    except CollabSlamError as exc:
        logger.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
