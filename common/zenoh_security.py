"""Secure Zenoh configs for a deployment: mutual TLS plus per-robot access control.

The base station's Zenoh session (or a `zenohd` router in front of it) listens on
`tls/...` with mutual TLS: a remote must present a certificate signed by the fleet CA
(`deploy/make_certs.sh`), whose common name (CN) is its robot id. Its access-control
table, keyed by that CN, lets robot `rX`

- ingress (rX -> base): put/delete under `collabslam/<fleet>/robot/rX/**` only, declare
  subscribers there only (ack, correction, goal, path, neighbours), declare its liveliness token
  `alive/agent/rX`, and watch the base station's token;
- egress (base -> rX): receive puts under `robot/rX/**` only, the base station's
  subscriber declarations (so rX routes its keyframes and state to it) and its token.

Everything else is denied (`default_permission: deny`): a robot's put on another
robot's key is dropped at the base station, and a subscription to another robot's
path never gets a sample. A connection without a certificate, or with one from another
CA, fails the TLS handshake. The functions here return plain dicts (JSON, hence valid
JSON5) that `common/bus.py` loads through `zenoh.config_file`; the mode, scouting and
any `--listen/--connect` endpoints still come from our `ZenohConfig`.
"""

from __future__ import annotations

import json
import logging
import ssl
import time
from pathlib import Path
from typing import Any

import zenoh

from common.errors import ConfigError
from protocol.keys import DOWNLINK_TOPICS, Keys

log = logging.getLogger(__name__)

BASESTATION_CN = "basestation"
_ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


TLS_FILE_KEYS = (
    "root_ca_certificate",
    "listen_private_key",
    "listen_certificate",
    "connect_private_key",
    "connect_certificate",
)


def check_tls_files(conf: zenoh.Config, source: str, now: float | None = None) -> None:
    """Raise ConfigError naming the key if a TLS file of `conf` cannot be read, or if a
    certificate (its own, the CA's) has expired; warn if one is not valid yet (a drone
    without a real-time clock, before its clock is set: Zenoh retries until it is).

    Zenoh itself would only fail the link (a peer then retries forever in silence): a
    fleet whose certificates had expired together (`make_certs.sh` gives the CA and the
    robots one lifetime) had gone dark with only "no base station seen" in its logs.
    """
    for key in TLS_FILE_KEYS:
        path = json.loads(conf.get_json(f"transport/link/tls/{key}"))
        if path is None:
            continue
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            raise ConfigError(
                f"{source}: transport.link.tls.{key} {path!r}: {exc.strerror}"
            ) from None
        if not key.endswith("_key") and (cert := _decode_certificate(path)) is not None:
            _check_dates(cert, f"{source}: transport.link.tls.{key} {path!r}", now)


def _decode_certificate(path: str) -> dict[str, Any] | None:
    """A PEM certificate's fields (CPython's own reader; the ssl module has no public
    one), None if it cannot be read (a CA bundle, another format)."""
    try:
        return ssl._ssl._test_decode_cert(path)  # type: ignore[attr-defined,no-any-return]
    except (OSError, ssl.SSLError, AttributeError, ValueError):
        return None


def check_acl_fleet(conf: zenoh.Config, fleet: str, source: str) -> None:
    """ConfigError if the access-control rules of `conf` are for another fleet than this
    process's (configs made with another `--fleet`): every message would be dropped at
    the base station, counted nowhere."""
    try:
        rules = json.loads(conf.get_json("access_control/rules")) or []
    except Exception:  # (no access control in this file)
        return
    prefix = f"collabslam/{fleet}/"
    others = sorted({k for r in rules for k in r.get("key_exprs", ()) if not k.startswith(prefix)})
    if others:
        raise ConfigError(f"{source}: its access-control rules are for other keys than fleet "
                          f"{fleet!r}'s ({prefix}...): {', '.join(others[:3])}; made with "
                          "another --fleet? (deploy/make_zenoh_configs.py --fleet)")  # fmt: skip


def certificate_names(path: str | Path) -> list[str] | None:
    """The host names and addresses (subjectAltName) of a PEM certificate; None if it
    cannot be read."""
    cert = _decode_certificate(str(path))
    return None if cert is None else [v for _, v in cert.get("subjectAltName", ())]


