"""The Zenoh key-expression layout, defined in one place.

    collabslam/<fleet>/robot/<id>/sensor/{scan,odom,imu,altimeter}   simulator/driver -> agent
    collabslam/<fleet>/robot/<id>/sensor/gnss                        simulator/driver -> base
    collabslam/<fleet>/robot/<id>/cmd                                agent -> simulator/autopilot
    collabslam/<fleet>/robot/<id>/keyframe                           agent -> base station
    collabslam/<fleet>/robot/<id>/state                              agent -> anyone
    collabslam/<fleet>/robot/<id>/pose/control                       agent -> controller, anyone
    collabslam/<fleet>/robot/<id>/{ack,correction,goal,path,neighbours}  base station -> agent
    collabslam/<fleet>/robot/<id>/sensor/clock                       simulator -> agent (lockstep)
    collabslam/<fleet>/robot/<id>/clock                              base -> agent (lockstep)
    collabslam/<fleet>/alive/{basestation,agent,sim}/<id>           liveliness tokens
    collabslam/<fleet>/clock/{sim,basestation}                       lock-step handshake

Everything a robot publishes lives under its own `robot/<id>/` prefix, so access
control can allow a robot to write only there.
"""

from __future__ import annotations

import re

from common.errors import ConfigError

PREFIX = "collabslam"
_NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")

SENSOR_TOPICS = ("scan", "odom", "imu", "altimeter", "gnss", "clock")
UPLINK_TOPICS = ("keyframe", "state", "cmd", "pose/control")
DOWNLINK_TOPICS = ("ack", "correction", "goal", "path", "neighbours", "clock")


def _check(kind: str, name: str) -> str:
    if not _NAME.match(name):
        raise ConfigError(f"{kind} {name!r} is invalid: expected 1-32 letters, digits, '_' or '-'")
    return name


class Keys:
    """Key expressions of one fleet."""

    def __init__(self, fleet: str) -> None:
        self.fleet = _check("fleet name", fleet)
        self.root = f"{PREFIX}/{fleet}"

    def robot(self, robot_id: str, topic: str) -> str:
        return f"{self.root}/robot/{_check('robot id', robot_id)}/{topic}"

    def sensor(self, robot_id: str, kind: str) -> str:
        if kind not in SENSOR_TOPICS:
            raise ConfigError(f"unknown sensor topic {kind!r}")
        return self.robot(robot_id, f"sensor/{kind}")

    def all_robots(self, topic: str) -> str:
        """Wildcard over every robot for one topic, e.g. all keyframes."""
        return f"{self.root}/robot/*/{topic}"

    def alive(self, role: str, name: str) -> str:
        return f"{self.root}/alive/{role}/{_check('name', name)}"

    def alive_all(self, role: str = "*") -> str:
        return f"{self.root}/alive/{role}/*"

    def clock(self, sender: str) -> str:
        """The lock-step handshake key of `sender` ("sim" or "basestation")."""
        if sender not in ("sim", "basestation"):
            raise ConfigError(f"unknown clock sender {sender!r}")
        return f"{self.root}/clock/{sender}"

    def robot_id_of(self, key: str) -> str | None:
        """The robot id in a key under this fleet's robot/ space, else None."""
        parts = str(key).split("/")
        if len(parts) >= 5 and "/".join(parts[:2]) == self.root and parts[2] == "robot":
            return parts[3]
        return None
