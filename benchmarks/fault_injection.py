"""Hostile traffic for `collabslam bench faults`: bad payloads and replayed keyframes.

- `bad_payloads(n, ...)`: n messages the base station must log and drop, cycling
  through seven kinds: random bytes, a truncated keyframe, a wrong schema version,
  an oversized payload, a NaN stamp, a message of the wrong type on the keyframe
  key, a keyframe whose robot id does not match its key, plus keyframes from a
  robot the roster does not know. Each comes with the key to put it on.
- `Replayer`: listens to the agents' keyframes on its own session and puts a
  fraction of them to the base station again on another one, half at once
  (duplicates) and half 0.2-2 s later (after newer keyframes: out of order). It
  skips robots whose link is cut, so it never carries data around a cut.
"""

from __future__ import annotations

import heapq
import threading
import time
from collections.abc import Callable

import msgpack
import numpy as np

from common.bus import Bus
from common.geometry import pose4_to_pose7
from protocol import SCHEMA_VERSION, Keyframe, KeyframeAck, Keys, Scan2D, encode

BAD_KINDS = (
    "garbage",
    "truncated",
    "wrong_version",
    "oversized",
    "nan",
    "wrong_type",
    "robot_mismatch",
    "unknown_robot",
)


def _keyframe(robot: str, seq: int) -> Keyframe:
    ranges = np.full(181, 3.0)
    return Keyframe(
        robot,
        seq,
        float(seq),
        pose4_to_pose7([0.0, 0.0, 1.0, 0.0]),
        pose4_to_pose7([0.0, 0.0, 0.0, 0.0]),
        np.eye(6) * 1e-4,
        Scan2D.from_ranges(-np.pi / 2, np.pi / 180, 30.0, ranges),
        None,
    )


def bad_payloads(
    n: int, keys: Keys, robots: list[str], max_bytes: int, seed: int = 0
) -> list[tuple[str, bytes, str]]:
    """n (key, payload, kind) triples, every kind in turn (see the module doc)."""
    rng = np.random.default_rng(seed)
    good = encode(_keyframe(robots[0], 10**6))
    env = msgpack.unpackb(good, raw=False)
    out = []
    for i in range(n):
        kind = BAD_KINDS[i % len(BAD_KINDS)]
        robot = robots[i % len(robots)]
        key = keys.robot(robot, "keyframe")
        if kind == "garbage":
            p = b"\xc1" + rng.bytes(int(rng.integers(1, 200)))  # 0xc1: never valid msgpack
        elif kind == "truncated":
            p = good[: int(rng.integers(1, len(good) - 1))]
        elif kind == "wrong_version":
            p = msgpack.packb({**env, "v": SCHEMA_VERSION + 1}, use_bin_type=True)
        elif kind == "oversized":
            p = b"\x00" * (max_bytes + 1)
        elif kind == "nan":
            p = msgpack.packb({**env, "d": dict(env["d"], stamp=float("nan"))}, use_bin_type=True)
        elif kind == "wrong_type":
            p = encode(KeyframeAck(robot, i))
        elif kind == "robot_mismatch":
            p = encode(_keyframe("intruder", i))
        else:
            key, p = keys.robot("intruder", "keyframe"), encode(_keyframe("intruder", i))
        out.append((key, p, kind))
    return out


class Replayer:
    """Re-puts a fraction of the keyframes it hears (see the module doc)."""

    def __init__(
        self,
        listen: Bus,
        send: Bus,
        fraction: float,
        is_cut: Callable[[str], bool],
        seed: int = 0,
    ) -> None:
        self.send = send
        self.fraction = fraction
        self.is_cut = is_cut
        self.rng = np.random.default_rng(seed)
        self.duplicated = 0
        self.reordered = 0
        self._heap: list[tuple[float, int, str, bytes]] = []
        self._n = 0
        self._cond = threading.Condition()
        self._stop = False
        listen.subscribe(listen.keys.all_robots("keyframe"), Keyframe, self._on_keyframe)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on_keyframe(self, kf: Keyframe, key: str) -> None:
        if self.is_cut(kf.robot_id):
            return
        with self._cond:
            u = self.rng.random()
            if u >= self.fraction:
                return
            delay = 0.0 if u < self.fraction / 2 else float(self.rng.uniform(0.2, 2.0))
            if delay:
                self.reordered += 1
            else:
                self.duplicated += 1
            self._n += 1
            heapq.heappush(self._heap, (time.monotonic() + delay, self._n, key, encode(kf)))
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stop and (not self._heap or self._heap[0][0] > time.monotonic()):
                    wait = self._heap[0][0] - time.monotonic() if self._heap else None
                    self._cond.wait(wait)
                if self._stop:
                    return
                _, _, key, payload = heapq.heappop(self._heap)
            self.send.put_raw(key, payload)

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(5.0)
