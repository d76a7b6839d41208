"""Graceful shutdown (uvicorn's capture_signals): the first SIGINT/SIGTERM asks the
process to drain and persist; a second one forces exit."""

from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType

log = logging.getLogger(__name__)


def install_signal_handlers(stop: threading.Event) -> None:
    """Set `stop` on the first SIGINT/SIGTERM; exit at once (code 130) on the second."""

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            log.warning("second %s: forcing exit", signal.Signals(signum).name)
            os._exit(130)
        log.info("%s received: shutting down (send again to force)", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
