"""Logging configuration; only entry points call `setup_logging`."""

from __future__ import annotations

import logging
import sys


def setup_logging(level: str = "INFO", name: str = "") -> None:
    """One line per record on stderr, tagged with the process role."""
    tag = f"[{name}] " if name else ""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s %(levelname)s {tag}%(name)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )
    for noisy in ("numba", "matplotlib", "PIL"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
