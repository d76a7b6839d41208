#!/usr/bin/env python3
"""Write the secure Zenoh configs of a fleet (mutual TLS + per-robot access control).

    deploy/make_zenoh_configs.py --certs /etc/collabslam/certs --out /etc/collabslam/zenoh \\
        --base-host 192.168.8.1 r0 r1 r2

writes into --out:
  basestation.json5        the base station (`collabslam basestation --zenoh-config ...`):
                           listens on tls/0.0.0.0:7447 with mTLS, ACL keyed by certificate CN
  robot-<id>.json5         one per drone (`collabslam agent --robot-id <id> --zenoh-config ...`):
                           client certificate CN=<id>, connects to tls/<base-host>:7447,
                           listens on tcp/127.0.0.1:7448 for the drone's own sensor driver
  router.json5             the zenohd router option: same listener and ACL as basestation.json5
  basestation-client.json5 the base station behind that router (certificate CN=basestation)

The certificates come from deploy/make_certs.sh (same robot ids). Re-run both scripts
when a robot joins the fleet: the ACL lists every robot explicitly.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's code first
from common.zenoh_security import certificate_names, write_deploy_configs  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("robots", nargs="+", help="robot ids (= certificate common names)")
    p.add_argument("--certs", required=True, help="folder made by deploy/make_certs.sh")
    p.add_argument("--out", required=True, help="folder for the .json5 files")
    p.add_argument("--fleet", default="default", help="fleet name (config key `fleet`)")
    p.add_argument("--base-host", default="localhost", help="name/IP robots use for the base")
    p.add_argument("--port", type=int, default=7447, help="base station TLS port")
    p.add_argument("--robot-listen", default="tcp/127.0.0.1:7448", help="'' for none")
    args = p.parse_args(argv)
    names = certificate_names(Path(args.certs) / "basestation.pem")
    if names is not None and args.base_host not in names:  # (the handshake would fail)
        print(f"--base-host {args.base_host}: not among the names of {args.certs}/basestation.pem "
              f"({', '.join(names)}): every drone would refuse the base station's certificate. "
              f"Remake it: BASE_HOSTS={args.base_host} deploy/make_certs.sh {args.certs} "
              f"{' '.join(args.robots)}", file=sys.stderr)  # fmt: skip
        return 2
    paths = write_deploy_configs(
        args.certs,
        args.out,
        args.fleet,
        args.robots,
        base_host=args.base_host,
        port=args.port,
        robot_listen=[args.robot_listen] if args.robot_listen else [],
    )
    for path in paths:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
