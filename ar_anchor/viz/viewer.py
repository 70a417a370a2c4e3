"""The rerun viewer as a process: start one of this run's own that listens on this machine only, or check
that the one given by ``--connect`` is there before a run starts.

No rerun import here: the viewer is found beside the interpreter (``rerun`` from rerun-sdk) or on ``PATH``,
started with a fixed command line, and probed on its gRPC port.

``--spawn`` never streams into a viewer that is already listening (it may be another user's, or another
run's): it starts its own, on rerun's default port when that is free and on a free port otherwise. To
stream into a running viewer, ``--connect`` names it (without a URL: the local one on the default port),
and :func:`require_viewer` refuses, before anything is written, an address where nothing listens.

``ar-anchor view`` opens recordings in a native viewer of the command's own (:func:`open_native_viewer`) or
serves the web viewer (:func:`serve_web_viewer`: ``rerun --serve-web``, the page over HTTP and the
recordings over gRPC), which ``--serve`` also starts for a run to stream to. All listen on :data:`LOOPBACK`
unless ``view --bind`` names another address.
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

from ..errors import ArAnchorError, InputError, printable

__all__ = [
    "LOCAL_VIEWER_URL",
    "LOOPBACK",
    "VIEWER_PORT",
    "WebViewer",
    "has_display",
    "is_loopback",
    "open_native_viewer",
    "require_viewer",
    "serve_web_viewer",
    "spawn_local_viewer",
    "stop_process",
    "viewer_address",
]

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


# ---------------------------------------------------------------------------------------------- viewing
# ``ar-anchor view`` and ``--serve``: the viewer as a foreground process of the command (native), or the
# rerun CLI's web server (``rerun --serve-web``: the web viewer's files over HTTP plus a gRPC server that the
# browser reads the recording from). Both listen on :data:`LOOPBACK` unless the user names another address.

LOOPBACK = "127.0.0.1"
WEB_VIEWER_PORT = 9090  # rerun's default HTTP port of the web viewer
_SERVE_START_TIMEOUT_S = 30.0  # how long the web server gets to listen (it loads the files meanwhile)
_STOP_TIMEOUT_S = 5.0


def has_display() -> bool:
    """Can a native window open here? On Linux only with DISPLAY or WAYLAND_DISPLAY set."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def is_loopback(address: str) -> bool:
    """Is ``address`` (an IP address or ``localhost``) reachable from this machine only?"""
    import ipaddress

    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


def _bind_option(address: str) -> list[str]:
    """``--bind ADDRESS`` for the rerun CLI (whose own default is every interface, 0.0.0.0). The one
    place a command line takes a bind address that is not a constant: :data:`LOOPBACK` unless the user
    gave ``--bind`` (``ar-anchor view``), which the CLI warns about."""
    return ["--bind", address]


def _url_host(address: str) -> str:
    """The host to put in a URL for a server bound to ``address`` (an unspecified address: this machine)."""
    if address in ("0.0.0.0", "::", ""):
        return LOOPBACK
    return f"[{address}]" if ":" in address else address


