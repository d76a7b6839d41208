"""Worlds: shipped files, the procedural generator, clearance queries."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from common.errors import CollabSlamError, ConfigError, FileFormatError
from common.map_io import GridMap, read_map, write_map
from simulation.world import SHIPPED_WORLDS, SHIPPED_WORLDS_DIR, World, resolve_world
from simulation.world_generator import generate_world, main, random_floor, validate_world

# Building size (m) of each shipped world: the free cells' bounding box.
SIZES = {"bshape": (13.5, 20.0), "rooms15": (15.0, 15.0), "floor30x25": (30.0, 25.0)}


def box_room(w_m: float = 4.0, h_m: float = 3.0, res: float = 0.05) -> GridMap:
    """A closed room: free inside, one-cell walls, origin (0, 0)."""
    w, h = round(w_m / res), round(h_m / res)
    data = np.full((h, w), 100, dtype=np.int8)
    data[1:-1, 1:-1] = 0
    return GridMap(data=data, resolution=res, origin=(0.0, 0.0, 0.0))


# ----------------------------------------------------------------------------- resolve


def test_resolve_shipped_names_and_paths(tmp_path: Path) -> None:
    for name in SHIPPED_WORLDS:
        assert resolve_world(name) == SHIPPED_WORLDS_DIR / f"{name}.yaml"
    path = tmp_path / "mine.yaml"
    write_map(box_room(), path)
    assert resolve_world(str(path)) == path


def test_resolve_errors_list_shipped_names(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="bshape.*rooms15.*floor30x25"):
        resolve_world("castle")
    with pytest.raises(ConfigError, match="bshape"):
        resolve_world(str(tmp_path / "missing.yaml"))
    png = tmp_path / "map.txt"
    png.write_text("x")
    with pytest.raises(FileFormatError, match="bshape"):
        resolve_world(str(png))


# ----------------------------------------------------------------------------- shipped


@pytest.mark.parametrize("name", SHIPPED_WORLDS)
def test_shipped_world_shape(name: str) -> None:
    world = World.load(name)
    g = world.grid
    assert g.resolution == pytest.approx(0.05)
    assert (SHIPPED_WORLDS_DIR / f"{name}.pgm").stat().st_size < 400_000
    # Free space is one 4-connected region, passable for a 0.5 m drone everywhere.
    validate_world(g)
    assert ndimage.label(world.free)[1] == 1
    # Size of the building.
    iy, ix = np.nonzero(world.free)
    w_m = (ix.max() - ix.min() + 1) * g.resolution
    h_m = (iy.max() - iy.min() + 1) * g.resolution
    assert (w_m, h_m) == pytest.approx(SIZES[name], abs=1.0)
    # Outside the building is unknown; free space never touches unknown (walls between).
    assert (g.data[0, 0], g.data[-1, -1]) == (-1, -1)
    grown = ndimage.binary_dilation(world.free, structure=np.ones((3, 3), bool))
    assert not np.any(grown & (g.data == -1))
    # Outer walls are 0.15 m thick: every wall cell touching the outside is within 3 cells
    # (chessboard) of free space, and a row through the middle meets exactly 3 wall cells.
    # (Checked on the layout without furniture, which may stand against a wall.)
    bare = generate_world(name, furniture_per_room=0.0)
    cells_to_free = ndimage.distance_transform_cdt(~bare.free_mask(), metric="chessboard")
    outside = ndimage.binary_dilation(bare.data == -1, structure=np.ones((3, 3), bool))
    assert cells_to_free[bare.occupied_mask() & outside].max() == 3
    row = g.data[g.height // 2]
    first_wall = int(np.argmax(row == 100))
    assert np.all(row[:first_wall] == -1)
    assert row[first_wall : first_wall + 4].tolist() == [100, 100, 100, 0]


@pytest.mark.parametrize("name", SHIPPED_WORLDS)
def test_shipped_files_match_generator(name: str) -> None:
    shipped = read_map(SHIPPED_WORLDS_DIR / f"{name}.yaml")
    fresh = generate_world(name, seed=0)
    assert shipped.origin == fresh.origin
    np.testing.assert_array_equal(shipped.data, fresh.data)


def test_cli_writes_worlds(tmp_path: Path) -> None:
    assert main(["--out", str(tmp_path), "--kinds", "rooms15"]) == 0
    grid = read_map(tmp_path / "rooms15.yaml")
    np.testing.assert_array_equal(grid.data, generate_world("rooms15").data)
    assert main(["--out", str(tmp_path), "--kinds", "castle"]) == 1


def test_unknown_kind_raises() -> None:
    with pytest.raises(ConfigError, match="bshape"):
        generate_world("castle")


# ----------------------------------------------------------------------------- random


@pytest.mark.parametrize(
    ("seed", "size"), [(11, (20.0, 15.0)), (12, (30.0, 20.0)), (13, (12.0, 12.0))]
)
def test_random_floor_valid(seed: int, size: tuple[float, float]) -> None:
    a = random_floor(seed, *size)
    validate_world(a)
    free_m2 = np.count_nonzero(a.free_mask()) * a.resolution**2
    assert 0.3 * size[0] * size[1] < free_m2 <= size[0] * size[1]
    # Several rooms: partition walls exist inside the building.
    assert np.count_nonzero(a.occupied_mask()) * a.resolution > 2 * (size[0] + size[1])


def test_random_floor_deterministic_per_seed() -> None:
    a = random_floor(5, 16.0, 12.0)
    np.testing.assert_array_equal(a.data, random_floor(5, 16.0, 12.0).data)
    assert not np.array_equal(a.data, random_floor(6, 16.0, 12.0).data)
    np.testing.assert_array_equal(
        a.data, generate_world("random", 5, width_m=16.0, height_m=12.0).data
    )


def test_random_floor_rejects_tiny_size() -> None:
    with pytest.raises(ConfigError):
        random_floor(0, 3.0, 20.0)


def test_validate_world_rejects_split_and_narrow_door() -> None:
    g = box_room(6.0, 3.0)
    g.data[:, 60] = 100  # a full wall splits the room
    with pytest.raises(CollabSlamError, match="2 free regions"):
        validate_world(g)
    g.data[25:33, 60] = 0  # a 0.4 m door: connected, but too narrow for the drone
    with pytest.raises(CollabSlamError, match="passable"):
        validate_world(g)
    g.data[10:40, 60] = 0  # 1.5 m door
    validate_world(g)


# ----------------------------------------------------------------------------- World


def test_clearance_and_is_free() -> None:
    world = World(box_room(4.0, 3.0))
    # Wall faces at x = 0.05, x = 3.95, y = 0.05, y = 2.95.
    xy = np.array([[1.0, 1.5], [1.6, 1.2], [0.32, 1.5], [2.0, 0.2], [0.02, 1.0], [-1.0, 1.0]])
    np.testing.assert_allclose(world.clearance(xy), [0.95, 1.15, 0.27, 0.15, 0.0, 0.0], atol=1e-9)
    # On the medial axis (equidistant from two walls) clearance is still exact; the
    # interpolated planning field is conservative by at most half a cell there.
    corridor = World(box_room(4.0, 1.1))  # wall faces at y = 0.05 and y = 1.05
    centre = np.array([[2.0, 0.55]])
    assert corridor.clearance(centre)[0] == pytest.approx(0.5)
    assert 0.5 - 0.5 * 0.05 - 1e-9 <= corridor.free_clearance(centre)[0] <= 0.5
    assert world.is_free(xy, 0.25).tolist() == [True, True, True, False, False, False]
    assert world.is_free(xy).tolist() == [True, True, True, True, False, False]
    np.testing.assert_allclose(world.free_clearance(xy[:2]), world.clearance(xy[:2]))
    with pytest.raises(ConfigError):
        world.is_free(xy, -1.0)


def test_clearance_exact_at_outside_corners() -> None:
    g = box_room(6.0, 6.0)
    g.data[60:64, 60:64] = 100  # pillar: x, y in [3.0, 3.2]
    world = World(g)
    rng = np.random.default_rng(0)
    ang = rng.uniform(-np.pi, -np.pi / 2, 50)  # all around the lower-left corner
    r = rng.uniform(0.01, 0.5, 50)
    xy = np.array([3.0, 3.0]) + r[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    np.testing.assert_allclose(world.clearance(xy), r, atol=1e-9)
    far = np.array([[1.3, 1.2]])  # beyond the exact range: interpolated, within half a cell
    assert world.clearance(far)[0] == pytest.approx(1.15, abs=0.025)


def test_free_clearance_sees_unknown_but_clearance_does_not() -> None:
    g = box_room(4.0, 3.0)
    g.data[1:-1, 1:20] = -1  # unknown strip on the left (x < 1.0)
    world = World(g)
    p = np.array([[1.3, 1.4]])
    assert world.clearance(p)[0] == pytest.approx(1.25)
    assert world.free_clearance(p)[0] == pytest.approx(0.3)


def test_area_and_bounds() -> None:
    world = World(box_room(4.0, 3.0))
    assert world.free_area_m2 == pytest.approx(3.9 * 2.9)
    assert world.bounds == pytest.approx((0.0, 0.0, 4.0, 3.0))
    assert world.occupied.shape == world.free.shape == (60, 80)
