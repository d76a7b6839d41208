"""What the base station writes of its map at the end: trajectories, grid, picture."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from common.geodesy import GeoOrigin
from common.map_io import GridMap, write_map
from common.picture import render_map_picture
from common.trajectory_io import Trajectory, write_tum


def write_map_outputs(
    out: Path,
    trajectories: dict[str, Trajectory],
    grid: GridMap | None,
    on_map: Callable[[str], bool],
    wgs84_origin: GeoOrigin | None,
) -> None:
    """trajectories/<id>.tum (map frame; a robot not `on_map`, never joined: its own
    floating frame), map.yaml + map.pgm and map.png (the grid with the trajectories of
    the robots on the map); with a WGS84 origin, both say where map is (not a floating
    robot's file: its frame is not that ENU frame)."""
    for rid, traj in trajectories.items():
        geo = wgs84_origin if on_map(rid) else None
        write_tum(out / "trajectories" / f"{rid}.tum", traj, wgs84_origin=geo)
    if grid is None:
        return
    shown = {rid: t for rid, t in trajectories.items() if on_map(rid)}
    grid.wgs84_origin = wgs84_origin
    write_map(grid, out / "map.yaml", "map.pgm")
    render_map_picture(
        out / "map.png",
        grid,
        trajectories={rid: t.positions[:, :2] for rid, t in shown.items()},
        robots={rid: t.poses_se2()[-1] for rid, t in shown.items() if len(t)},
        title=f"collabslam map: {len(shown)} of {len(trajectories)} robots on the map",
    )


__all__ = ["write_map_outputs"]
