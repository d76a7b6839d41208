"""Keyframes the base station acknowledged, kept on disk for a base station that
has lost them.

A base station acknowledges a keyframe once it is in its database. If that database
is lost (a new laptop, a base station restarted without `--db`), the new base station
has none of the robot's keyframes and says so (an ack of -1,
basestation/keyframe_store.py); the agent then sends what it kept here, and what is
not acknowledged yet, as a new keyframe chain (agent/node.py), so the new base station
maps the mission so far and not only what comes next.

The payloads go to unnamed temporary files (deleted by the operating system when the
process ends); the process holds 8 bytes per keyframe (where it starts in its file).
At most `max_keyframes` are kept, in two files of up to half as many each: when the
newer is full the older is deleted, so the latest `max_keyframes / 2` at least are
always there (2D keyframes of 1081 beams: ~2.8 kB each, 20,000 ~55 MB).
"""

from __future__ import annotations

import os
import tempfile
import weakref
from array import array
from collections.abc import Iterator


class _Segment:
    """Consecutive keyframes' payloads in one temporary file."""

    def __init__(self, first_seq: int) -> None:
        self.first_seq = first_seq
        self.starts = array("q", [0])  # byte offsets: payload i is starts[i]:starts[i + 1]
        self._file = tempfile.TemporaryFile(prefix="collabslam-keyframes-")
        self.close = weakref.finalize(self, self._file.close)

    def __len__(self) -> int:
        return len(self.starts) - 1

    def append(self, payload: bytes) -> None:
        self._file.write(payload)
        self.starts.append(self.starts[-1] + len(payload))

    def payloads(self) -> Iterator[bytes]:
        self._file.flush()
        fd = self._file.fileno()
        for a, b in zip(self.starts[:-1], self.starts[1:], strict=True):
            data = os.pread(fd, b - a, a)
            if len(data) != b - a:
                raise OSError(f"keyframe history: {len(data)} of {b - a} bytes read back")
            yield data


class KeyframeHistory:
    def __init__(self, max_keyframes: int) -> None:
        self.max_keyframes = max_keyframes
        self._segments: list[_Segment] = []  # oldest first, at most two
        self.dropped = 0  # keyframes deleted with an older file

    def add(self, seq: int, payload: bytes) -> None:
        """Keep an acknowledged keyframe (seqs consecutive; a gap starts over)."""
        if self.max_keyframes <= 0:
            return
        seg = self._segments[-1] if self._segments else None
        if seg is not None and seq != seg.first_seq + len(seg):
            self.clear()  # not the chain's next one: what was kept cannot precede it
            seg = None
        if seg is None or len(seg) >= max(1, self.max_keyframes // 2):
            seg = _Segment(seq)
            self._segments.append(seg)
            if len(self._segments) > 2:
                old = self._segments.pop(0)
                self.dropped += len(old)
                old.close()
        seg.append(payload)

    @property
    def first_seq(self) -> int | None:
        """The oldest keyframe kept (None: none is)."""
        return self._segments[0].first_seq if self._segments else None

    def __len__(self) -> int:
        return sum(len(s) for s in self._segments)

    def payloads(self) -> Iterator[bytes]:
        """Every payload kept, oldest first, read back from disk."""
        for seg in list(self._segments):
            yield from seg.payloads()

    def clear(self) -> None:
        """Forget (and delete) every keyframe kept."""
        for seg in self._segments:
            seg.close()
        self._segments = []
