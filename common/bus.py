"""The one class in front of Zenoh: sessions, typed publishers and subscribers.

Every process talks through a `Bus`. Publishers encode protocol messages;
subscribers decode and validate them, and a payload that fails (malformed,
oversized, wrong version, NaN, a robot id that does not match its key) is
logged (the first few of each kind) and dropped: the callback never sees it and the process
keeps running. Reliable data (keyframes, acks, corrections, commands) uses
`Reliability.RELIABLE` + `CongestionControl.BLOCK`.

Callbacks run on Zenoh's threads: handlers must be quick and thread-safe
(typically they put the message on a queue).
"""

from __future__ import annotations

import json
import logging
import re
import secrets
import threading
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from common.config import ZenohConfig
from common.errors import ConfigError, ProtocolError
from common.zenoh_security import check_acl_fleet, check_tls_files
from protocol.codec import DEFAULT_MAX_BYTES, decode, encode
from protocol.keys import Keys

log = logging.getLogger(__name__)
M = TypeVar("M")
REJECTS_LOGGED_PER_KIND = 5  # bad messages of one kind logged in full (then 1 in 1000)
REJECT_KINDS_KEPT = 64  # kinds counted apart in `rejected`; then "other"
_NAMES_AND_NUMBERS = re.compile(r"'[^']*'|\"[^\"]*\"|(?<![\w.])[-+]?\d[\d.eE+-]*")


def zenoh_config(zc: ZenohConfig, fleet: str | None = None) -> zenoh.Config:
    """Build a Zenoh session config: mode, endpoints, scouting (zenoh examples/common);
    `fleet`: its access-control rules must be that fleet's."""
    try:
        conf = zenoh.Config.from_file(zc.config_file) if zc.config_file else zenoh.Config()
    except Exception as exc:
        raise ConfigError(f"zenoh.config_file {zc.config_file!r}: {exc}") from None
    if zc.config_file:
        check_tls_files(conf, f"zenoh.config_file {zc.config_file!r}")
        if fleet is not None:
            check_acl_fleet(conf, fleet, f"zenoh.config_file {zc.config_file!r}")
    settings: dict[str, Any] = {"mode": zc.mode}
    if not zc.config_file:  # a file decides its own scouting (deploy/'s: none at all)
        settings["scouting/multicast/enabled"] = zc.multicast_scouting
        settings["scouting/gossip/enabled"] = zc.gossip_scouting
    if zc.listen or not zc.config_file:
        # [] listens nowhere. Zenoh's own default for a peer is every interface on a random
        # port, and gossip then tells the others to connect there: a base station restarted
        # after a crash opened a second link to each agent while the agent was reconnecting
        # to it, and the pair sometimes ended with the agent's acks and keyframes lost for
        # good (1 in 8 runs of test_basestation_recovery). It also let a peer bypass a
        # relayed link (simulation/link_relay.py) by connecting to the agent directly.
        settings["listen/endpoints"] = zc.listen
    if zc.listen and not zc.config_file:
        # A process that listens (base station, simulator) only accepts links; the others
        # connect to it. Were it to connect to peers that gossip names (e.g. a restarted
        # base station to the simulator) while they reconnect to it, the pair would get
        # two links at once (tests/test_links.py).
        settings["scouting/gossip/autoconnect"] = {"router": [], "peer": []}
    if zc.connect:
        settings["connect/endpoints"] = zc.connect
    for key, value in settings.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise ConfigError(f"zenoh.{key.split('/')[0]}: {exc}") from None
    return conf


