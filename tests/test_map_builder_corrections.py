"""The global map after corrections: it stays what a fresh drawing at the final poses
gives when a correction moves keyframes past the grid's edge, turns them by less than
`map.pose_moved_rad` with far walls, or when blank scans share a view with good ones;
and poses in a frame with large coordinates draw as sharp as near the origin."""

from __future__ import annotations

import numpy as np

from basestation.map_builder import VIEW_KEEP, MapBuilder
from common.config import MapConfig
from common.map_io import OCCUPIED
from protocol.messages import Scan2D


def _ring(n: int, r: float) -> Scan2D:
    """A round room of radius r around the sensor, n beams."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return Scan2D.from_ranges(float(ang[0]), float(ang[1] - ang[0]), 8.0, np.full(n, r))


def _walls(mb: MapBuilder) -> int:
    return int((mb.gridmap().data == OCCUPIED).sum())


def _wall_cells(mb: MapBuilder) -> set[tuple[int, int]]:
    """The occupied cells, as cell-sized steps in metres (grids sized apart compare)."""
    g = mb.gridmap()
    xy = g.cell_to_world(np.argwhere(g.data == OCCUPIED)[:, ::-1])
    return {(int(x), int(y)) for x, y in np.round(xy / g.resolution)}


def test_keyframes_moved_past_the_grids_edge_keep_their_walls() -> None:
    """The grid only grew for new keyframes: a 20 m shift (a loop closure, a GNSS batch)
    of drawn ones cut their walls at the old edge, for good (0 wall cells of 335)."""
    keys = [("a", i) for i in range(5)]
    scans = [_ring(181, 3.0)] * 5
    poses = np.column_stack([np.linspace(0, 2.4, 5), np.zeros(5), np.zeros(5)])
    mb = MapBuilder(MapConfig())
    mb.update(keys, scans, poses, budget_s=None)
    mb.update(keys, scans, poses + [20.0, 0.0, 0.0], budget_s=None)
    mb.finish()
    ref = MapBuilder(MapConfig())
    ref.update(keys, scans, poses + [20.0, 0.0, 0.0], budget_s=None)
    assert _walls(mb) >= 0.9 * _walls(ref) > 100


def test_blank_scans_do_not_push_a_views_good_ones_out_of_a_redraw() -> None:
    """A redraw keeps the newest VIEW_KEEP keyframes of a view: blank ones (a dropout,
    never drawn) had counted, and a 5 cm correction erased the room they hid."""
    room = _ring(361, 2.0)
    blank = Scan2D.from_ranges(room.angle_min, room.angle_increment, 8.0, np.full(361, np.nan))
    good = [[0.1 + 0.03 * i, 0.1, 0.0] for i in range(4)]
    high = [[0.25 + 0.03 * i, 0.12, 0.0] for i in range(VIEW_KEEP)]
    keys = [("a", i) for i in range(len(good) + len(high))]
    scans = [room] * len(good) + [blank] * len(high)
    poses = np.array(good + high)
    mb = MapBuilder(MapConfig())
    mb.update(keys, scans, poses, budget_s=None)
    before = _walls(mb)
    mb.update(keys, scans, poses + [0.05, 0.0, 0.0], budget_s=None)
    mb.finish()
    assert _walls(mb) > 0.5 * before > 100


def test_a_small_turn_moves_far_walls_and_they_are_redrawn() -> None:
    """A 0.0045 rad turn (under `pose_moved_rad`) moves a wall 50 m away by 0.22 m: it
    had been left where it was. A farthest ray end moved two cells redraws now."""
    ang = np.linspace(-0.3, 0.3, 2001)
    scan = Scan2D.from_ranges(float(ang[0]), float(ang[1] - ang[0]), 60.0, 50.0 / np.cos(ang))
    keys = [("a", i) for i in range(3)]
    poses = np.array([[0.0, 0.0, 0.0], [0.7, 0.0, 0.0], [1.4, 0.0, 0.0]])
    turned = poses + [0.0, 0.0, 0.0045]
    cfg = MapConfig(max_free_range_m=10.0)
    mb = MapBuilder(cfg)
    mb.update(keys, [scan] * 3, poses, budget_s=None)
    mb.update(keys, [scan] * 3, turned, budget_s=None)
    mb.finish()
    ref = MapBuilder(cfg)
    ref.update(keys, [scan] * 3, turned, budget_s=None)
    a, b = _wall_cells(mb), _wall_cells(ref)  # (grids sized apart: compared in metres)
    assert len(b - a) < 0.1 * len(b)


def test_a_map_in_utm_sized_coordinates_is_as_sharp_as_near_the_origin() -> None:
    """Poses kept as float32 round a northing of 5.6e6 m to 0.5 m: walls drawn double
    (964 wall cells against 480 near the origin)."""
    n = 721
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    c, s = np.cos(ang), np.sin(ang)

    def box_scan(x: float, y: float) -> Scan2D:  # a 6 m square room seen from (x, y)
        tx = np.where(c > 0, (3 - x) / np.where(c == 0, 1, c), (-3 - x) / np.where(c == 0, 1, c))
        ty = np.where(s > 0, (3 - y) / np.where(s == 0, 1, s), (-3 - y) / np.where(s == 0, 1, s))
        r = np.minimum(np.abs(tx), np.abs(ty))
        return Scan2D.from_ranges(float(ang[0]), float(ang[1] - ang[0]), 8.0, r)

    rng = np.random.default_rng(0)
    local = np.column_stack([rng.uniform(-1.5, 1.5, 40), rng.uniform(-1.5, 1.5, 40), np.zeros(40)])
    scans = [box_scan(x, y) for x, y, _ in local]
    keys = [("a", i) for i in range(40)]

    def walls(offset: tuple[float, float]) -> int:
        mb = MapBuilder(MapConfig())
        mb.update(keys, scans, local + [offset[0], offset[1], 0.0], budget_s=None)
        return _walls(mb)

    assert walls((512345.0, 5612345.0)) <= 1.3 * walls((0.0, 0.0))


def test_the_beam_angles_kept_are_bounded() -> None:
    """One array of beam angles per scan geometry: a driver whose angle_min jitters made
    one per keyframe, never dropped (~430 MB at 100,000 keyframes of 1081 beams)."""
    from basestation.map_builder import ANGLE_GEOMETRIES_KEPT

    mb = MapBuilder(MapConfig())
    n = 200
    keys = [("a", i) for i in range(n)]
    scans = [Scan2D.from_ranges(-1.0 + 1e-4 * i, 0.01, 8.0, np.full(201, 2.0)) for i in range(n)]
    mb.update(keys, scans, np.zeros((n, 3)), budget_s=None)
    assert len(mb._angles) <= ANGLE_GEOMETRIES_KEPT and _walls(mb) > 0
