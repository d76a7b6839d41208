"""WGS84 <-> ENU (pymap3d) round trips and known distances."""

from __future__ import annotations

import numpy as np
import pytest

from common.errors import CollabSlamError
from common.geodesy import GeoOrigin, enu_to_geodetic, geodetic_to_enu, georeferenced_waypoints

ORIGIN = GeoOrigin(45.8118, 16.0106, 160.0)


def test_enu_round_trip() -> None:
    rng = np.random.default_rng(0)
    enu = rng.uniform([-2000, -2000, -50], [2000, 2000, 300], size=(50, 3))
    lla = enu_to_geodetic(enu, ORIGIN)
    np.testing.assert_allclose(geodetic_to_enu(lla, ORIGIN), enu, atol=1e-6)


def test_geodetic_round_trip_and_origin_is_zero() -> None:
    lla = np.array([[45.8120, 16.0110, 170.0], [45.80, 16.02, 150.0]])
    np.testing.assert_allclose(
        enu_to_geodetic(geodetic_to_enu(lla, ORIGIN), ORIGIN), lla, atol=1e-9
    )
    np.testing.assert_allclose(geodetic_to_enu(ORIGIN.as_list(), ORIGIN), 0.0, atol=1e-6)


def test_axes_point_east_north_up() -> None:
    north = geodetic_to_enu([ORIGIN.lat_deg + 1e-3, ORIGIN.lon_deg, ORIGIN.alt_m], ORIGIN)
    east = geodetic_to_enu([ORIGIN.lat_deg, ORIGIN.lon_deg + 1e-3, ORIGIN.alt_m], ORIGIN)
    # 0.001 deg of latitude is ~111 m; of longitude ~111 m * cos(lat)
    assert north[1] == pytest.approx(111.1, abs=0.3) and abs(north[0]) < 1e-6
    assert east[0] == pytest.approx(111.3 * np.cos(np.radians(ORIGIN.lat_deg)), abs=0.3)
    assert abs(east[1]) < 0.01
    up = geodetic_to_enu([ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m + 10.0], ORIGIN)
    np.testing.assert_allclose(up, [0.0, 0.0, 10.0], atol=1e-6)


def test_waypoints_and_bad_input() -> None:
    wps = georeferenced_waypoints([ORIGIN.as_list(), ORIGIN.as_list()], ORIGIN)
    assert wps.shape == (2, 3)
    with pytest.raises(CollabSlamError):
        GeoOrigin(91.0, 0.0, 0.0)
    with pytest.raises(CollabSlamError):
        geodetic_to_enu([0.0, 200.0, 0.0], ORIGIN)
    with pytest.raises(CollabSlamError):
        GeoOrigin.from_sequence([1.0, 2.0])
