"""Options every `collabslam` sub-command shares, and the config they select.

``add_common_args`` adds ``--config``/``--set`` (and the Zenoh endpoint options);
``load_cfg`` turns a parsed namespace into the validated ``Config``. Used by
``collabslam.cli`` and ``collabslam.bench_cli``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.errors import ConfigError

if TYPE_CHECKING:
    from common.config import Config


def add_common_args(sp: argparse.ArgumentParser, zenoh: bool = True) -> None:
    """``--config`` and ``--set``; with ``zenoh``, also ``--listen``/``--connect``/
    ``--zenoh-config`` (for the processes that open a Zenoh session themselves)."""
    sp.add_argument("--config", help="TOML config file (defaults are built in)")
    sp.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config key, e.g. --set sim.seed=3",
    )
    if zenoh:
        sp.add_argument(
            "--listen",
            action="append",
            metavar="ENDPOINT",
            help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447",
        )
        sp.add_argument(
            "--connect",
            action="append",
            metavar="ENDPOINT",
            help="Zenoh endpoint to connect to",
        )
        sp.add_argument(
            "--zenoh-config",
            metavar="PATH",
            help="Zenoh JSON5 config merged under our endpoints, e.g. the TLS + "
            "access-control files made by deploy/make_zenoh_configs.py",
        )


def parse_set(items: list[str]) -> dict[str, Any]:
    """--set key=value, value parsed as TOML (numbers, booleans, strings, lists)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected key=value")
        try:
            out[key.strip()] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = raw  # bare word: a string
    return out


def load_cfg(args: argparse.Namespace) -> Config:
    """The validated ``common.config.Config``: --config file, then --set and endpoint options."""
    from common.config import load_config

    overrides = parse_set(args.set)
    if getattr(args, "listen", None):
        overrides["zenoh.listen"] = args.listen
    if getattr(args, "connect", None):
        overrides["zenoh.connect"] = args.connect
    if getattr(args, "zenoh_config", None):
        overrides["zenoh.config_file"] = args.zenoh_config
    if getattr(args, "db", None):
        overrides["basestation.db_path"] = args.db
    cfg = load_config(args.config, overrides)
    if getattr(args, "out", None):
        writable_folder(args.out)
    if getattr(args, "json", None):
        json_file(args.json)
    limit = getattr(args, "max_sim_time", None)  # (nan had run with no limit)
    if limit is not None and not (math.isfinite(limit) and limit > 0.0):
        raise ConfigError(f"--max-sim-time: expected a number of seconds > 0, got {limit}")
    return cfg


def json_file(path: str, beside: bool = True) -> None:
    """`--json` must name a file (with `beside`, a .json file: a benchmark's other
    outputs go in a folder beside it named by its stem; one without a suffix is that
    folder, and the JSON could not be written after hours of running)."""
    p = Path(path)
    if p.is_dir() or (beside and p.suffix != ".json"):
        raise ConfigError(f"--json {path}: expected a file name" + " ending in .json" * beside)
    writable_folder(str(p.parent), "--json's folder")


def writable_folder(path: str, option: str = "--out") -> None:
    """Make `--out` and try writing in it now: found unusable only at shutdown (a file in
    its path, a read-only disk), a whole mission's outputs had been lost to a traceback."""
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise ConfigError(f"{option} {path}: not a writable folder: {exc}") from None
