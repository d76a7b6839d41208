"""Where the agent's velocity commands go.

`ZenohVehicle` publishes `VehicleCommand`s (to the simulator or an autopilot
bridge); `NullVehicle` drops them (log replay: nothing to fly), so the agent
has no `if replay:` branches.
"""

from __future__ import annotations

from common.bus import Bus
from protocol import VehicleCommand


class ZenohVehicle:
    def __init__(self, bus: Bus, robot_id: str) -> None:
        self._bus = bus
        self._robot_id = robot_id
        self._key = bus.keys.robot(robot_id, "cmd")

    def command(
        self,
        stamp: float,
        vx: float,
        vy: float,
        vz: float,
        yaw_rate: float,
        keyframes_sent: int = 0,
        state_stamp: float = -1.0,
    ) -> None:
        msg = VehicleCommand(
            self._robot_id, stamp, vx, vy, vz, yaw_rate, keyframes_sent, state_stamp
        )
        self._bus.publish(self._key, msg)


class NullVehicle:
    def command(self, stamp: float, *args: float) -> None:
        """Replayed data: there is no vehicle to command."""
