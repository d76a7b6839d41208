"""What a keyframe carries besides its poses: its planar scan (`Scan2D`), or a 3-D
cloud (`Cloud3D`), and where its odom frame began (`OdomOrigin`). Nested in `Keyframe`
(protocol/messages.py)."""

from __future__ import annotations

import numpy as np

from protocol.codec import array_field, message

# Scan2D.ranges_mm: a reading the laser refused (below its range_min: the drone's own
# frame, a driver's error code; -inf, ROS's "too close"), neither a return nor free
# space. Valid readings stay below 65 m, 65000 mm. A base station from before this takes
# it as 65.535 m: a no return clearing free space (range_max <= 65 m) or a far hit;
# upgrade base stations first (docs/operations.md).
NO_READING_MM = 65535


@message
class Scan2D:
    """A keyframe's planar scan, ranges quantized to millimetres (0 = no return,
    `NO_READING_MM` = no reading)."""

    angle_min: float
    angle_increment: float
    range_max: float
    ranges_mm: np.ndarray = array_field("u2", (None,))

    def ranges(self) -> np.ndarray:
        """Ranges in metres as float32, NaN for no return and for no reading."""
        r = self.ranges_mm.astype(np.float32) * np.float32(1e-3)
        r[(self.ranges_mm == 0) | (self.ranges_mm == NO_READING_MM)] = np.nan
        return r

    def angles(self) -> np.ndarray:
        return (self.angle_min + self.angle_increment * np.arange(self.ranges_mm.size)).astype(
            np.float32
        )

    @staticmethod
    def from_ranges(
        angle_min: float,
        angle_increment: float,
        range_max: float,
        ranges: np.ndarray,
        range_min: float = 0.0,
    ) -> Scan2D:
        """Quantize metres to mm; NaN/+inf/>= range_max/<= 0 become 0 (no return), and
        -inf and finite readings below a positive ``range_min`` `NO_READING_MM`."""
        r = np.asarray(ranges, dtype=np.float64)
        valid = np.isfinite(r) & (r > 0.0) & (r < min(range_max, 65.0)) & (r >= range_min)
        mm = np.zeros(r.shape, dtype=np.uint16)
        mm[valid] = np.clip(np.rint(r[valid] * 1000.0), 1, 65000).astype(np.uint16)
        refused = np.isneginf(r)
        if range_min > 0.0:
            refused |= np.isfinite(r) & (r < range_min)
        mm[refused] = NO_READING_MM
        return Scan2D(float(angle_min), float(angle_increment), float(range_max), mm)


@message
class OdomOrigin:
    """Where an agent's `odom` frame's origin is on its odometry source's frame at a
    keyframe, [x, y, yaw] (m, rad): the source's pose composed with the inverse of the
    local pose (they drift apart as local SLAM corrects the odometry). Two runs of a
    robot's agent in one flight share the source's frame: the base station starts a
    later run's frame where the earlier run's latest puts it (basestation/
    robot_segments.py)."""

    x: float
    y: float
    yaw: float


@message
class Cloud3D:
    """A keyframe's downsampled 3-D cloud in the body frame (m)."""

    points: np.ndarray = array_field("f4", (None, 3))
