"""Keeps the drone's velocity command clear of what its laser sees right now.

The base station plans on a global map that lags the robot (and treats unknown
space as free), so the agent must never rely on the path alone: before each
command goes out, `SafetyGuard.limit` caps the speed along the commanded
direction so that the drone can stop (at `max_accel`) before any scan point
within its `radius_m + margin_m` corridor, and removes the velocity component
toward a point already closer than that. A drone held still for longer than
`blocked_after_s` is reported `blocked` so the base station replans.

The vehicle follows its command with a lag, so in a turn it still moves the way it
was going. Given its current velocity (`limit(..., velocity=)`, the odometry's
twist), the guard also caps the command along that motion at the speed the scan
allows there; when the drone already moves faster than that, the rest of the
command (the turn) is scaled down by allowed / actual speed: turning while braking
shares the vehicle's acceleration between the two, so the faster it is for what
lies ahead, the more of it goes to braking. (Braking alone, with no turn until
slow, left a drone on a scripted tour short of its corner, nose to the wall, held
for good.)

The other drones are kept apart too (`set_neighbours`): their centres, from the
base station's `Neighbours` relay (`neighbours_in_body`), must stay
`neighbour_keep_m` away. Toward each, the drone flies at most the speed from which
it stops within half the gap (the other brakes in its half; a neighbour moves, so
the whole line between them counts, not only what lies ahead). The lasers do not
see the other drones reliably (a thin frame at the laser's height) and the base
station plans once a second: this is the net under its plans (a leader that stopped,
a plan that came late). The agent turns it off on scripted tours unless told
otherwise (`agent.neighbour_guard_tours`): they are not deconflicted.

Last, the guard checks the command against the vehicle's own response (`velocity_lag_s`:
its velocity follows the command through a first-order lag, the acceleration capped
at `max_accel`, as `simulation/quadrotor.py` models it): the command held for
`HOLD_S`, then a stop, predicted from the current velocity, must keep the disc
`margin_m` clear of every scan point (or, already closer, no closer than now). If not,
the command is scaled down to the largest fraction that does. The corridor checks
above look straight along the command and along the motion; in a turn the motion
sweeps between the two, and a drone turning at speed round the end of a thin wall
came within 1 cm of it (`tests/test_safety_guard.py`).

All in the body frame of the latest scan (x forward, y left; the laser at the
origin), metres and seconds; the vehicle's own limits still apply after this.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from common.geometry import pose4_compose, pose4_inverse
from common.stamps import due

if TYPE_CHECKING:
    from common.config import AgentConfig

GIVE_WAY_MPS = 0.3  # m/s aside when a neighbour is in the way
REPEL_GAIN = 1.0  # m/s away from a neighbour per m inside the keep distance
DEAD_AHEAD = np.sin(np.radians(10.0))  # a neighbour within 10 deg of the way: pass right
# Slower than this (m/s), a drone turns in full while it brakes: the lag's exponential
# decay would hold its turn back for a second more, for the last centimetre.
TURN_WHILE_BRAKING_MPS = 0.1
HOLD_S = 0.1  # s the command is held in the prediction before the stop (latency, a tick)
HOLD_STEPS = 4  # integration steps over HOLD_S
SCALES = np.linspace(1.0, 0.0, 11)  # fractions of the command tried when it is not safe
SLACK_M = 0.01  # m of predicted clearance given up for more of the command, if none is safe


class SafetyGuard:
    def __init__(
        self,
        radius_m: float,
        margin_m: float,
        max_accel: float,
        reaction_s: float,
        blocked_after_s: float,
        horizon_m: float = 4.0,
        neighbour_keep_m: float = 1.3,
        velocity_lag_s: float = 0.2,
    ) -> None:
        self.corridor = radius_m + margin_m  # half-width swept by the drone, m
        self.stop_margin = margin_m  # m left between the disc and a point when stopped
        self.max_accel = max_accel
        self.reaction_s = reaction_s
        self.blocked_after_s = blocked_after_s
        self.horizon = horizon_m
        self.velocity_lag = velocity_lag_s
        self.points: NDArray[np.float64] = np.zeros((0, 2))
        self._range: NDArray[np.float64] = np.zeros(0)  # of each point, m
        self.predicted_ticks = 0  # commands the predicted response scaled down
        self.neighbour_keep = neighbour_keep_m  # m between drone centres
        self.neighbours: NDArray[np.float64] = np.zeros((0, 2))  # their centres
        self.neighbour_ticks = 0  # commands the neighbours limited
        self._held_since: float | None = None
        self.blocked = False
        self.limited_ticks = 0

    @classmethod
    def from_config(cls, a: AgentConfig, exploring: bool) -> SafetyGuard:
        """The agent's guard (`agent.*`); scripted tours (not `exploring`) are not
        deconflicted, so drones meeting in a corridor would hold each other for good
        (docs/architecture.md, neighbour guard): no neighbours kept off there, unless
        `agent.neighbour_guard_tours`."""
        keep = a.neighbour_keep_m if exploring or a.neighbour_guard_tours else 0.0
        return cls(a.vehicle_radius_m, a.safety_margin_m, a.max_accel_mps2,
                   a.safety_reaction_s, a.blocked_after_s, neighbour_keep_m=keep,
                   velocity_lag_s=a.velocity_lag_s)  # fmt: skip

    def stats(self) -> dict[str, int]:
        return {
            "guard_limited_ticks": self.limited_ticks,
            "guard_predicted_ticks": self.predicted_ticks,
            "guard_neighbour_ticks": self.neighbour_ticks,
        }

    def update(
        self, angles: NDArray[np.float64], ranges: NDArray[np.float64], range_min: float = 0.0
    ) -> None:
        """Take the latest scan (beam angles, rad; ranges, m; NaN/inf, or below the
        laser's `range_min`, = no return: a driver's error codes, the drone's own frame,
        had held it as a wall at 2 cm)."""
        r = np.asarray(ranges, dtype=np.float64)
        keep = np.isfinite(r) & (r >= range_min) & (r < self.horizon)
        a = np.asarray(angles, dtype=np.float64)[keep]
        self.points = np.column_stack([r[keep] * np.cos(a), r[keep] * np.sin(a)])
        self._range = r[keep]

    def set_neighbours(self, centres: NDArray[np.float64]) -> None:
        """The other drones' centres now ((k, 2), body frame)."""
        self.neighbours = np.asarray(centres, dtype=np.float64).reshape(-1, 2)

    def limit(
        self,
        stamp: float,
        vx: float,
        vy: float,
        velocity: NDArray[np.float64] | None = None,
    ) -> tuple[float, float]:
        """The body-frame horizontal command (vx, vy), m/s, made safe for the last scan
        and the neighbours; `velocity`: the drone's body-frame (vx, vy) now, if known."""
        command = np.array([vx, vy], dtype=np.float64)
        wanted = float(np.hypot(vx, vy))
        aside = self._apart_from_neighbours(command, give_way=True)  # may move a hovering
        self.neighbour_ticks += int(not np.array_equal(aside, command))  # drone
        v = self._safe(aside, velocity)
        if wanted > 0.05 and float(np.hypot(*v)) < 0.05:
            # the way aside ran into a wall (random:1: a drone in a doorway, a neighbour
            # 2.3 m ahead, the jamb on the side it gave way to: held for good), so go
            # on without it: the neighbour limits still hold
            straight = self._safe(self._apart_from_neighbours(command), velocity)
            if float(np.hypot(*straight)) > float(np.hypot(*v)):
                v = straight
        limited = float(np.hypot(*v)) < wanted - 1e-6
        self.limited_ticks += int(limited)
        held = wanted > 0.05 and float(np.hypot(*v)) < 0.05
        if not held:
            self._held_since = None
        elif self._held_since is None:
            self._held_since = stamp
        self.blocked = held and due(stamp, self._held_since, self.blocked_after_s)
        return float(v[0]), float(v[1])

    def _safe(
        self, v: NDArray[np.float64], velocity: NDArray[np.float64] | None
    ) -> NDArray[np.float64]:
        """`limit`'s command `v`, already kept apart from the neighbours, made clear of
        the scan, braked along the current motion, and its predicted stop clear too."""
        for _ in range(3):  # a way aside must be clear of the scan, and not toward
            if float(np.hypot(*v)) <= 1e-6:  # another drone: taking motion toward
                break  # one away may add some toward the other (a drone by a wall)
            after = self._apart_from_neighbours(self._clear_of_scan(v))
            done = bool(np.allclose(after, v, atol=1e-3))
            v = after
            if done:
                break
        if velocity is not None:
            moving = np.asarray(velocity, dtype=np.float64)[:2]
            v = self._brake_along_motion(v, moving)
            if np.all(np.isfinite(moving)):
                v = self._stoppable(v, moving)
        return v

    def _stopping_speed(self, room: float) -> float:
        """The highest speed from which the drone stops within `room` (m), one reaction
        time of travel included."""
        a, t = self.max_accel, self.reaction_s
        return float(-a * t + np.sqrt((a * t) ** 2 + 2.0 * a * max(room, 0.0)))

    def _clear_of_scan(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        """No motion toward the nearest scan point if it is within the corridor already,
        and the speed capped so that the disc stops before any point ahead."""
        p = self.points
        if len(p) == 0:
            return v
        dist = np.hypot(p[:, 0], p[:, 1])
        k = int(np.argmin(dist))
        if dist[k] < self.corridor:  # too close already: no motion toward it
            n = p[k] / max(dist[k], 1e-9)
            v = v - max(float(v @ n), 0.0) * n
        speed = float(np.hypot(*v))
        if speed > 1e-6:
            allowed = self._allowed_along(v / speed)
            if allowed < speed:
                v = v * (allowed / speed)
        return v

    def _allowed_along(self, u: NDArray[np.float64]) -> float:
        """The highest speed along unit vector `u` from which the disc stops before the
        nearest scan point ahead (inf when none is ahead)."""
        p = self.points
        along = p @ u
        lateral = np.abs(p @ np.array([-u[1], u[0]]))
        ahead = (along > 0.0) & (lateral < self.corridor)
        if not ahead.any():
            return float("inf")
        # distance the disc can travel before touching the nearest point ahead
        travel = along[ahead] - np.sqrt(self.corridor**2 - lateral[ahead] ** 2)
        return self._stopping_speed(float(travel.min()) - self.stop_margin)

    def _brake_along_motion(
        self, v: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """The command `v` with at most the allowed speed along the current motion, and
        less of its turn when the drone moves faster than that (see the module doc)."""
        speed = float(np.hypot(*velocity))
        if not 1e-3 < speed < np.inf or len(self.points) == 0:  # slow, no scan, not finite
            return v
        u = velocity / speed
        allowed = self._allowed_along(u)
        toward = float(v @ u)
        if toward > allowed:
            v = v - (toward - allowed) * u
        if speed > max(allowed, TURN_WHILE_BRAKING_MPS):  # too fast: brake more, turn less
            along = float(v @ u)
            turn = (v - u * along) * (allowed / speed)  # may have led away from a neighbour
            v = self._apart_from_neighbours(self._clear_of_scan(u * along + turn))
        return v

    def _stoppable(
        self, v: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """`v`, or the largest fraction of it from which the predicted response (held for
        `HOLD_S`, then a stop) keeps clear of the scan (see the module doc)."""
        fastest = max(float(np.hypot(*velocity)), float(np.hypot(*v)))
        if len(self.points) == 0 or fastest < 1e-3:
            return v
        reach = fastest * (HOLD_S + self.velocity_lag) + fastest**2 / (2.0 * self.max_accel)
        near = self.points[self._range < reach + self.corridor]
        if len(near) == 0:
            return v
        need = min(self.corridor, float(self._range.min())) - 1e-3
        if self._clearance(v[None], velocity, near)[0] >= need:
            return v
        tries = SCALES[:, None] * v[None]
        clear = self._clearance(tries, velocity, near)
        ok = clear >= need
        if not ok.any():  # no way to keep the margin now: the most of the command that
            ok = clear >= clear.max() - SLACK_M  # comes within SLACK_M of the best
        self.predicted_ticks += 1
        return tries[int(np.argmax(ok))]

    def _clearance(
        self, commands: NDArray[np.float64], velocity: NDArray[np.float64], points: NDArray
    ) -> NDArray[np.float64]:
        """For each command ((k, 2)), the closest the drone's centre comes to `points` if
        it follows the command for `HOLD_S` from `velocity` and then stops: first-order
        lag of `velocity_lag`, acceleration capped at `max_accel`. A stop is a straight
        line along the velocity (the braking acceleration opposes it): at `max_accel`
        down to `max_accel * lag`, then the lag's exponential tail."""
        dt = HOLD_S / HOLD_STEPS
        a, tau = self.max_accel, max(self.velocity_lag, dt)
        vel = np.repeat(velocity[None], len(commands), axis=0)
        held = np.zeros_like(vel)
        for _ in range(HOLD_STEPS):
            accel = (commands - vel) / tau
            norm = np.hypot(accel[:, 0], accel[:, 1])[:, None]
            new = vel + accel * np.minimum(1.0, a / np.maximum(norm, 1e-12)) * dt
            held += 0.5 * (vel + new) * dt
            vel = new
        speed = np.hypot(vel[:, 0], vel[:, 1])
        slow = a * tau  # below this speed the lag, not the cap, sets the deceleration
        stop = np.where(speed > slow, (speed**2 - slow**2) / (2.0 * a) + slow * tau, speed * tau)
        end = held + vel * (stop / np.maximum(speed, 1e-12))[:, None]
        return np.minimum(
            _to_segments(points, np.zeros_like(held), held), _to_segments(points, held, end)
        )

    def _apart_from_neighbours(
        self, v: NDArray[np.float64], give_way: bool = False
    ) -> NDArray[np.float64]:
        """Toward each neighbour, at most the speed from which the drone stops within
        half the gap left above `neighbour_keep` (the other drone brakes in its half):
        the separation never shrinks faster than both can stop; closer than that (news
        a state period old, a drone slow to follow its command), it moves away at
        `REPEL_GAIN` per m inside, even when hovering. Motion across the line between
        them is kept (the drones slide round each other). With `give_way` (the pass
        before the scan check; the one after it never adds motion), a
        drone held back by a neighbour in its way also moves aside at `GIVE_WAY_MPS`:
        past the side the neighbour leaves free, or to the right if it is dead ahead
        (both drones do, so two meeting head-on pass instead of holding each other
        forever). `neighbour_keep` 0: off."""
        if self.neighbour_keep <= 0.0:
            return v
        wanted = float(np.hypot(*v))
        u = v / max(wanted, 1e-9)  # the way it wants to go
        for p in self.neighbours:
            d = float(np.hypot(*p))
            n = p / max(d, 1e-9)
            gap = d - self.neighbour_keep
            if gap >= 0.0:
                allowed = self._stopping_speed(0.5 * gap)
            elif give_way:  # too close already (late news, a lagging turn): move apart
                allowed = -min(REPEL_GAIN * -gap, GIVE_WAY_MPS)
            else:  # the pass after the scan check only takes away
                allowed = 0.0
            toward = float(v @ n)
            if toward <= allowed:
                continue
            v = v - (toward - allowed) * n
            if give_way and toward > 0.5 * wanted:  # it is in the way, not just near
                side = np.array([n[1], -n[0]])  # right of the line to it
                if u[0] * n[1] - u[1] * n[0] < -DEAD_AHEAD:
                    side = -side  # it lies to the right of the way: pass it on the left
                v = v + max(GIVE_WAY_MPS - float(v @ side), 0.0) * side
        return v

    def clear(self) -> None:
        """A new path: forget being blocked."""
        self._held_since = None
        self.blocked = False


def _to_segments(
    points: NDArray[np.float64], start: NDArray[np.float64], end: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The distance from the nearest of `points` ((p, 2)) to each segment start -> end
    ((k, 2) each): (k,)."""
    d = end - start
    rel = points[None, :, :] - start[:, None, :]  # (k, p, 2)
    length2 = np.maximum(np.einsum("kj,kj->k", d, d), 1e-18)[:, None]
    t = np.clip(np.einsum("kpj,kj->kp", rel, d) / length2, 0.0, 1.0)
    off = rel - t[:, :, None] * d[:, None, :]
    return np.sqrt(np.min(off[..., 0] ** 2 + off[..., 1] ** 2, axis=1))


def neighbours_in_body(
    stamps: NDArray[np.float64],
    xy: NDArray[np.float64],
    velocity: NDArray[np.float64],
    stamp: float,
    pose_map: NDArray[np.float64],
    max_age_s: float,
    max_extrapolation_s: float,
) -> NDArray[np.float64]:
    """Other drones' centres ((k, 2), body frame of a drone at `pose_map` [x, y, z, yaw])
    at time `stamp`: each from its last reported `map` position (at `stamps`) moved on at
    its velocity for up to `max_extrapolation_s`; those older than `max_age_s` left out."""
    age = stamp - np.asarray(stamps, dtype=np.float64)
    ok = age <= max_age_s
    dt = np.clip(age[ok], 0.0, max_extrapolation_s)[:, None]
    at = np.asarray(xy, dtype=np.float64)[ok] + np.asarray(velocity, dtype=np.float64)[ok] * dt
    at4 = np.column_stack([at, np.full(len(at), pose_map[2]), np.zeros(len(at))])
    return pose4_compose(pose4_inverse(pose_map), at4)[:, :2]
