"""The rerun viewer as a process: start one of this run's own that listens on this machine only, or check
that the one given by ``--connect`` is there before a run starts.

No rerun import here: the viewer is found beside the interpreter (``rerun`` from rerun-sdk) or on ``PATH``,
started with a fixed command line, and probed on its gRPC port.

``--spawn`` never streams into a viewer that is already listening (it may be another user's, or another
run's): it starts its own, on rerun's default port when that is free and on a free port otherwise. To
stream into a running viewer, ``--connect`` names it (without a URL: the local one on the default port),
and :func:`require_viewer` refuses, before anything is written, an address where nothing listens.
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
from urllib.parse import urlparse

from ..errors import InputError, printable

__all__ = ["LOCAL_VIEWER_URL", "VIEWER_PORT", "require_viewer", "spawn_local_viewer", "viewer_address"]

log = logging.getLogger(__name__)

VIEWER_PORT = 9876  # rerun's default gRPC port
LOCAL_VIEWER_URL = f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"  # what ``--connect`` alone streams to
_START_TIMEOUT_S = 10.0  # how long a started viewer gets to listen
_PROBE_TIMEOUT_S = 2.0  # how long --connect's viewer gets to accept a connection


def _listening(host: str, port: int, timeout_s: float = 0.2) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:  # refused, unreachable, timed out, or a host name that does not resolve
        return False


def _free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on now (the system's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def viewer_address(url: str) -> tuple[str, int]:
    """The host and port of a viewer's gRPC URL (``rerun+http://host:port/proxy``; rerun's port when none)."""
    parsed = urlparse(url)
    if not parsed.hostname:
        raise InputError(f"{printable(url)}: not a rerun viewer URL (e.g. {LOCAL_VIEWER_URL})")
    return parsed.hostname, parsed.port or VIEWER_PORT


def require_viewer(url: str, option: str = "--connect") -> None:
    """A viewer listens at ``url``, or :class:`~ar_anchor.errors.InputError` naming ``option`` and the
    address: found out before the run, not after it crawled along streaming into nothing."""
    host, port = viewer_address(url)
    if not _listening(host, port, _PROBE_TIMEOUT_S):
        raise InputError(
            f"{option} {printable(url)}: no rerun viewer is listening at {printable(host)}:{port} "
            "(start one with `rerun`, or use --spawn to start one for this run)"
        )


def _viewer_executable() -> str | None:
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.exists() else shutil.which("rerun")


def _choose_port(what: str) -> int:
    """rerun's default port when nothing listens there, else one the system says is free."""
    if not _listening("127.0.0.1", VIEWER_PORT):
        return VIEWER_PORT
    port = _free_port()
    log.info(
        "%s: 127.0.0.1:%d is taken (another viewer?); this run's viewer listens on port %d", what, VIEWER_PORT, port
    )
    return port


def spawn_local_viewer(what: str = "--spawn") -> str | None:
    """Start a rerun viewer of this run's own that listens on 127.0.0.1 only, and return its gRPC URL;
    None (with a warning naming ``what`` asked for it) when there is no display or no viewer. A viewer
    already listening is never reused: the new one takes another port (:func:`_choose_port`).

    ``rr.spawn`` is not used: the viewer it starts listens on every network interface (0.0.0.0), and
    rerun 0.41 offers no bind address for it. The viewer outlives the run (its own session).
    """
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        log.warning("%s: no display (DISPLAY / WAYLAND_DISPLAY unset), so no rerun viewer; recording only", what)
        return None
    executable = _viewer_executable()
    if executable is None:
        log.warning("%s: no rerun viewer found (pip install rerun-sdk); recording to file only", what)
        return None
    port = _choose_port(what)
    command = [executable, "--bind", "127.0.0.1", "--port", str(port), "--expect-data-soon"]
    try:
        viewer = subprocess.Popen(  # noqa: S603 - a fixed command line, no shell
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
    while time.monotonic() < deadline and viewer.poll() is None:
        if _listening("127.0.0.1", port):
            return f"rerun+http://127.0.0.1:{port}/proxy"
        time.sleep(0.1)
    log.warning("%s: the rerun viewer did not start listening on port %d; recording to file only", what, port)
    return None
