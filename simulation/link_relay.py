"""A radio link that can be cut: a TCP relay between one agent and the base station.

The agent connects its Zenoh session to the relay's port instead of the base
station's; `cut()` closes every relayed connection and stops listening (the
agent's Zenoh sees the link drop and its reconnects refused, exactly as when the
drone flies out of range), `restore()` listens again on the same port. The agent
must not learn the base station's own endpoint by gossip (it would go around the
relay): run it with `zenoh.gossip_scouting = false`.

Threads: one accept thread, two pump threads per relayed connection.
"""

from __future__ import annotations

import logging
import socket
import threading

log = logging.getLogger(__name__)


class LinkRelay:
    def __init__(self, upstream: tuple[str, int], listen_port: int = 0) -> None:
        """Relay 127.0.0.1:listen_port (0: a free port) to `upstream` (host, port)."""
        self.upstream = upstream
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._server: socket.socket | None = None
        self.cuts = 0
        self.port = listen_port
        self.restore()

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    @property
    def is_cut(self) -> bool:
        return self._server is None

    def restore(self) -> None:
        """Listen (again) on the relay port."""
        with self._lock:
            if self._server is not None:
                return
            srv = socket.socket()
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind(("127.0.0.1", self.port))
            srv.listen(8)
            self.port = srv.getsockname()[1]
            self._server = srv
        threading.Thread(target=self._accept, args=(srv,), daemon=True).start()

    def cut(self) -> None:
        """Drop every relayed connection and refuse new ones until `restore()`."""
        with self._lock:
            srv, self._server = self._server, None
            conns, self._conns = self._conns, []
        if srv is None:
            return
        self.cuts += 1
        _close(srv)
        for c in conns:
            _close(c)

    def close(self) -> None:
        self.cut()

    def _accept(self, srv: socket.socket) -> None:
        while True:
            try:
                down, _ = srv.accept()
            except OSError:
                return  # cut
            try:
                up = socket.create_connection(self.upstream, timeout=2.0)
                up.settimeout(None)
            except OSError:
                _close(down)  # the base station is not there: the agent retries
                continue
            with self._lock:
                if self._server is not srv:
                    _close(down)
                    _close(up)
                    return
                self._conns += [down, up]
            for a, b in ((down, up), (up, down)):
                threading.Thread(target=_pump, args=(a, b), daemon=True).start()


def _pump(src: socket.socket, dst: socket.socket) -> None:
    try:
        while data := src.recv(65536):
            dst.sendall(data)
    except OSError:
        pass
    _close(src)
    _close(dst)


def _close(s: socket.socket) -> None:
    try:
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    s.close()
