"""The fault benchmark's tools: every bad payload is one the decoder (or the roster)
refuses, and the link relay really cuts and restores a TCP link."""

from __future__ import annotations

import socket
import threading

import pytest

from benchmarks.fault_injection import BAD_KINDS, bad_payloads
from common.errors import ProtocolError
from protocol import Keyframe, Keys, decode
from simulation.link_relay import LinkRelay


def test_every_bad_payload_is_refused() -> None:
    keys = Keys("default")
    robots = ["r0", "r1"]
    payloads = bad_payloads(3 * len(BAD_KINDS), keys, robots, max_bytes=4096, seed=1)
    assert {k for _, _, k in payloads} == set(BAD_KINDS)
    for key, payload, kind in payloads:
        if kind in ("robot_mismatch", "unknown_robot"):
            msg = decode(payload, Keyframe, 4096)  # valid bytes, wrong sender
            key_robot = keys.robot_id_of(key)
            assert msg.robot_id != key_robot or key_robot not in robots
        else:
            with pytest.raises(ProtocolError):
                decode(payload, Keyframe, 4096)


def _echo(c: socket.socket) -> None:
    with c:
        while data := c.recv(99):
            c.sendall(data)


def _echo_server() -> tuple[socket.socket, int]:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)

    def serve() -> None:
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            threading.Thread(target=_echo, args=(c,), daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    return srv, srv.getsockname()[1]


def test_link_relay_cuts_and_restores() -> None:
    srv, port = _echo_server()
    relay = LinkRelay(("127.0.0.1", port))
    try:
        c = socket.create_connection(("127.0.0.1", relay.port), timeout=5)
        c.sendall(b"hello")
        assert c.recv(5) == b"hello"
        relay.cut()
        assert relay.is_cut and c.recv(5) == b""  # the relayed connection is gone
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", relay.port), timeout=2)
        relay.restore()
        c2 = socket.create_connection(("127.0.0.1", relay.port), timeout=5)
        c2.sendall(b"again")
        assert c2.recv(5) == b"again" and relay.cuts == 1
        c.close()
        c2.close()
    finally:
        relay.close()
        srv.close()