def _port_free(address: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((address, port))
        except OSError:
            return False
    return True


def _pick_port(address: str, port: int | None, default: int, option: str) -> int:
    """``port`` (the user's: InputError naming ``option`` when it is taken), else ``default`` when free,
    else one the system says is free."""
    if port is not None:
        if port and not _port_free(address, port):
            raise InputError(f"{option} {port}: {address}:{port} is in use (give another port, or leave it out)")
        return port or _free_port(address)
    if _port_free(address, default):
        return default
    chosen = _free_port(address if ":" not in address else LOOPBACK)
    log.info("%s:%d is taken (another viewer?); using port %d", address, default, chosen)
    return chosen


def _quiet_output() -> int | None:
    """The viewer's own output: shown with -vv (ar_anchor's debug logging), else dropped."""
    return None if logging.getLogger("ar_anchor").isEnabledFor(logging.DEBUG) else subprocess.DEVNULL


def _require_executable() -> str:
    """The viewer binary itself when rerun-sdk's ``rerun_cli`` has it (``rerun`` beside the interpreter is a
    Python launcher that runs it as a child: stopping the launcher alone would leave the viewer running),
    else ``rerun`` as :func:`_viewer_executable` finds it; InputError when there is none."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        binary = Path(spec.origin).with_name("rerun")
        if binary.is_file() and os.access(binary, os.X_OK):
            return str(binary)
    executable = _viewer_executable()
    if executable is None:
        raise InputError("no rerun viewer found: the `rerun` program comes with rerun-sdk (pip install rerun-sdk)")
    return executable


class WebViewer:
    """The rerun CLI serving the web viewer: its process, the page to open (:attr:`url`) and the gRPC
    server the page reads from (:attr:`grpc_url`, where a run streams to). :meth:`stop` ends it."""

    def __init__(self, process: subprocess.Popen[bytes], *, url: str, grpc_url: str) -> None:
        self.process = process
        self.url = url
        self.grpc_url = grpc_url

    def wait(self) -> int:
        """Block until the server exits (Ctrl-C: ``KeyboardInterrupt``); its exit status."""
        return self.process.wait()

    def stop(self) -> None:
        """End the server (killed when it does not exit within a few seconds)."""
        stop_process(self.process)


def stop_process(process: subprocess.Popen[bytes]) -> None:
    """Terminate ``process`` (started in a session of its own) with its process group, and wait for it;
    killed when it does not exit within a few seconds. The group, in case ``process`` is a launcher (``rerun``
    beside the interpreter runs the viewer binary as its child and does not pass a signal on)."""
    import signal

    for signum in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, signum)
        except (ProcessLookupError, PermissionError):  # the group is gone
            if process.poll() is None:
                process.send_signal(signum)
        try:
            process.wait(_STOP_TIMEOUT_S)
            return
        except subprocess.TimeoutExpired:
            continue


def serve_web_viewer(
    files: list[Path] | tuple[Path, ...] = (),
    *,
    bind: str = LOOPBACK,
    web_port: int | None = None,
    grpc_port: int | None = None,
    options: tuple[str, str] = ("--port", "--grpc-port"),
) -> WebViewer:
    """Start ``rerun --serve-web`` on ``bind`` (both its ports): the web viewer over HTTP on ``web_port``
    (default 9090, or a free port when taken) and a gRPC server on ``grpc_port`` (default 9876, likewise)
    that holds ``files`` (none: it waits for a run to stream to it). Returns once both ports listen.

    Not ``rr.serve_grpc`` / ``rr.serve_web_viewer``: in rerun 0.41 they listen on every interface and take
    no bind address. ``options`` name the two port options in errors."""
    executable = _require_executable()
    web_port = _pick_port(bind, web_port, WEB_VIEWER_PORT, options[0])
    grpc_port = _pick_port(bind, grpc_port, VIEWER_PORT, options[1])
    if web_port == grpc_port:
        raise InputError(f"{options[0]} and {options[1]}: two different ports are needed, got {web_port} twice")
    command = [
        executable,
        "--serve-web",
        *_bind_option(bind),
        "--port",
        str(grpc_port),
        "--web-viewer-port",
        str(web_port),
        *(str(path) for path in files),
    ]
    output = _quiet_output()
    try:
        process = subprocess.Popen(  # noqa: S603 - a fixed command line, no shell
            command, stdin=subprocess.DEVNULL, stdout=output, stderr=output, start_new_session=True
        )
    except OSError as err:
        raise InputError(f"could not start the rerun web viewer ({err.strerror or err})") from None
    host = _url_host(bind)
    grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
    from urllib.parse import quote

    viewer = WebViewer(process, url=f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}", grpc_url=grpc_url)
    connect_host = host.strip("[]")
    deadline = time.monotonic() + _SERVE_START_TIMEOUT_S
    try:
        while process.poll() is None:
            if _listening(connect_host, grpc_port) and _listening(connect_host, web_port):
                return viewer
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
    except BaseException:
        viewer.stop()
        raise
    viewer.stop()
    status = process.returncode
    raise ArAnchorError(
        f"the rerun web viewer did not start listening on {bind} ports {web_port} and {grpc_port}"
        + (f" (it exited with status {status}; -vv shows its output)" if status is not None else "")
    )


def open_native_viewer(files: list[Path], *, bind: str = LOOPBACK, port: int | None = None) -> subprocess.Popen[bytes]:
    """Start the native rerun viewer on ``files`` (its own gRPC server on ``bind``, port ``port`` or a
    free one) and return its process; InputError when no window can open here (no display)."""
    if not has_display():
        raise InputError("no display here (DISPLAY / WAYLAND_DISPLAY unset): use --web to view in a browser")
    executable = _require_executable()
    port = _pick_port(bind, port, VIEWER_PORT, "--grpc-port")
    command = [executable, *_bind_option(bind), "--port", str(port), *(str(path) for path in files)]
    output = _quiet_output()
    try:
        return subprocess.Popen(  # noqa: S603 - a fixed command line, no shell
            command, stdin=subprocess.DEVNULL, stdout=output, stderr=output, start_new_session=True
        )
    except OSError as err:
        raise InputError(f"could not start the rerun viewer ({err.strerror or err})") from None
