"""Tests for common.picture (PNG map snapshots)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from PIL import Image

from common.errors import CollabSlamError
from common.map_io import GridMap
from common.picture import (
    FRONTIER_COLOUR,
    VIEW_MARGIN_M,
    cropped,
    map_rgb,
    render_map_picture,
    robot_colour,
)


def _grid() -> GridMap:
    data = np.full((500, 600), -1, dtype=np.int8)  # 30 x 25 m at 0.05 m
    data[50:450, 50:550] = 0
    data[50:52, 50:550] = 100
    data[448:450, 50:550] = 100
    data[50:450, 50:52] = 100
    data[50:450, 548:550] = 100
    return GridMap(data=data, resolution=0.05, origin=(-2.5, -2.5, 0.0))


def test_map_colours() -> None:
    grid = GridMap(np.array([[-1, 0, 100]], dtype=np.int8), 1.0, (0.0, 0.0, 0.0))
    rgb = map_rgb(grid)
    assert rgb.shape == (1, 3, 3) and rgb.dtype == np.uint8
    assert 100 < rgb[0, 0, 0] < 250  # unknown grey
    assert rgb[0, 1, 0] == 255 and rgb[0, 2, 0] == 0  # free white, occupied black


def test_render_writes_a_non_trivial_png(tmp_path: Path) -> None:
    t = np.linspace(0.0, 2.0 * np.pi, 50)
    traj = {
        "r0": np.column_stack([5 + 3 * np.cos(t), 5 + 2 * np.sin(t), np.zeros_like(t)]),
        "r1": np.column_stack([15 + 2 * np.cos(t), 12 + 2 * np.sin(t)]),
    }
    out = tmp_path / "pics" / "map.png"
    render_map_picture(
        out,
        _grid(),
        trajectories=traj,
        robots={"r0": np.array([8.0, 5.0, 1.57]), "r1": np.array([17.0, 12.0, -0.5])},
        frontiers=np.array([[20.0, 3.0], [21.0, 3.5]]),
        paths={"r0": np.array([[8.0, 5.0], [12.0, 8.0], [20.0, 3.0]])},
        ground_truth={"r0": traj["r0"] + 0.2},
        title="test",
    )
    assert out.stat().st_size > 20_000
    with Image.open(out) as img:
        assert img.format == "PNG"
        w, h = img.size
        pixels = np.asarray(img.convert("RGB"), dtype=np.int16)
    assert 900 < w < 2000 and 600 < h < 2000  # ~150 dpi, sized for a 30 x 25 m map
    assert pixels.std() > 10.0
    colours = {tuple(c) for c in pixels.reshape(-1, 3)[::97]}
    assert len(colours) > 10  # map greys plus robot colours, not a blank canvas
    assert np.any((pixels[..., 0] < 60) & (pixels[..., 2] > 150))  # r0's blue line drawn


def test_render_map_only_and_bad_input(tmp_path: Path) -> None:
    render_map_picture(tmp_path / "bare.png", _grid())
    assert (tmp_path / "bare.png").stat().st_size > 5_000
    with pytest.raises(CollabSlamError, match="trajectories"):
        render_map_picture(tmp_path / "bad.png", _grid(), trajectories={"r0": np.zeros(5)})


def test_a_large_map_is_drawn_in_blocks_and_its_thin_walls_stay(tmp_path: Path) -> None:
    """A 2,001-cell map is drawn from a raster of at most MAX_RASTER_PX a side (matplotlib
    resamples in float64: the memory is the raster's), the darkest cell of each block:
    a wall one cell thick still crosses the picture from side to side."""
    from common.picture import MAX_RASTER_PX, _raster

    data = np.zeros((2001, 2001), dtype=np.int8)  # 100 x 100 m of free space at 0.05 m
    data[:, 1000] = 100  # a wall one cell thick at x = 50.0-50.05 m
    grid = GridMap(data=data, resolution=0.05, origin=(0.0, 0.0, 0.0))
    raster, extent = _raster(grid)
    assert max(raster.shape[:2]) <= MAX_RASTER_PX and raster.dtype == np.uint8
    assert extent[0] == 0.0 and extent[1] >= 100.05 and extent[3] >= 100.05  # covers it
    dark = np.flatnonzero((raster[..., 0] == 0).all(axis=0))
    assert len(dark) == 1  # one block column, every row of it
    x = extent[0] + (dark[0] + 0.5) * (extent[1] - extent[0]) / raster.shape[1]
    assert abs(x - 50.0) < 0.2
    render_map_picture(tmp_path / "big.png", grid)
    with Image.open(tmp_path / "big.png") as img:
        grey = np.asarray(img.convert("L"), dtype=np.int16)
    rows = grey[grey.shape[0] // 4 : 3 * grey.shape[0] // 4]  # inside the axes
    assert (rows.min(axis=1) < 60).all()  # the wall in every row of the picture


def test_the_picture_shows_the_known_area_and_the_overlays_not_the_whole_grid() -> None:
    grid = _grid()  # known from (0, 0) to (25, 20) m in a 30 x 25 m grid from (-2.5, -2.5)
    c = cropped(grid, [])
    x0, x1, y0, y1 = c.extent
    assert x0 == pytest.approx(-VIEW_MARGIN_M, abs=0.06) and y0 == pytest.approx(-1.0, abs=0.06)
    assert x1 == pytest.approx(25.0 + VIEW_MARGIN_M, abs=0.06)
    assert y1 == pytest.approx(20.0 + VIEW_MARGIN_M, abs=0.06)
    np.testing.assert_array_equal(c.data, grid.data[30:470, 30:570])  # the same cells
    wide = cropped(grid, [np.array([[26.5, 10.0]])])  # a robot out in the unknown
    assert wide.extent[1] == pytest.approx(27.5, abs=0.06)  # the grid's own edge
    assert cropped(GridMap(np.full((10, 10), -1, np.int8), 0.1, (0.0, 0.0, 0.0)), []).extent == (
        0.0,
        1.0,
        0.0,
        1.0,
    )  # nothing known, nothing given: all of it


def test_every_robot_of_a_big_fleet_has_its_own_colour() -> None:
    """8 drones and 3 restarted segments: the 11th had taken the 1st's colour."""
    assert len({robot_colour(i, 11) for i in range(11)}) == 11
    assert len({robot_colour(i, 3) for i in range(3)}) == 3
    rgb = np.array([to_rgb(robot_colour(i, 30)) for i in range(30)])  # none like the
    for other in (FRONTIER_COLOUR, "#7f7f7f"):  # frontiers' orange or the unknown's grey
        assert np.linalg.norm(rgb - to_rgb(other), axis=1).min() > 0.25