def _check_dates(cert: dict[str, Any], what: str, now: float | None = None) -> None:
    now = time.time() if now is None else now
    try:
        start = ssl.cert_time_to_seconds(cert["notBefore"])
        end = ssl.cert_time_to_seconds(cert["notAfter"])
    except (KeyError, ValueError):
        return
    if now > end:
        raise ConfigError(f"{what}: the certificate expired on {cert['notAfter']}: every TLS "
                          "link with it is refused (remake it: deploy/make_certs.sh)")  # fmt: skip
    if now < start:
        log.warning("%s: the certificate is valid only from %s, and this host's clock says "
                    "%s: TLS links are refused until the clock is set", what,
                    cert["notBefore"], time.strftime("%b %d %H:%M:%S %Y GMT",
                                                     time.gmtime(now)))  # fmt: skip


def check_certificate_name(config_file: str, name: str) -> None:
    """ConfigError if the certificate a Zenoh config file connects with (its
    connect_certificate) is not `name`'s (CN): the access control drops all this process
    sends, and a drone given another drone's config had flown a mission mapping nothing,
    with no line in any log. A listening base station's own certificate may be named
    after its host: the rules are about those who connect."""
    try:
        conf = zenoh.Config.from_file(config_file)
    except Exception:  # (the Bus names a file it cannot read)
        return
    path = json.loads(conf.get_json("transport/link/tls/connect_certificate"))
    if not path:
        return
    if (cert := _decode_certificate(path)) is None or "subject" not in cert:
        return  # (check_tls_files names a file it cannot read)
    cn = dict(pair[0] for pair in cert["subject"]).get("commonName")
    if cn != name:
        raise ConfigError(
            f"zenoh.config_file {config_file!r}: its certificate {path} is {cn!r}'s, not "
            f"{name!r}'s: the access control would drop everything this process sends "
            "(another drone's config?)"
        )


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": key_exprs,
    }


def robot_rules(fleet: str, robot_id: str) -> list[dict[str, Any]]:
    """Allow rules for robot `robot_id` as seen from the base station.

    ACL key matching is by inclusion: a message's key must lie inside a rule's key
    expression, so `robot/*/keyframe` (the base station's subscription) needs its own
    rule and never matches `robot/<id>/**`. That rule is needed when the base station
    is a peer (a peer sends a put only where a matching subscriber was declared);
    each rule here was checked by removing it (tests/test_security.py exercises all).
    """
    if robot_id == BASESTATION_CN:
        raise ConfigError(f"robot id {robot_id!r} is reserved for the base station")
    keys = Keys(fleet)
    own = f"{keys.root}/robot/{robot_id}/**"
    base_alive = keys.alive_all("basestation")
    return [
        _rule(f"{robot_id}-in-own", "ingress", ["put", "delete", "declare_subscriber"], [own]),
        _rule(
            f"{robot_id}-in-token", "ingress", ["liveliness_token"], [keys.alive("agent", robot_id)]
        ),
        _rule(
            f"{robot_id}-in-watch-base",
            "ingress",
            ["declare_liveliness_subscriber", "liveliness_query"],
            [base_alive],
        ),
        _rule(f"{robot_id}-out-own", "egress", ["put", "delete", "declare_subscriber"], [own]),
        _rule(
            f"{robot_id}-out-base-subs",
            "egress",
            ["declare_subscriber"],
            # (GNSS: a drone's fixes its agent passes on, `agent.relay_gnss`)
            [keys.all_robots("keyframe"), keys.all_robots("state"), keys.all_robots("sensor/gnss")],
        ),
        _rule(
            f"{robot_id}-out-liveliness",
            "egress",
            ["liveliness_token", "reply"],
            [base_alive],
        ),
    ]


def access_control(fleet: str, robots: list[str]) -> dict[str, Any]:
    """The base station's `access_control` section: one subject and policy per robot CN.

    The base station's own CN (a process connecting as `basestation`, e.g. the base
    station behind a `zenohd` router) may do anything under `collabslam/<fleet>/**`.
    """
    keys = Keys(fleet)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for rid in robots:
        rr = robot_rules(fleet, rid)
        rules += rr
        subjects.append({"id": f"robot-{rid}", "cert_common_names": [rid]})
        policies.append(
            {"id": f"policy-{rid}", "rules": [r["id"] for r in rr], "subjects": [f"robot-{rid}"]}
        )
    for flow in ("ingress", "egress"):
        rules.append(_rule(f"basestation-{flow}", flow, _ALL_MESSAGES, [f"{keys.root}/**"]))
    subjects.append({"id": "basestation", "cert_common_names": [BASESTATION_CN]})
    policies.append(
        {
            "id": "policy-basestation",
            "rules": ["basestation-ingress", "basestation-egress"],
            "subjects": ["basestation"],
        }
    )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _no_scouting() -> dict[str, Any]:
    # Explicit endpoints only: no multicast discovery, no gossip of other peers' locators
    # (robots must never learn of or connect to each other).
    return {"multicast": {"enabled": False}, "gossip": {"enabled": False}}


