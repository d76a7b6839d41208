"""A mission scenario: the world, the robots, their start poses and scripted tours.

Written by `collabslam run` into the output folder and read by the simulator
(where to spawn robots), the agents (which tour to fly) and the base station
(known start poses, the robot roster). JSON, checked on read.

A robot's tour may be given georeferenced, as ``"tour_wgs84": [[lat_deg, lon_deg,
alt_m], ...]`` instead of ``"tour"``: it is converted on read into the world
frame, the ENU frame at the world's ``wgs84_origin`` (its map YAML, or the
scenario's own ``"wgs84_origin": [lat, lon, alt]``). Altitudes are dropped (tours
are flown at the cruise altitude).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.errors import CollabSlamError, FileFormatError
from common.geodesy import GeoOrigin, georeferenced_waypoints
from common.world_files import world_wgs84_origin
from protocol.checks import ROBOT_ID_RE

MAX_COORDINATE_M = 1e6  # m: start poses and tour points (map frame)


@dataclass
class RobotScenario:
    robot_id: str
    start_pose: np.ndarray  # T_map_base at start, [x, y, yaw]
    tour: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (M, 2) map frame


@dataclass
class Scenario:
    world: str  # path of the world's map_server YAML
    robots: list[RobotScenario]
    seed: int = 0
    # the ENU origin of `map` for GNSS (None: the world YAML's, if any); `collabslam run`
    # writes the one its simulator's fixes are made at, so both use the same
    wgs84_origin: GeoOrigin | None = None

    def robot(self, robot_id: str) -> RobotScenario:
        for r in self.robots:
            if r.robot_id == robot_id:
                return r
        raise FileFormatError(
            f"robot {robot_id!r} is not in the scenario "
            f"({', '.join(r.robot_id for r in self.robots)})"
        )

    @property
    def robot_ids(self) -> list[str]:
        return [r.robot_id for r in self.robots]


def write_scenario(path: str | Path, sc: Scenario) -> None:
    doc = {
        "world": sc.world,
        "seed": sc.seed,
        "robots": [
            {
                "id": r.robot_id,
                "start_pose": [float(v) for v in r.start_pose],
                "tour": np.asarray(r.tour, dtype=float).tolist(),
            }
            for r in sc.robots
        ],
    }
    if sc.wgs84_origin is not None:
        doc["wgs84_origin"] = sc.wgs84_origin.as_list()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(doc, indent=1))


def read_scenario(path: str | Path) -> Scenario:
    try:
        doc = json.loads(Path(path).read_text())
        if not isinstance(doc, dict) or not isinstance(doc.get("robots"), list):
            raise ValueError('expected an object with "world" and a list of "robots"')
        robots = []
        origin: GeoOrigin | None = None
        for r in doc["robots"]:
            rid = str(r["id"])
            if not ROBOT_ID_RE.match(rid):
                raise ValueError(f"invalid robot id {rid!r}")
            start = np.asarray(r["start_pose"], dtype=np.float64)
            if "tour_wgs84" in r:
                origin = origin or _origin(doc)
                tour = georeferenced_waypoints(r["tour_wgs84"], origin)[:, :2]
            else:
                tour = np.asarray(r.get("tour", []), dtype=np.float64).reshape(-1, 2)
            if start.shape != (3,) or not np.all(np.isfinite(start)):
                raise ValueError(f"robot {rid}: start_pose must be 3 finite numbers")
            for name, xy in (("start_pose", start[:2]), ("tour", tour)):
                # a tour point of Infinity had made every command NaN
                if not (np.all(np.isfinite(xy)) and np.all(np.abs(xy) <= MAX_COORDINATE_M)):
                    raise ValueError(f"robot {rid}: {name} beyond {MAX_COORDINATE_M:g} m")
            robots.append(RobotScenario(rid, start, tour))
        if len({r.robot_id for r in robots}) != len(robots):
            raise ValueError("duplicate robot ids")
        seed = doc.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**31:
            raise ValueError(f"seed must be an integer in 0..2**31-1, got {seed!r}")
        given = GeoOrigin.from_sequence(doc["wgs84_origin"]) if "wgs84_origin" in doc else None
        return Scenario(str(doc["world"]), robots, seed, given)
    except FileNotFoundError:
        raise FileFormatError(f"scenario file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, not text
        raise FileFormatError(f"{path}: cannot read the scenario: {exc}") from None
    except KeyError as exc:
        raise FileFormatError(f"{path}: invalid scenario: no {exc} given") from None
    except (TypeError, ValueError, json.JSONDecodeError, CollabSlamError, OverflowError) as exc:
        raise FileFormatError(f"{path}: invalid scenario: {exc}") from None
    except RecursionError:  # nested 100,000 deep
        raise FileFormatError(f"{path}: invalid scenario: nested too deep") from None


def _origin(doc: dict) -> GeoOrigin:
    """The ENU origin for georeferenced waypoints: the scenario's, else its world's."""
    if "wgs84_origin" in doc:
        return GeoOrigin.from_sequence(doc["wgs84_origin"])
    origin = world_wgs84_origin(doc["world"])
    if origin is None:
        raise ValueError("tour_wgs84 needs a wgs84_origin (in the scenario or its world YAML)")
    return origin
