"""A screenshot of a recording in the rerun web viewer, on a machine without a display (``ar-anchor view
--screenshot``).

How: the recording's files (every part of a split run: ``recording.rrd``, ``recording.part2.rrd``, ...) are
served over HTTP on 127.0.0.1 from a thread of this process; the web viewer's page comes from the rerun CLI
(:func:`~.viewer.serve_web_viewer`, also on 127.0.0.1), and headless Chromium (:mod:`.browser`; WebGL on the
CPU, SwiftShader) opens it with every part (``?url=<part>&url=<part>...``: the parts share a recording id, so
the viewer merges them into one recording). Once the viewer has loaded them all, the layout asked for
(:data:`LAYOUT_NAMES`, a blueprint with the time panel paused on the ``frame`` timeline) is loaded after them, so
that it replaces the layout stored in the recording instead of racing it. The time cursor goes to the frame
through the viewer's control API (``window._handle.viewer_control``, a protobuf ``SetTimeCursorRequest``;
experimental in rerun 0.41), and the shot is taken once the page has stopped changing. The cursor is read
back before and after the shot: a viewer that moved it (it follows new data while a recording loads) is a
failure, never a picture of another frame.

The web viewer's control API speaks protobuf (``rerun.viewer_control.v1alpha1``): the few fields used here are
read with a minimal wire-format parser and written by hand, so that no protobuf package is needed.
"""

from __future__ import annotations

import functools
import http.server
import logging
import shutil
import tempfile
import threading
import time
import urllib.parse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ArAnchorError, InputError, printable

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "LAYOUT_NAMES",
    "ScreenshotError",
    "Shot",
    "encode_png",
    "layout_blueprint",
    "require_chromium",
    "take_screenshot",
]

log = logging.getLogger(__name__)

#: The layouts a screenshot can show (``ar-anchor view --layout``; what each shows: the command's help).
LAYOUT_NAMES = ("full", "overlay", "camera", "3d")

INSTALL_HINT = "install it (apt install chromium) or name it with --chromium PATH"
_POLL_S = 0.25  # how often the viewer's state is read while it loads (a cheap call)
_NO_FRAMES_S = 15.0  # loaded this long without a `frame` timeline: the recording has none
_QUIET_S = 6.0  # the page unchanged this long: the picture has settled


class ScreenshotError(ArAnchorError):
    """The viewer or Chromium failed, or did not reach the frame: one line saying which."""


@dataclass(frozen=True)
class Shot:
    """A screenshot (BGR) of ``frame``, in a recording whose ``frame`` timeline spans ``frames`` (first, last)."""

    image: np.ndarray
    frame: int
    frames: tuple[int, int]


# ---------------------------------------------------------------------------------------------- layouts
def layout_blueprint(layout: str) -> Any:
    """The blueprint of ``layout`` (:data:`LAYOUT_NAMES`) with a collapsed time panel paused on ``frame``."""
    import rerun.blueprint as rrb

    from .blueprints import PROJECTED, run_blueprint

    if layout == "full":
        root = run_blueprint().root_container
    elif layout == "overlay":
        root = rrb.Spatial2DView(origin="world/camera", contents=list(PROJECTED), name="AR overlay")
    elif layout == "camera":
        root = rrb.Spatial2DView(origin="world/camera", contents="$origin/**", name="Camera")
    elif layout == "3d":
        root = rrb.Spatial3DView(origin="world", name="3D scene", line_grid=rrb.LineGrid3D(visible=True, spacing=0.1))
    else:
        raise InputError(f"--layout {printable(layout)}: not a layout (any of {', '.join(LAYOUT_NAMES)})")
    time_panel = rrb.TimePanel(state="collapsed", timeline="frame", play_state="paused")
    return rrb.Blueprint(root, time_panel, collapse_panels=True)


