"""basestation.visibility: frontiers in sight of a robot's way."""

from __future__ import annotations

import numpy as np

from basestation.visibility import seen_from, unknown_in_view, viewpoints
from common.map_io import GridMap


def _two_rooms() -> GridMap:
    """10 x 6 m, free; a wall at y = 3 from x = 0 to 8 (open at x > 8)."""
    data = np.zeros((120, 200), np.int8)
    data[59:61, :160] = 100
    return GridMap(data, 0.05, (0.0, 0.0, 0.0))


def test_viewpoints_are_spaced_along_the_path_with_its_heading() -> None:
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 0.0], [2.0, 1.0]])
    pts, heading = viewpoints(path, 0.5)
    assert np.allclose(pts[:5], [[0, 0], [0.5, 0], [1, 0], [1.5, 0], [2, 0]])
    assert np.allclose(pts[-1], [2.0, 1.0])
    assert np.allclose(heading[:4], 0.0) and np.allclose(heading[-1], np.pi / 2)
    one, h = viewpoints(np.array([[1.0, 1.0], [1.0, 1.0]]), 0.5)
    assert np.allclose(one, [[1.0, 1.0]]) and len(h) == 1


def test_line_of_sight_range_field_of_view_and_unknown() -> None:
    g = _two_rooms()
    pts, heading = viewpoints(np.array([[1.0, 1.5], [5.0, 1.5]]), 0.5)
    targets = np.array(
        [
            [7.0, 1.0],  # ahead, same room
            [3.0, 4.5],  # behind the wall
            [9.5, 1.5],  # ahead, 4.5 m from the path's end
            [1.0, 5.5],  # other room, far
        ]
    )
    fov = np.radians(270.0)
    assert seen_from(g, pts, heading, targets, 6.0, fov).tolist() == [True, False, True, False]
    assert seen_from(g, pts, heading, targets, 4.0, fov).tolist() == [True, False, False, False]
    # the laser's blind sector: flying east, a target due west of the start is not seen
    west = np.array([[0.2, 1.5]])
    assert not seen_from(g, pts[:1], heading[:1], west, 6.0, fov)[0]
    assert seen_from(g, pts[:1], heading[:1], west, 6.0, np.radians(360.0))[0]
    # unknown cells block the view: nothing is known about what stands in them
    g.data[:, 160:170] = -1
    assert seen_from(g, pts, heading, targets, 6.0, fov).tolist() == [True, False, False, False]


def test_unknown_in_view_is_the_unknown_area_a_look_round_takes_in() -> None:
    data = np.full((200, 200), -1, np.int8)  # 10 x 10 m, the west half known free
    data[:, :100] = 0
    g = GridMap(data, 0.05, (0.0, 0.0, 0.0))
    pts = np.array([[1.5, 5.0], [4.9, 5.0]])  # deep in the known half; at its edge
    deep, edge = unknown_in_view(g, pts, 3.0)
    assert deep == 0.0
    assert abs(edge - 0.5 * np.pi * 9.0) < 0.1 * 0.5 * np.pi * 9.0  # half the disc
    # a wall 0.6 m into the unknown: only the strip before it is taken in
    g.data[:, 110] = 100
    (walled,) = unknown_in_view(g, pts[1:], 3.0)
    assert 0.7 * 0.6 * 6.0 < walled < 0.6 * 6.0  # about 0.6 m x the 6 m chord
    assert unknown_in_view(g, np.zeros((0, 2)), 3.0).shape == (0,)
