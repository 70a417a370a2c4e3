"""The rerun viewer as a process: start one that listens on this machine only, or reuse the one already there.

No rerun import here: the viewer is found beside the interpreter (``rerun`` from rerun-sdk) or on ``PATH``,
started with a fixed command line, and probed on its gRPC port.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["VIEWER_PORT", "spawn_local_viewer"]

log = logging.getLogger(__name__)

VIEWER_PORT = 9876  # rerun's default gRPC port
_START_TIMEOUT_S = 10.0  # how long a started viewer gets to listen


def _listening(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.2)
        return probe.connect_ex((host, port)) == 0


def _viewer_executable() -> str | None:
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.exists() else shutil.which("rerun")


def spawn_local_viewer(what: str = "--spawn") -> str | None:
    """Start a rerun viewer that listens on 127.0.0.1 only, and return its gRPC URL; None (with a
    warning naming ``what`` asked for it) when there is no display or no viewer. A viewer already
    listening there is reused.

    ``rr.spawn`` is not used: the viewer it starts listens on every network interface (0.0.0.0), and
    rerun 0.41 offers no bind address for it. The viewer outlives the run (its own session).
    """
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        log.warning("%s: no display (DISPLAY / WAYLAND_DISPLAY unset), so no rerun viewer; recording only", what)
        return None
    url = f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"
    if _listening("127.0.0.1", VIEWER_PORT):
        return url
    executable = _viewer_executable()
    if executable is None:
        log.warning("%s: no rerun viewer found (pip install rerun-sdk); recording to file only", what)
        return None
    command = [executable, "--bind", "127.0.0.1", "--port", str(VIEWER_PORT), "--expect-data-soon"]
    try:
        subprocess.Popen(  # noqa: S603 - a fixed command line, no shell
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
    except OSError as err:
        log.warning("%s: could not start the rerun viewer (%s); recording to file only", what, err.strerror or err)
        return None
    deadline = time.monotonic() + _START_TIMEOUT_S
    while time.monotonic() < deadline:
        if _listening("127.0.0.1", VIEWER_PORT):
            return url
        time.sleep(0.1)
    log.warning("%s: the rerun viewer did not start listening; recording to file only", what)
    return None