# ---------------------------------------------------------------------------------------------- serving
class _Files(http.server.SimpleHTTPRequestHandler):
    """Static files, readable from the viewer's origin (another port: CORS), without a request log."""

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")  # the server listens on 127.0.0.1 only
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (the base class's name)
        """Quiet."""


def _serve(directory: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    """Serve ``directory`` on 127.0.0.1 from a thread; the server and its base URL."""
    handler = functools.partial(_Files, directory=str(directory))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, name="screenshot-files", daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


# ---------------------------------------------------------------------------------------------- viewer control
def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it."""
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, pos


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1
    while True:
        out.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def proto_fields(data: bytes) -> dict[int, list[Any]]:
    """A protobuf message's fields: number -> values (ints, or bytes for length-delimited ones)."""
    fields: dict[int, list[Any]] = {}
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        number, kind = key >> 3, key & 7
        value: Any
        if kind == 0:
            value, pos = _varint(data, pos)
        elif kind == 2:
            length, pos = _varint(data, pos)
            value, pos = data[pos : pos + length], pos + length
        elif kind in (1, 5):
            size = 8 if kind == 1 else 4
            value, pos = int.from_bytes(data[pos : pos + size], "little"), pos + size
        else:
            raise ScreenshotError(f"the viewer's state: protobuf wire type {kind} not understood (rerun changed?)")
        fields.setdefault(number, []).append(value)
    return fields


def _one(fields: dict[int, list[Any]], number: int, default: Any = None) -> Any:
    """The (last) value of field ``number``."""
    return fields.get(number, [default])[-1]


def _signed(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def parse_viewer_state(state_bytes: bytes) -> dict[str, Any]:
    """What a ``GetViewerStateResponse`` says of the active recording: ``loading`` (sources still loading),
    ``frames`` (the ``frame`` timeline's first and last, or None) and ``cursor`` (the time cursor on ``frame``,
    or None when it is on another timeline)."""
    state = proto_fields(state_bytes)
    active = _one(state, 2, b"")
    result: dict[str, Any] = {"started": True, "loading": len(state.get(7, [])), "frames": None, "cursor": None}
    for raw in state.get(3, []):  # ViewerRecording: store_id 1, timelines 2, current_time 3
        recording = proto_fields(raw)
        store = _one(recording, 1, b"")
        if (active and store != active) or not bytes(store).startswith(b"Recording:"):
            continue
        for timeline_raw in recording.get(2, []):  # ViewerTimeline: timeline 1 (name 1), time_range 3
            timeline = proto_fields(timeline_raw)
            if _one(proto_fields(_one(timeline, 1, b"")), 1) == b"frame" and 3 in timeline:
                span = proto_fields(_one(timeline, 3))
                result["frames"] = (_signed(int(_one(span, 1, 0))), _signed(int(_one(span, 2, 0))))
        cursor = proto_fields(_one(recording, 3, b""))  # TimeCursor: timeline 1, time 3 (TimelineTime: time 1)
        if _one(proto_fields(_one(cursor, 1, b"")), 1) == b"frame" and 3 in cursor:
            result["cursor"] = _signed(int(_one(proto_fields(_one(cursor, 3)), 1, 0)))
    return result


def _field(number: int, payload: bytes) -> bytes:
    """Length-delimited field ``number`` holding ``payload`` (a string or a message)."""
    return _encode_varint((number << 3) | 2) + _encode_varint(len(payload)) + payload


def set_time_cursor_request(frame: int) -> bytes:
    """``ViewerControlRequest.set_time_cursor`` (6): timeline ``frame`` (2, its name 1), time (3, TimelineTime 1)."""
    request = _field(2, _field(1, b"frame")) + _field(3, b"\x08" + _encode_varint(frame))
    return _field(6, request)


class _Viewer:
    """The web viewer in a page of ``browser``: its state and controls."""

    def __init__(self, browser: Any) -> None:
        self.browser = browser

    def state(self) -> dict[str, Any]:
        encoded = self.browser.evaluate(
            "window._handle ? Array.from(window._handle.viewer_state(), b => String.fromCharCode(b)).join('') : null"
        )
        if encoded is None:
            return {"started": False}
        return parse_viewer_state(str(encoded).encode("latin-1"))

    def add(self, url: str) -> None:
        """Load one more source (a recording or a blueprint) by URL."""
        self.browser.evaluate(f"(window._handle.add_receiver({_js_string(url)}), true)")

    def set_frame(self, frame: int) -> None:
        array = ",".join(str(b) for b in set_time_cursor_request(frame))
        self.browser.evaluate(f"window._handle.viewer_control(new Uint8Array([{array}])).then(() => true)")


def _js_string(text: str) -> str:
    import json

    return json.dumps(text)


# ---------------------------------------------------------------------------------------------- the shot
def require_chromium(explicit: str | None = None) -> str:
    """The Chromium binary (``explicit``, else one on PATH), or an :class:`InputError` saying how to install it."""
    from .browser import find_chromium

    binary = find_chromium(explicit)
    if binary is None:
        which = f"--chromium {printable(explicit)}: not found" if explicit else "no headless Chromium found"
        raise InputError(f"a screenshot needs Chromium, {which}: {INSTALL_HINT}")
    return binary


def take_screenshot(
    files: Sequence[Path],
    *,
    frame: int | None = None,
    layout: str = "full",
    size: tuple[int, int] = (1600, 900),
    timeout_s: float = 300.0,
    chromium: str | None = None,
    say: Callable[[str], None] | None = None,
    keep_log: Path | None = None,
) -> Shot:
    """The web viewer showing ``files`` (a recording's parts, in order) in ``layout`` at ``frame`` (default:
    the middle of the ``frame`` timeline), in a ``size`` (width, height) page of headless Chromium
    (``chromium``: its binary; default the first of :data:`~.browser.CHROMIUM_NAMES` on PATH).

    :class:`InputError` when there is no Chromium, the layout is unknown or ``frame`` is outside the
    recording's frames; :class:`ScreenshotError` when the viewer does not load the recording, reach the frame
    or stay on it within ``timeout_s``. ``say`` is told each step (a line); ``keep_log`` gets Chromium's log."""
    from .browser import Browser, BrowserError
    from .viewer import serve_web_viewer

    binary = require_chromium(chromium)
    blueprint = layout_blueprint(layout)
    say = say or (lambda _line: None)
    deadline = time.monotonic() + timeout_s
    with tempfile.TemporaryDirectory(prefix="ar_anchor_shot_") as tmp:
        work = Path(tmp)
        served = work / "served"
        served.mkdir()
        names = []
        for index, path in enumerate(files):
            name = f"part{index + 1}.rrd"
            (served / name).symlink_to(Path(path).resolve())
            names.append(name)
        blueprint.save("ar_anchor", served / "layout.rbl")
        files_server, base = _serve(served)
        viewer_server = None
        browser = None
        log_path = work / "chromium.log"
        try:
            viewer_server = serve_web_viewer(web_port=0, grpc_port=0)
            page = viewer_server.url.split("?", 1)[0]
            query = "&".join(f"url={urllib.parse.quote(f'{base}/{name}', safe='')}" for name in names)
            try:
                browser = Browser(size, log_path, binary=binary, profile=work / "profile", dark=True)
                browser.navigate(f"{page}?{query}")
                return _shoot(_Viewer(browser), browser, f"{base}/layout.rbl", frame, deadline, say)
            except BrowserError as err:
                raise ScreenshotError(f"Chromium: {err}{_log_tail(log_path)}") from None
            except ScreenshotError as err:
                raise ScreenshotError(f"{err}{_log_tail(log_path)}") from None
        finally:
            if browser is not None:
                browser.close()
            if viewer_server is not None:
                viewer_server.stop()
            files_server.shutdown()
            files_server.server_close()
            if keep_log is not None and log_path.exists():
                shutil.copy(log_path, keep_log)


def _log_tail(log_path: Path) -> str:
    """`` (Chromium's log ends: ...)`` with its last lines, when logged at debug level (it is noisy)."""
    if not log.isEnabledFor(logging.DEBUG) or not log_path.exists():
        return ""
    tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
    return f" (Chromium's log ends: {' | '.join(tail) or 'empty'})"


def _shoot(viewer: _Viewer, browser: Any, layout_url: str, frame: int | None, deadline: float, say: Any) -> Shot:
    say("loading the recording in the web viewer")
    frames = _wait_loaded(viewer, deadline)
    first, last = frames
    wanted = (first + last) // 2 if frame is None else frame
    if not first <= wanted <= last:
        raise InputError(f"--frame {wanted}: not in the recording (its frames are {first}..{last})")
    viewer.add(layout_url)  # after the recording: the layout asked for replaces the one stored in it
    _wait_loaded(viewer, deadline)
    _go_to(viewer, wanted, deadline)
    say(f"time cursor on frame {wanted} (frames {first}..{last})")
    image = _settled(browser, deadline)
    state = viewer.state()
    if state.get("cursor") != wanted or state.get("loading"):
        raise ScreenshotError(
            f"the viewer left frame {wanted} while the picture settled (now at {state.get('cursor')}): no screenshot"
        )
    return Shot(image=image, frame=wanted, frames=frames)


def _wait_loaded(viewer: _Viewer, deadline: float) -> tuple[int, int]:
    """Wait until the viewer has started and loaded every source; the ``frame`` timeline's range."""
    last = None
    loaded_since = None  # when the viewer last said it had loaded everything, yet had no frame timeline
    while True:
        state = viewer.state()
        if state != last:
            log.debug("viewer: %s", state)
            last = state
        if state.get("started") and not state["loading"]:
            if state["frames"] is not None:
                return state["frames"]
            loaded_since = loaded_since or time.monotonic()
            if time.monotonic() - loaded_since > _NO_FRAMES_S:
                raise ScreenshotError("the recording has no `frame` timeline (not an ar-anchor run's recording?)")
        else:
            loaded_since = None
        if time.monotonic() > deadline:
            raise ScreenshotError(f"the viewer did not finish loading the recording within --timeout (last: {last})")
        time.sleep(_POLL_S)


def _go_to(viewer: _Viewer, frame: int, deadline: float) -> None:
    """Move the time cursor to ``frame`` and wait until the viewer says it is there."""
    viewer.set_frame(frame)
    while viewer.state().get("cursor") != frame:
        if time.monotonic() > deadline:
            raise ScreenshotError(f"the viewer's time cursor did not move to frame {frame} within --timeout")
        time.sleep(_POLL_S)
        viewer.set_frame(frame)


def _settled(browser: Any, deadline: float, quiet_s: float = _QUIET_S) -> np.ndarray:
    """A screenshot taken once the page has not changed for ``quiet_s`` seconds (or at ``deadline``)."""
    import numpy as np

    previous, still_since = browser.screenshot(), time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(1.0)
        image = browser.screenshot()
        if image.shape != previous.shape or np.any(image != previous):
            previous, still_since = image, time.monotonic()
        elif time.monotonic() - still_since >= quiet_s:
            break
    return previous


def encode_png(image: np.ndarray, max_bytes: int | None = None) -> bytes:
    """``image`` as PNG; with ``max_bytes``, made smaller, then given fewer colour levels per channel, until it
    fits (:class:`ScreenshotError` when even half size with 16 levels does not)."""
    import cv2
    import numpy as np

    scales = (1.0, 0.9, 0.8, 0.7, 0.6, 0.5) if max_bytes is not None else (1.0,)
    for scale in scales:
        resized = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        for levels in (256, 64, 32, 16) if max_bytes is not None else (256,):
            step = 256 // levels
            reduced = resized if levels == 256 else (resized // step * step + step // 2).astype(np.uint8)
            ok, png = cv2.imencode(".png", reduced, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            if ok and (max_bytes is None or len(png) <= max_bytes):
                return png.tobytes()
    raise ScreenshotError(f"the PNG stays over --max-kb {max_bytes // 1000 if max_bytes else 0} even at half size")
