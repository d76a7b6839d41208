"""The base station's bounded queue of received keyframes.

Zenoh's callbacks put keyframes here; the base station's thread takes them in
batches. The queue is bounded: a base station that falls behind drops what does not
fit, and its memory does not follow the backlog. Nothing is lost by that: an agent
keeps every keyframe in its outbox until it is acknowledged and sends it again
(agent/outbox.py), and acknowledgements only cover keyframes in the graph.
"""

from __future__ import annotations

import logging
import queue

from protocol import Keyframe

log = logging.getLogger(__name__)

INBOX_MAX_KEYFRAMES = 2000  # received, not yet processed (10 robots x batch_max)


class KeyframeInbox:
    def __init__(self, max_keyframes: int = INBOX_MAX_KEYFRAMES) -> None:
        self._q: queue.Queue[Keyframe] = queue.Queue(maxsize=max_keyframes)
        self.max_keyframes = max_keyframes
        self.drops = 0
        self._highest: dict[str, tuple[int, int]] = {}  # robot -> highest (chain, seq)

    def put(self, kf: Keyframe) -> bool:
        """Queue a keyframe (any thread); False if the inbox was full and it was dropped."""
        try:
            self._q.put_nowait(kf)
            key = (kf.chain, kf.seq)  # (one Zenoh thread)
            self._highest[kf.robot_id] = max(self._highest.get(kf.robot_id, key), key)
            return True
        except queue.Full:
            self.drops += 1
            if self.drops == 1 or self.drops % 1000 == 0:
                log.warning(
                    "inbox full (%d keyframes: the base station is behind); %d dropped so "
                    "far, their agents will send them again",
                    self.max_keyframes,
                    self.drops,
                )
            return False

    def take(self, max_n: int, timeout: float = 0.0) -> list[Keyframe]:
        """Up to `max_n` keyframes, waiting up to `timeout` s for the first one."""
        batch: list[Keyframe] = []
        try:
            batch.append(self._q.get(timeout=timeout) if timeout > 0 else self._q.get_nowait())
            while len(batch) < max_n:
                batch.append(self._q.get_nowait())
        except queue.Empty:
            pass
        return batch

    def highest_seq(self, robot_id: str) -> int:
        """The highest seq of `robot_id`'s latest keyframe chain queued here (-1: none)."""
        return self._highest.get(robot_id, (0, -1))[1]

    def empty(self) -> bool:
        return self._q.empty()

    def __len__(self) -> int:
        return self._q.qsize()
