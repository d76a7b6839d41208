"""WGS84 geodetic coordinates <-> a local east-north-up (ENU) frame (pymap3d).

With GPS on, the base station's ``map`` frame is an ENU frame whose origin is a
fixed point on (or above) the WGS84 ellipsoid (seed 000 §III): x = east, y = north,
z = up, metres. ``GeoOrigin`` names that point; every world carries one.

Latitudes and longitudes are in degrees, altitudes in metres above the WGS84
ellipsoid (not above mean sea level).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GeoOrigin:
    """The WGS84 point at the ENU (``map``) frame's origin."""

    lat_deg: float  # deg, WGS84 geodetic latitude, [-90, 90]
    lon_deg: float  # deg, WGS84 longitude, [-180, 180]
    alt_m: float  # m above the WGS84 ellipsoid

    def __post_init__(self) -> None:
        values = (self.lat_deg, self.lon_deg, self.alt_m)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise CollabSlamError(f"GeoOrigin: expected 3 finite numbers, got {values}")
        if not -90.0 <= self.lat_deg <= 90.0 or not -180.0 <= self.lon_deg <= 180.0:
            raise CollabSlamError(
                f"GeoOrigin: latitude must be in [-90, 90] and longitude in [-180, 180] deg, "
                f"got {self.lat_deg}, {self.lon_deg}"
            )

    def as_list(self) -> list[float]:
        """[lat_deg, lon_deg, alt_m]."""
        return [float(self.lat_deg), float(self.lon_deg), float(self.alt_m)]

    @classmethod
    def from_sequence(cls, values: ArrayLike) -> GeoOrigin:
        """From [lat_deg, lon_deg, alt_m]."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.shape != (3,):
            raise CollabSlamError(f"GeoOrigin: expected [lat, lon, alt], got {values!r}")
        return cls(float(v[0]), float(v[1]), float(v[2]))


def _lla(lla: ArrayLike) -> FloatArray:
    arr = np.asarray(lla, dtype=np.float64)
    if arr.shape[-1:] != (3,) or not np.all(np.isfinite(arr)):
        raise CollabSlamError(f"expected finite [..., 3] [lat, lon, alt], got shape {arr.shape}")
    if np.any(np.abs(arr[..., 0]) > 90.0) or np.any(np.abs(arr[..., 1]) > 180.0):
        raise CollabSlamError("latitude must be in [-90, 90] and longitude in [-180, 180] deg")
    return arr


def geodetic_to_enu(lla: ArrayLike, origin: GeoOrigin) -> FloatArray:
    """(..., 3) [lat_deg, lon_deg, alt_m] -> (..., 3) [east, north, up] m in ``origin``'s ENU."""
    arr = _lla(lla)
    e, n, u = pymap3d.geodetic2enu(
        arr[..., 0], arr[..., 1], arr[..., 2], origin.lat_deg, origin.lon_deg, origin.alt_m
    )
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=-1).astype(np.float64)


def enu_to_geodetic(enu: ArrayLike, origin: GeoOrigin) -> FloatArray:
    """(..., 3) [east, north, up] m in ``origin``'s ENU -> (..., 3) [lat_deg, lon_deg, alt_m]."""
    arr = np.asarray(enu, dtype=np.float64)
    if arr.shape[-1:] != (3,) or not np.all(np.isfinite(arr)):
        raise CollabSlamError(f"expected finite [..., 3] [east, north, up], got shape {arr.shape}")
    lat, lon, alt = pymap3d.enu2geodetic(
        arr[..., 0], arr[..., 1], arr[..., 2], origin.lat_deg, origin.lon_deg, origin.alt_m
    )
    return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=-1).astype(np.float64)


def wgs84_pose_to_enu(pose7_wgs84: ArrayLike, origin: GeoOrigin) -> FloatArray:
    """[lat_deg, lon_deg, alt_m, qx, qy, qz, qw] (orientation in ENU) -> pose7 in ``map``."""
    p = np.asarray(pose7_wgs84, dtype=np.float64).reshape(-1)
    if p.shape != (7,):
        raise CollabSlamError(f"expected a pose7 [lat, lon, alt, qx, qy, qz, qw], got {p.shape}")
    return np.concatenate([geodetic_to_enu(p[:3], origin), p[3:]])


def georeferenced_waypoints(lla: ArrayLike, origin: GeoOrigin) -> FloatArray:
    """(N, 3) [lat_deg, lon_deg, alt_m] waypoints -> (N, 3) [x, y, z] in the ENU ``map``."""
    return geodetic_to_enu(np.asarray(lla, dtype=np.float64).reshape(-1, 3), origin)
