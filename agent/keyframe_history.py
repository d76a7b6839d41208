"""Every keyframe an agent cut, kept on disk: for a base station that has lost the
acknowledged ones, and, with a state folder, for the agent itself after a restart.

A base station acknowledges a keyframe once it is in its database. If that database
is lost (a new laptop, a base station restarted without `--db`), the new base station
has none of the robot's keyframes and says so (an ack of -1,
basestation/keyframe_store.py); the agent then sends what it kept here as a new
keyframe chain (agent/outbox.py `new_chain`), so the new base station maps the
mission so far and not only what comes next. An agent restarted on its state folder
(`agent.state_dir`, agent/resume.py) finds here the keyframes not acknowledged yet.

Payloads are appended, each after its length, to files of up to `max_keyframes / 2`
keyframes each, named by their first seq: unnamed temporary files (deleted by the
operating system when the process ends), or files in `directory`, written to the disk
itself at each keyframe before it is sent (a killed process loses none, nor a power
cut: a reboot whose files were a few keyframes behind what the base station had
acknowledged re-cut those seqs, and the base station froze the robot out as another
source; ~0.2 ms a keyframe here). When a third file
starts the oldest is deleted (unless it holds keyframes not acknowledged yet), so the
latest `max_keyframes / 2` at least are always there (2D keyframes of 1081 beams:
~2.8 kB each, 20,000 ~55 MB). The process holds 8 bytes per keyframe (where it starts
in its file). A new chain's keyframes replace them whole or not at all (`replace`).
"""

from __future__ import annotations

import logging
import os
import struct
import tempfile
import weakref
from array import array
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

log = logging.getLogger(__name__)

_LEN = struct.Struct("<I")
NEXT = "next-"  # a replacement's files (`KeyframeHistory.replace`) ...
NEXT_DONE = "next-done"  # ... written whole


class _Segment:
    """Consecutive keyframes' payloads in one file."""

    def __init__(self, first_seq: int, file: BinaryIO, path: Path | None = None) -> None:
        self.first_seq = first_seq
        self.path = path
        self.starts = array("q", [0])  # record i is starts[i]:starts[i + 1] (length first)
        self._file = file
        self._close = weakref.finalize(self, file.close)

    @classmethod
    def new(cls, first_seq: int, directory: Path | None, prefix: str = "") -> _Segment:
        if directory is None:
            return cls(first_seq, tempfile.TemporaryFile(prefix="collabslam-keyframes-"))
        path = directory / f"{prefix}keyframes-{first_seq:010d}.log"
        return cls(first_seq, open(path, "w+b"), path)  # noqa: SIM115 (kept open)

    @classmethod
    def load(cls, path: Path) -> _Segment:
        """A file written before (a restart): its records read up to a torn last one."""
        seg = cls(int(path.stem.rsplit("-", 1)[1]), open(path, "r+b"), path)  # noqa: SIM115
        data = path.read_bytes()
        at = 0
        while at + _LEN.size <= len(data):
            end = at + _LEN.size + _LEN.unpack_from(data, at)[0]
            if end > len(data):
                break
            seg.starts.append(end)
            at = end
        if at < len(data):
            log.warning("%s: %d bytes of a keyframe cut short (killed while writing): "
                        "dropped", path, len(data) - at)  # fmt: skip
            seg._file.truncate(at)
        seg._file.seek(at)
        return seg

    def __len__(self) -> int:
        return len(self.starts) - 1

    def append(self, payload: bytes, sync: bool = True) -> None:
        """`sync`: on the disk itself before this returns (a file in a folder)."""
        self._file.write(_LEN.pack(len(payload)) + payload)
        self.starts.append(self.starts[-1] + _LEN.size + len(payload))
        if sync:
            self.sync()

    def sync(self) -> None:
        self._file.flush()
        if self.path is not None:  # (an unnamed temporary file outlives no reboot)
            os.fdatasync(self._file.fileno())

    def payloads(self, skip: int = 0) -> Iterator[bytes]:
        fd = self._file.fileno()
        for a, b in zip(self.starts[skip:-1], self.starts[skip + 1 :], strict=True):
            data = os.pread(fd, b - a, a)
            if len(data) != b - a:
                raise OSError(f"keyframe history: {len(data)} of {b - a} bytes read back")
            yield data[_LEN.size :]

    def delete(self) -> None:
        self._close()
        if self.path is not None:
            self.path.unlink(missing_ok=True)

    def rename(self, path: Path) -> None:
        assert self.path is not None
        os.replace(self.path, path)
        self.path = path