def basestation_config(
    cert_dir: str | Path, fleet: str, robots: list[str], listen: list[str]
) -> dict[str, Any]:
    """Zenoh config of the base station: mTLS listener(s) + the per-robot ACL."""
    d = Path(cert_dir)
    return {
        "listen": {"endpoints": list(listen)},
        "scouting": _no_scouting(),
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(d / "ca.pem"),
                    "listen_private_key": str(d / f"{BASESTATION_CN}.key"),
                    "listen_certificate": str(d / f"{BASESTATION_CN}.pem"),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                },
            }
        },
        "access_control": access_control(fleet, robots),
    }


def robot_config(
    cert_dir: str | Path, robot_id: str, connect: list[str], listen: list[str] | None = None
) -> dict[str, Any]:
    """Zenoh config of robot `robot_id`: mTLS client certificate (CN = robot id).

    `connect` are the base station's `tls/...` endpoints; `listen` optional local
    endpoints (e.g. `tcp/127.0.0.1:7448` for the drone's own sensor driver). Without
    them the session listens nowhere (a Zenoh peer's default is `tcp/[::]:0`: every
    interface, no TLS, out of the base station's access control).
    """
    d = Path(cert_dir)
    conf: dict[str, Any] = {
        "connect": {"endpoints": list(connect)},
        "listen": {"endpoints": list(listen or [])},
        "scouting": _no_scouting(),
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": str(d / "ca.pem"),
                    "connect_private_key": str(d / f"{robot_id}.key"),
                    "connect_certificate": str(d / f"{robot_id}.pem"),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                }
            }
        },
    }
    return conf


def downlink_keys(fleet: str, robot_id: str) -> list[str]:
    """Keys the base station sends to `robot_id` (ack, correction, goal, path, neighbours)."""
    keys = Keys(fleet)
    return [keys.robot(robot_id, t) for t in DOWNLINK_TOPICS]


def write_deploy_configs(
    cert_dir: str | Path,
    out_dir: str | Path,
    fleet: str,
    robots: list[str],
    base_host: str = "localhost",
    port: int = 7447,
    robot_listen: list[str] | None = None,
) -> list[Path]:
    """Write basestation.json5, robot-<id>.json5, router.json5, basestation-client.json5.

    `cert_dir` is where the processes will find the certificates (made absolute here,
    as Zenoh reads the paths relative to its working directory).
    """
    certs = Path(cert_dir).resolve()
    out = Path(out_dir)
    listen = [f"tls/0.0.0.0:{port}"]
    connect = [f"tls/{base_host}:{port}"]
    made = f"made by deploy/make_zenoh_configs.py for fleet {fleet!r}, robots {' '.join(robots)}"
    base = basestation_config(certs, fleet, robots, listen)
    paths = [
        write_json5(
            base,
            out / "basestation.json5",
            f"collabslam base station: mTLS listener + per-robot access control.\n{made}\n"
            "Mode comes from collabslam's config (zenoh.mode, default peer); scouting is\n"
            "this file's own (off).",
        ),
        write_json5(
            {"mode": "router", **base},
            out / "router.json5",
            f"zenohd router option (zenohd -c router.json5): same mTLS + ACL.\n{made}",
        ),
        write_json5(
            robot_config(certs, BASESTATION_CN, [f"tls/127.0.0.1:{port}"]),
            out / "basestation-client.json5",
            "collabslam base station behind the zenohd router on the same laptop "
            f"(certificate CN={BASESTATION_CN}).\n{made}",
        ),
    ]
    for rid in robots:
        paths.append(
            write_json5(
                robot_config(certs, rid, connect, robot_listen),
                out / f"robot-{rid}.json5",
                f"collabslam agent of robot {rid}: client certificate CN={rid}.\n{made}",
            )
        )
    return paths


def write_json5(conf: dict[str, Any], path: str | Path, header: str = "") -> Path:
    """Write a config dict as JSON5 (plain JSON with a `//` comment header)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"// {line}".rstrip() for line in header.splitlines()]
    p.write_text("\n".join(lines + [json.dumps(conf, indent=2)]) + "\n")
    return p
