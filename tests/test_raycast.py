"""Exact grid ray casting: hand-made corridors with known distances."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.errors import CollabSlamError
from simulation.raycast import block_grid, cast_rays

RES = 0.05


@pytest.fixture
def corridor() -> np.ndarray:
    """200 x 40 cells (10 x 2 m) at origin (0, 0): walls along y = 0 (row 0) and the
    top (row 39), an end wall at column 199, the left end open."""
    occ = np.zeros((40, 200), dtype=bool)
    occ[0, :] = True
    occ[39, :] = True
    occ[:, 199] = True
    return occ


def cast(occ: np.ndarray, pose: list[float], angles: list[float], rmax: float = 30.0) -> np.ndarray:
    return cast_rays(occ, RES, (0.0, 0.0), pose, np.array(angles), rmax)


def test_corridor_exact_distances(corridor: np.ndarray) -> None:
    # Wall faces: x = 9.95 (column 199), y = 1.95 (row 39 bottom), y = 0.05 (row 0 top).
    r = cast(corridor, [1.0, 1.0, 0.0], [0.0, math.pi / 2, -math.pi / 2, math.pi / 4])
    assert r.dtype == np.float32
    np.testing.assert_allclose(r, [8.95, 0.95, 0.95, 0.95 * math.sqrt(2)], atol=1e-5)


def test_sensor_yaw_rotates_beams(corridor: np.ndarray) -> None:
    # Sensor facing +y: beam 0 goes up, beam -pi/2 goes along +x to the end wall.
    r = cast(corridor, [2.0, 0.5, math.pi / 2], [0.0, -math.pi / 2])
    np.testing.assert_allclose(r, [1.45, 7.95], atol=1e-5)


def test_beam_leaving_map_is_inf(corridor: np.ndarray) -> None:
    r = cast(corridor, [1.0, 1.0, 0.0], [math.pi])  # open left end
    assert np.isinf(r[0])


def test_range_max_cuts_hits(corridor: np.ndarray) -> None:
    assert np.isinf(cast(corridor, [1.0, 1.0, 0.0], [0.0], rmax=8.9)[0])
    assert cast(corridor, [1.0, 1.0, 0.0], [0.0], rmax=9.0)[0] == pytest.approx(8.95, abs=1e-5)


def test_sensor_outside_map(corridor: np.ndarray) -> None:
    # 2 m left of the grid, looking along +x down the corridor: hits the end wall.
    assert cast(corridor, [-2.0, 1.0, 0.0], [0.0])[0] == pytest.approx(11.95, abs=1e-5)
    # Looking away from the grid: nothing.
    assert np.isinf(cast(corridor, [-2.0, 1.0, 0.0], [math.pi])[0])
    # Passing beside the grid: nothing.
    assert np.isinf(cast(corridor, [-2.0, 5.0, 0.0], [0.0])[0])


def test_sensor_inside_wall_reads_zero(corridor: np.ndarray) -> None:
    assert cast(corridor, [5.0, 0.02, 0.0], [0.3])[0] == 0.0


def test_axis_aligned_beam_along_cell_boundary() -> None:
    # A beam running exactly along the boundary between two rows still finds the wall.
    occ = np.zeros((10, 10), dtype=bool)
    occ[:, 8] = True
    r = cast(occ, [0.1, 0.25, 0.0], [0.0])
    assert r[0] == pytest.approx(0.3, abs=1e-6)


@pytest.mark.parametrize("size", [1, 3, 8, 16])
def test_block_traversal_matches_plain(size: int) -> None:
    rng = np.random.default_rng(size)
    occ = rng.random((90, 130)) < 0.02
    occ[40:45, 10:100] = True
    blocks = block_grid(occ, size)
    angles = np.linspace(-math.pi, math.pi, 361)
    for _ in range(30):
        pose = [rng.uniform(-1.0, 7.5), rng.uniform(-1.0, 5.5), rng.uniform(-3.2, 3.2)]
        rmax = float(rng.choice([0.3, 2.0, 30.0]))
        a = cast_rays(occ, RES, (0.0, 0.0), pose, angles, rmax)
        b = cast_rays(occ, RES, (0.0, 0.0), pose, angles, rmax, blocks=blocks)
        np.testing.assert_array_equal(a, b)
    assert np.isfinite(a).any()


def test_bad_inputs_raise(corridor: np.ndarray) -> None:
    with pytest.raises(CollabSlamError):
        cast_rays(corridor[0], RES, (0.0, 0.0), [0.0, 0.0, 0.0], [0.0], 10.0)
    with pytest.raises(CollabSlamError):
        cast_rays(corridor, RES, (0.0, 0.0), [0.0, np.nan, 0.0], [0.0], 10.0)
    with pytest.raises(CollabSlamError):
        cast_rays(
            corridor, RES, (0.0, 0.0), [0.0, 0.0, 0.0], [0.0], 10.0, blocks=block_grid(corridor[:5])
        )