class KeyframeHistory:
    def __init__(self, max_keyframes: int, directory: str | Path | None = None) -> None:
        """`directory`: keep the files there (and take up the ones already there)."""
        self.max_keyframes = max_keyframes
        self.directory = None if directory is None else Path(directory)
        self._segments: list[_Segment] = []  # oldest first, at most two
        self.dropped = 0  # keyframes deleted with an older file
        if self.directory is not None:
            self._finish_replace()
            for path in sorted(self.directory.glob("keyframes-*.log")):
                seg = _Segment.load(path)
                if self._segments and seg.first_seq != self.next_seq:
                    log.warning("%s does not follow on the files before it: those are "
                                "dropped", path)  # fmt: skip
                    self.clear()
                self._segments.append(seg)

    @property
    def next_seq(self) -> int | None:
        """The seq after the newest kept (None: none is)."""
        return self._segments[-1].first_seq + len(self._segments[-1]) if self._segments else None

    @property
    def first_seq(self) -> int | None:
        """The oldest keyframe kept (None: none is)."""
        return self._segments[0].first_seq if self._segments else None

    def add(self, seq: int, payload: bytes, keep_from: int | None = None) -> None:
        """Keep a keyframe (seqs consecutive; a gap starts over). An older file is
        deleted only if it holds nothing from `keep_from` on (the unacknowledged ones,
        which a restarted agent must send again, are kept however many). A disk error
        is logged and turns the history off: the agent flies on."""
        if self.max_keyframes <= 0:
            return
        try:
            self._add(seq, payload, seq if keep_from is None else keep_from)
        except OSError as exc:
            log.error("keyframe history off (%s): a base station that loses its "
                      "database, or this agent restarted, cannot get them", exc)  # fmt: skip
            self.max_keyframes = 0
            self.clear()

    def _add(self, seq: int, payload: bytes, keep_from: int) -> None:
        if self._segments and seq != self.next_seq:
            self.clear()  # not the chain's next one: what was kept cannot precede it
        seg = self._segments[-1] if self._segments else None
        if seg is None or len(seg) >= max(1, self.max_keyframes // 2):
            seg = _Segment.new(seq, self.directory)
            self._segments.append(seg)
            while len(self._segments) > 2 and self._segments[1].first_seq <= keep_from:
                old = self._segments.pop(0)
                self.dropped += len(old)
                old.delete()
        seg.append(payload)

    def __len__(self) -> int:
        return sum(len(s) for s in self._segments)

    def payloads(self, start_seq: int | None = None) -> Iterator[bytes]:
        """The payloads kept from `start_seq` on (all: None), oldest first, read back."""
        for seg in list(self._segments):
            skip = 0 if start_seq is None else min(max(0, start_seq - seg.first_seq), len(seg))
            yield from seg.payloads(skip)

    def replace(self, payloads: list[bytes]) -> None:
        """Keep `payloads` (seqs from 0: a new keyframe chain) instead of what is kept. In
        a folder, the new files are written beside the old ones and take their place only
        once whole (`NEXT_DONE`): a kill while writing keeps the old ones (a kill had lost
        every keyframe not rewritten yet). A disk error turns the history off (`add`)."""
        if self.max_keyframes <= 0:
            return
        try:
            per_file = max(1, self.max_keyframes // 2)
            new = [_Segment.new(i, self.directory, NEXT) for i in range(0, len(payloads), per_file)]
            for i, p in enumerate(payloads):
                new[i // per_file].append(p, sync=False)
            for seg in new:  # once a file (20,000 syncs had held the agent seconds)
                seg.sync()
            if self.directory is not None:
                (self.directory / NEXT_DONE).touch()
            old, self._segments = self._segments, new
            for seg in old:
                seg.delete()
            if self.directory is not None:
                self._finish_replace()
        except OSError as exc:
            log.error("keyframe history off (%s): a base station that loses its "
                      "database, or this agent restarted, cannot get them", exc)  # fmt: skip
            self.max_keyframes = 0
            self.clear()

    def _finish_replace(self) -> None:
        """A replacement's new files (`NEXT` + name): whole (`NEXT_DONE`), they take the
        old files' place; else they are dropped."""
        assert self.directory is not None
        done = (self.directory / NEXT_DONE).exists()
        if done:
            for path in self.directory.glob("keyframes-*.log"):
                path.unlink()
        by_path = {s.path: s for s in self._segments}
        for path in sorted(self.directory.glob(f"{NEXT}keyframes-*.log")):
            seg = by_path.get(path)
            if not done:
                path.unlink()
            elif seg is not None:
                seg.rename(path.with_name(path.name[len(NEXT) :]))
            else:
                os.replace(path, path.with_name(path.name[len(NEXT) :]))
        (self.directory / NEXT_DONE).unlink(missing_ok=True)

    def clear(self) -> None:
        """Forget (and delete) every keyframe kept."""
        for seg in self._segments:
            try:
                seg.delete()
            except OSError as exc:
                log.error("keyframe history: %s", exc)
        self._segments = []