class Bus:
    """A Zenoh session plus the fleet's key layout and typed pub/sub helpers."""

    def __init__(self, zc: ZenohConfig, fleet: str, max_message_bytes: int = DEFAULT_MAX_BYTES):
        self.keys = Keys(fleet)
        self.max_message_bytes = max_message_bytes
        self.rejected: Counter[str] = Counter()
        self.rivals: set[str] = set()  # other processes of a unique role (declare_alive)
        self.rivals_up: set[str] = set()  # ... whose token is up now
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._handles: list[Any] = []
        try:
            self.session = zenoh.open(zenoh_config(zc, fleet))
        except ConfigError:
            raise
        except Exception as exc:
            raise ConfigError(f"cannot open a Zenoh session: {exc}") from None

    # --- publishing ---------------------------------------------------------------------
    def publish(self, key: str, msg: Any, reliable: bool = True) -> None:
        """Encode and put `msg` on `key` (publisher declared once per key)."""
        self.put_raw(key, encode(msg), reliable)

    def put_raw(self, key: str, payload: bytes, reliable: bool = True) -> None:
        with self._lock:
            pub = self._publishers.get(key)
            if pub is None:
                pub = self.session.declare_publisher(
                    key,
                    reliability=zenoh.Reliability.RELIABLE
                    if reliable
                    else zenoh.Reliability.BEST_EFFORT,
                    congestion_control=zenoh.CongestionControl.BLOCK
                    if reliable
                    else zenoh.CongestionControl.DROP,
                )
                self._publishers[key] = pub
        pub.put(payload)

    # --- subscribing --------------------------------------------------------------------
    def subscribe(
        self,
        key_expr: str,
        msg_type: type[M] | tuple[type, ...],
        handler: Callable[[M, str], None],
    ) -> None:
        """Decode each sample as `msg_type` (or any of a tuple of types) and call
        handler(msg, key).

        Samples on a robot key must carry that robot's id; bad samples are dropped.
        One subscriber keeps one sender's samples in order; two subscribers' callbacks do
        not keep their order between them (a wildcard over several topics does).
        """
        types = msg_type if isinstance(msg_type, tuple) else (msg_type,)
        expected = types[0] if len(types) == 1 else None

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                msg = decode(sample.payload.to_bytes(), expected, self.max_message_bytes)
                if not isinstance(msg, types):
                    raise ProtocolError(f"unexpected {type(msg).__name__} message")
                robot = self.keys.robot_id_of(key)
                if robot is not None and getattr(msg, "robot_id", robot) != robot:
                    raise ProtocolError(
                        f"robot_id {msg.robot_id!r} does not match key robot {robot!r}"
                    )
            except ProtocolError as exc:
                self._reject(key, str(exc))
                return
            try:
                handler(msg, key)
            except Exception:  # a handler bug must not kill Zenoh's thread silently
                log.exception("handler for %s failed", key)

        self._handles.append(self.session.declare_subscriber(key_expr, on_sample))

    def _reject(self, key: str, reason: str) -> None:
        # the reason up to its first colon, numbers and quoted names left out (a size or a
        # robot id before it had made a kind per message, and a flood filled the kinds)
        kind = _NAMES_AND_NUMBERS.sub("#", reason.split(":")[0])
        with self._lock:
            if kind not in self.rejected and len(self.rejected) >= REJECT_KINDS_KEPT:
                kind = "other"  # (a kind can name a robot id: a flood of them is bounded)
            self.rejected[kind] += 1
            n, of_kind = sum(self.rejected.values()), self.rejected[kind]
        # The first few of each kind in full, then every 1000th, so a flood cannot drown
        # the log (the first 20 of all had been logged: after an old agent's 20 states,
        # another robot's NaN keyframes were dropped without a line)
        if of_kind <= REJECTS_LOGGED_PER_KIND or n % 1000 == 0:
            log.error("dropped bad message on %s: %s (%d rejected so far)", key, reason, n)

    # --- liveliness ---------------------------------------------------------------------
    def declare_alive(self, role: str, name: str, unique: bool = False) -> None:
        """A liveliness token `role`/`name`. `unique`: there should be one process of this
        role on the fleet; the token is `name`-<random> and another's token is an error
        line, its name kept in `rivals` (and in `rivals_up` while its token is up; two
        base stations had split the agents' keyframes between them without a word:
        both declared one token)."""
        if unique:
            name = f"{name}-{secrets.token_hex(4)}"

            def on_other(other: str, alive: bool) -> None:
                if other != name:
                    (self.rivals_up.add if alive else self.rivals_up.discard)(other)
                if alive and other != name and other not in self.rivals:
                    self.rivals.add(other)
                    log.error("another %s is up on fleet %s (%s; this is %s): run one per "
                              "fleet (a restarted one's token lingers for Zenoh's lease, "
                              "10 s)", role, self.keys.fleet, other, name)  # fmt: skip

            self.watch_alive(role, on_other)
        self._handles.append(self.session.liveliness().declare_token(self.keys.alive(role, name)))

    def watch_alive(self, role: str, on_change: Callable[[str, bool], None]) -> None:
        """on_change(name, alive) for every token of `role`, including those already there."""

        def on_sample(sample: zenoh.Sample) -> None:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            on_change(name, sample.kind == zenoh.SampleKind.PUT)

        self._handles.append(
            self.session.liveliness().declare_subscriber(
                self.keys.alive_all(role), on_sample, history=True
            )
        )

    def close(self) -> None:
        for h in self._handles:
            try:
                h.undeclare()
            except Exception:  # already closed
                pass
        self._handles.clear()
        self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def endpoint(port: int, host: str = "127.0.0.1") -> str:
    return f"tcp/{host}:{port}"


def ensure_dir(path: str | Path) -> Path:
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    return p
