"""Listening ports for missions come from outside the kernel's ephemeral range, where
outgoing connections of other processes (another mission beside this one) take theirs."""

from __future__ import annotations

import socket

import pytest

from collabslam import supervisor
from common.errors import ProcessError


def test_free_ports_are_distinct_bindable_and_outside_the_ephemeral_range() -> None:
    lo, hi = (int(v) for v in supervisor._EPHEMERAL_RANGE.read_text().split())
    ports = supervisor.free_ports(20)
    assert len(set(ports)) == 20
    assert all(not lo <= p <= hi and p >= supervisor._LOWEST_PORT for p in ports)
    socks = []
    try:
        for p in ports:  # each can be listened on
            s = socket.socket()
            socks.append(s)
            s.bind(("127.0.0.1", p))
            s.listen()
    finally:
        for s in socks:
            s.close()


def test_a_port_in_use_is_not_given(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        with socket.socket() as other:
            other.bind(("127.0.0.1", 0))
            spare = other.getsockname()[1]
        pool = [range(busy, busy + 1), range(spare, spare + 1)]
        monkeypatch.setattr(supervisor, "_listen_port_ranges", lambda: pool)
        assert supervisor.free_ports(1) == [spare]
        with pytest.raises(ProcessError, match="no 2 free loopback ports"):
            supervisor.free_ports(2)
