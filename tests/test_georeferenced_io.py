"""Georeferenced I/O: WGS84 origin in map YAML, TUM header, worlds; lat/lon waypoints, goals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from common.errors import FileFormatError, ProtocolError
from common.geodesy import GeoOrigin, geodetic_to_enu, wgs84_pose_to_enu
from common.map_io import GridMap, read_map, read_wgs84_origin, write_map
from common.scenario import read_scenario
from common.trajectory_io import Trajectory, read_tum, write_tum
from protocol import Goal
from protocol.codec import decode, encode
from simulation.world import SHIPPED_WORLDS, World

ORIGIN = GeoOrigin(45.8118, 16.0106, 160.25)


def _grid() -> GridMap:
    data = np.zeros((4, 5), dtype=np.int8)
    data[1, 2] = 100
    return GridMap(data, 0.05, (-1.0, -2.0, 0.0))


def test_map_yaml_round_trips_the_origin(tmp_path: Path) -> None:
    grid = _grid()
    grid.wgs84_origin = ORIGIN
    write_map(grid, tmp_path / "m.yaml")
    assert "wgs84_origin: [45.8118, 16.0106, 160.25]" in (tmp_path / "m.yaml").read_text()
    back = read_map(tmp_path / "m.yaml")
    assert back.wgs84_origin == ORIGIN
    assert read_wgs84_origin(tmp_path / "m.yaml") == ORIGIN
    np.testing.assert_array_equal(back.data, grid.data)


def test_map_without_origin_still_reads(tmp_path: Path) -> None:
    write_map(_grid(), tmp_path / "m.yaml")
    assert "wgs84_origin" not in (tmp_path / "m.yaml").read_text()
    assert read_map(tmp_path / "m.yaml").wgs84_origin is None
    text = (tmp_path / "m.yaml").read_text() + "wgs84_origin: [95.0, 0.0, 0.0]\n"
    (tmp_path / "m.yaml").write_text(text)
    with pytest.raises(FileFormatError, match="wgs84_origin"):
        read_map(tmp_path / "m.yaml")


def test_tum_header_round_trips_the_origin(tmp_path: Path) -> None:
    traj = Trajectory.from_pose4([0.0, 1.0], [[1.0, 2.0, 3.0, 0.1], [2.0, 2.5, 3.0, 0.2]])
    write_tum(tmp_path / "t.tum", traj, wgs84_origin=ORIGIN)
    back = read_tum(tmp_path / "t.tum")
    assert back.wgs84_origin == ORIGIN
    np.testing.assert_allclose(back.positions, traj.positions)
    write_tum(tmp_path / "u.tum", back)  # the trajectory's own origin is kept
    assert read_tum(tmp_path / "u.tum").wgs84_origin == ORIGIN
    write_tum(tmp_path / "plain.tum", traj)
    assert read_tum(tmp_path / "plain.tum").wgs84_origin is None
    (tmp_path / "bad.tum").write_text("# wgs84_origin: 45.0 north\n0 0 0 0 0 0 0 1\n")
    with pytest.raises(FileFormatError, match="wgs84_origin"):
        read_tum(tmp_path / "bad.tum")


def test_every_shipped_world_is_georeferenced() -> None:
    for name in SHIPPED_WORLDS:
        origin = World.load(name).geo_origin
        assert origin is not None and 45.0 < origin.lat_deg < 46.5


def test_scenario_tour_in_wgs84(tmp_path: Path) -> None:
    world = tmp_path / "w.yaml"
    grid = _grid()
    grid.wgs84_origin = ORIGIN
    write_map(grid, world)
    enu = np.array([[3.0, 4.0, 1.0], [10.0, -2.0, 1.0]])
    from common.geodesy import enu_to_geodetic

    lla = enu_to_geodetic(enu, ORIGIN).tolist()
    doc = {
        "world": str(world),
        "robots": [{"id": "r0", "start_pose": [0, 0, 0], "tour_wgs84": lla}],
    }
    (tmp_path / "s.json").write_text(json.dumps(doc))
    sc = read_scenario(tmp_path / "s.json")
    np.testing.assert_allclose(sc.robots[0].tour, enu[:, :2], atol=1e-6)
    write_map(_grid(), world)  # the world loses its origin: the tour cannot be placed
    with pytest.raises(FileFormatError, match="wgs84_origin"):
        read_scenario(tmp_path / "s.json")
    doc["wgs84_origin"] = ORIGIN.as_list()  # unless the scenario names one
    (tmp_path / "s.json").write_text(json.dumps(doc))
    np.testing.assert_allclose(
        read_scenario(tmp_path / "s.json").robots[0].tour, enu[:, :2], atol=1e-6
    )


def test_scenario_tour_in_wgs84_on_a_shipped_world(tmp_path: Path) -> None:
    from common.geodesy import enu_to_geodetic

    origin = World.load("bshape").geo_origin
    enu = np.array([[2.0, 1.0, 1.0], [6.0, 3.0, 1.0]])
    doc = {
        "world": "bshape",  # a shipped world's name, as `collabslam run --world` takes
        "robots": [
            {
                "id": "r0",
                "start_pose": [0, 0, 0],
                "tour_wgs84": enu_to_geodetic(enu, origin).tolist(),
            }
        ],
    }
    (tmp_path / "s.json").write_text(json.dumps(doc))
    np.testing.assert_allclose(
        read_scenario(tmp_path / "s.json").robots[0].tour, enu[:, :2], atol=1e-6
    )
    doc["world"] = "no_such_world"
    (tmp_path / "s.json").write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match="unknown world 'no_such_world'"):
        read_scenario(tmp_path / "s.json")


def test_goal_in_wgs84() -> None:
    lla = [45.8120, 16.0110, 170.0]
    goal = Goal("r0", 1, 0.0, "wgs84", 0, np.array([*lla, 0.0, 0.0, 0.0, 1.0]))
    back = decode(encode(goal))
    assert back.frame == "wgs84"
    pose = wgs84_pose_to_enu(back.pose, ORIGIN)
    np.testing.assert_allclose(pose[:3], geodetic_to_enu(lla, ORIGIN), atol=1e-6)
    np.testing.assert_allclose(pose[3:], [0, 0, 0, 1])
    with pytest.raises(ProtocolError, match="frame"):
        Goal("r0", 1, 0.0, "ecef", 0, np.array([*lla, 0.0, 0.0, 0.0, 1.0])).validate()


def test_the_scenarios_origin_is_the_base_stations_map_origin(
    tmp_path: Path, endpoint: str
) -> None:
    """A scenario's own `wgs84_origin` (its tours_wgs84 are placed there) was dropped on
    reading, and the base station put its GNSS fixes in the ENU frame of the world YAML's
    (or of the first fixes' median): tours and fixes in two frames. And for a world
    without one, `collabslam run`'s simulator made its fixes at `sim.gnss.origin_*`
    while the base station took the median of the first five, ~13 m off (ATE 0.023 ->
    0.063 m): the launcher now writes the simulator's origin into the scenario."""
    from basestation.node import BaseStationNode
    from collabslam.launcher import with_gnss_origin
    from common.bus import Bus
    from common.config import ZenohConfig, load_config
    from common.scenario import RobotScenario, Scenario, write_scenario

    world = tmp_path / "w.yaml"
    write_map(_grid(), world)  # no origin of its own
    cfg = load_config(overrides={"sim.gnss.enabled": True, "basestation.gps.enabled": True})
    plain = Scenario(str(world), [RobotScenario("r0", np.zeros(3))])
    sc = with_gnss_origin(cfg, plain)
    g = cfg.sim.gnss
    assert sc.wgs84_origin == GeoOrigin(g.origin_lat_deg, g.origin_lon_deg, g.origin_alt_m)
    write_scenario(tmp_path / "s.json", sc)
    back = read_scenario(tmp_path / "s.json")
    assert back.wgs84_origin == sc.wgs84_origin
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, back)
        assert node.gnss.origin == sc.wgs84_origin
        node.db.close()
    cfg.sim.gnss.enabled = False  # no simulated fixes: nothing to agree on
    assert with_gnss_origin(cfg, plain).wgs84_origin is None


def test_a_robot_never_on_the_map_has_no_wgs84_header(tmp_path: Path) -> None:
    """A robot that never joined the map is written in its own floating frame: the
    `# wgs84_origin` line had said it was in the map's ENU frame."""
    from basestation.map_outputs import write_map_outputs

    traj = Trajectory.from_pose4([0.0, 1.0], [[1.0, 2.0, 3.0, 0.1], [2.0, 2.5, 3.0, 0.2]])
    write_map_outputs(tmp_path, {"r0": traj, "r1": traj}, None, lambda r: r == "r0", ORIGIN)
    assert read_tum(tmp_path / "trajectories" / "r0.tum").wgs84_origin == ORIGIN
    assert read_tum(tmp_path / "trajectories" / "r1.tum").wgs84_origin is None
