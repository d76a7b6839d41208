"""At-least-once keyframe uplink (modelled on Cartographer's local_trajectory_uploader).

Keyframes stay in the outbox, in sequence order, until the base station's
cumulative ack covers them. If no ack makes progress for the retransmission
timeout (wall time), the oldest `resend_batch` are sent again, in order; the base
station drops duplicates, so resending is harmless, but each one costs it a decode.
The timeout follows the measured ack delay as TCP's does (RFC 6298: smoothed delay
plus four times its mean deviation, sampled only from keyframes sent once), never
below `resend_timeout_s` nor above `MAX_TIMEOUT_S`: a base station that acks
keyframes 3 s after they were sent is busy, and resending after 1 s would only
queue duplicates in front of the originals (a 30-minute 10-robot soak got 150,000
that way). While acks stay stalled the wait doubles after each resend (up to
`max_backoff` times the fixed timeout), so a base station that is busy, not gone, is
not flooded with duplicates. Once an ack covers
a resent batch and stops there (what followed it was lost), the next batch goes at
once: after an outage the outbox drains, in order, at the pace of the acks. An ack
beyond the batch means the base station had the rest queued (busy, not cut off):
nothing more is resent until the acks stall again.

Every keyframe queued is also kept in a `KeyframeHistory` on disk (if given), for a
base station that has lost the acknowledged ones (`new_chain` then queues what is kept,
oldest first, renumbered as a new keyframe chain), and for the agent restarted on its
state folder (`restore`).

Bound policy: the outbox holds at most `max_len` keyframes. It warns once when
it passes `warn_fraction` of that; when full, `has_room()` is False and the
agent does not cut new keyframes (it keeps flying on local SLAM and the next
keyframe it cuts spans the gap), so the chain stays intact and nothing queued
is ever dropped.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from agent.keyframe_history import KeyframeHistory
from protocol.codec import relabel
from protocol.messages import Keyframe

log = logging.getLogger(__name__)

MAX_TIMEOUT_S = 30.0  # the measured retransmission timeout's ceiling (s)
IDENTITY7 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


class Outbox:
    def __init__(
        self,
        max_len: int,
        warn_fraction: float,
        resend_timeout_s: float,
        resend_batch: int,
        clock: Callable[[], float] = time.monotonic,
        max_backoff: int = 8,
        history: KeyframeHistory | None = None,
    ) -> None:
        self.max_len = max_len
        self.warn_len = max(1, int(max_len * warn_fraction))
        self.resend_timeout_s = resend_timeout_s
        self.resend_batch = resend_batch
        self._clock = clock
        self.max_backoff = max_backoff
        self.history = KeyframeHistory(0) if history is None else history
        self.chain = 0  # of the keyframes queued (Keyframe.chain)
        self._backoff = 1
        self._pending: OrderedDict[int, bytes] = OrderedDict()
        self._lock = threading.Lock()
        self._last_progress = clock()
        self._warned = False
        self.acked_seq = -1  # highest seq the base station confirmed
        self.added_seq = -1  # highest seq queued
        self.bad_acks = 0  # acks past added_seq: ignored
        self.resent = 0
        self.high_water = 0
        self.deferred = 0  # has_room() calls answered False
        self._full = False
        self._resent_upto = -1  # last seq of the last resent batch (-1: none outstanding)
        self._resend_now = False  # the next due_for_resend resends whatever the timer
        self._sent_at: dict[int, float] = {}  # seq -> time sent, for keyframes sent once
        self._srtt: float | None = None  # smoothed ack delay (s)
        self._rttvar = 0.0  # its mean deviation (s)

    def has_room(self) -> bool:
        """False while full (a keyframe due now is not cut: counted in `deferred`)."""
        with self._lock:
            room = len(self._pending) < self.max_len
            first = not room and not self._full  # warn once each time it fills up
            self._full = not room
            if not room:
                self.deferred += 1
        if first:
            log.warning(
                "outbox full (%d keyframes unacknowledged): no new keyframes until acks "
                "arrive; the next one will span the gap",
                self.max_len,
            )
        return room

    def add(self, seq: int, payload: bytes) -> None:
        """Queue a keyframe; seq must increase by one each call."""
        with self._lock:
            if self._pending and seq != next(reversed(self._pending)) + 1:
                raise ValueError(f"outbox expects consecutive seqs, got {seq}")
            self._pending[seq] = payload
            self.history.add(seq, payload, keep_from=self.acked_seq + 1)
            self._sent_at[seq] = self._clock()
            self.added_seq = max(self.added_seq, seq)
            n = len(self._pending)
            self.high_water = max(self.high_water, n)
            if n == 1:
                self._last_progress = self._clock()
                self._resend_now = False
        if n >= self.warn_len and not self._warned:
            self._warned = True
            log.warning(
                "outbox is %d/%d full: the base station is not acknowledging", n, self.max_len
            )

    def ack(self, acked_seq: int, chain: int | None = None) -> int:
        """Drop everything <= acked_seq (of keyframe chain `chain`: an ack of another is
        ignored, checked under the lock `new_chain` renumbers under); returns how many
        were released."""
        released = 0
        with self._lock:
            if chain is not None and chain != self.chain:
                return 0
            if acked_seq > self.added_seq:  # nothing sent that far: it would release
                self.bad_acks += 1  # keyframes the base station never had
                if self.bad_acks == 1 or self.bad_acks % 100 == 0:
                    log.error("ack for seq %d past the last queued (%d): ignored (%d so far)",
                              acked_seq, self.added_seq, self.bad_acks)  # fmt: skip
                return 0
            if acked_seq <= self.acked_seq:
                return 0
            self.acked_seq = acked_seq
            sent_at = self._sent_at.get(acked_seq)  # None: resent (Karn) or not ours
            if sent_at is not None:
                self._sample_delay(self._clock() - sent_at)
            while self._pending and next(iter(self._pending)) <= acked_seq:
                seq, _ = self._pending.popitem(last=False)
                self._sent_at.pop(seq, None)
                released += 1
            self._last_progress = self._clock()
            self._backoff = 1
            if self._resent_upto >= 0 and acked_seq >= self._resent_upto:
                # The ack stops at the resent batch's end: the base station has nothing
                # after it, those were lost (an outage): the next batch now. An ack past
                # the batch means the originals were only queued (a busy base station):
                # resending more would only send it duplicates to decode.
                lost = acked_seq == self._resent_upto
                self._resent_upto = -1
                if self._pending and lost:
                    self._resend_now = True
            if len(self._pending) < self.warn_len:
                self._warned = False
        return released

    def kick(self) -> None:
        """The base station is (back) up: resend at the next `due_for_resend` call,
        without the backoff built up while it was gone, nor the ack delay measured before
        (a new link: until an ack makes progress, retries come every `resend_timeout_s`,
        doubling). A batch resent at once can be lost while the link's routes form; with
        the old delay's timeout (seconds, from a busy base station) the next try came so
        late that the keyframes cut meanwhile overran the base station's reorder window
        (the link-cut test lost 556 keyframes that way under load)."""
        with self._lock:
            self._backoff = 1
            self._resend_now = True
            self._srtt, self._rttvar = None, 0.0
            self._sent_at.clear()  # sent into the outage: their delay is the outage's

    def new_chain(self, chain: int) -> int:
        """Every keyframe kept, acknowledged (the history) or not, renumbered as keyframe
        chain `chain` from seq 0 (the first with no delta: nothing precedes it), to be
        sent again from the first at once, paced by the acks; returns how many (the
        chain's next seq). For a base station that has none of them (~4 us a keyframe:
        the payloads are relabelled, not decoded)."""
        with self._lock:
            pending = next(iter(self._pending), self.added_seq + 1)  # the first unacked
            first = self.history.first_seq
            n = 0 if first is None or first > pending else pending - first
            kept = list(itertools.islice(self.history.payloads(), n))  # acknowledged
            lost = pending - n  # acknowledged, not kept
            payloads = [
                relabel(p, Keyframe, seq=i, chain=chain, **({"delta": IDENTITY7} if i == 0 else {}))
                for i, p in enumerate([*kept, *self._pending.values()])
            ]
            self.history.replace(payloads)  # (whole, or the old ones kept: a kill meanwhile)
            self._sent_at.clear()
            self._pending = OrderedDict(enumerate(payloads))
            self.acked_seq, self.added_seq, self._resent_upto = -1, len(payloads) - 1, -1
            self.chain = chain
            self._backoff, self._resend_now = 1, True
            self._srtt, self._rttvar = None, 0.0
            self._last_progress = self._clock()
            self.high_water = max(self.high_water, len(payloads))
        log.warning("the base station has none of this robot's keyframes (a new database): "
                    "sending the %d kept as keyframe chain %d (%d acknowledged before were "
                    "not kept)", len(payloads), chain, lost)  # fmt: skip
        return len(payloads)

    def restore(self, acked_seq: int, next_seq: int) -> None:
        """After a restart: keyframes up to `acked_seq` were acknowledged, the ones after
        it up to `next_seq` - 1 are taken from the history (on disk) to be sent again."""
        with self._lock:
            self.acked_seq, self.added_seq = acked_seq, next_seq - 1
            first = self.history.first_seq
            start = acked_seq + 1 if first is None else max(acked_seq + 1, first)
            for seq, p in zip(range(start, next_seq), self.history.payloads(start), strict=False):
                self._pending[seq] = p
            self._resend_now = True
        if len(self._pending) < next_seq - acked_seq - 1:
            log.error("keyframes %d..%d were not kept: the base station will wait for them",
                      acked_seq + 1, next_seq - 1)  # fmt: skip

    @property
    def timeout_s(self) -> float:
        """The retransmission timeout: from the measured ack delay, within bounds."""
        if self._srtt is None:
            return self.resend_timeout_s
        rto = self._srtt + 4.0 * self._rttvar
        return min(max(rto, self.resend_timeout_s), MAX_TIMEOUT_S)

    def _sample_delay(self, delay: float) -> None:
        if self._srtt is None:
            self._srtt, self._rttvar = delay, delay / 2.0
        else:
            self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - delay)
            self._srtt = 0.875 * self._srtt + 0.125 * delay

    def due_for_resend(self) -> list[bytes]:
        """The oldest unacknowledged payloads if the ack has stalled, else []."""
        with self._lock:
            rto = self.timeout_s
            wait = min(rto * self._backoff, max(rto, self.resend_timeout_s * self.max_backoff))
            stalled = self._clock() - self._last_progress >= wait
            if not self._pending or not (stalled or self._resend_now):
                return []
            self._resend_now = False
            self._last_progress = self._clock()
            self._backoff = min(2 * self._backoff, self.max_backoff)
            seqs = [s for _, s in zip(range(self.resend_batch), self._pending, strict=False)]
            batch = [self._pending[s] for s in seqs]
            for s in seqs:  # a later ack of these says nothing about the delay
                self._sent_at.pop(s, None)
            self._resent_upto = seqs[-1]
        self.resent += len(batch)
        return batch

    def __len__(self) -> int:
        with self._lock:
            return len(self._pending)
