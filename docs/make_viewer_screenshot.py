r"""Screenshot the Rerun web viewer showing a recording's "AR overlay" view, on a headless machine.

Usage (the project's venv active, Debian's Chromium installed: ``apt-get install chromium``)::

    python docs/make_viewer_screenshot.py --make demo --layout overlay --frame 10 \
        --out docs/images/overlay_viewer_demo.png
    python docs/make_viewer_screenshot.py --make real --layout overlay --out docs/images/overlay_viewer_real.png
    python docs/make_viewer_screenshot.py --recording run/recording.rrd --out shot.png --frame 120

(the docs' two images; the demo's middle frame shows its markers at about 20 px, hence ``--frame 10``).

``--make demo`` records ``ar-anchor demo --frames 60``; ``--make real`` replays
``../shared/realdata/aruco_testdata/chessboard/chessboard.avi`` (``--realdata DIR`` or ``AR_ANCHOR_REALDATA``
name another copy of ``realdata``); ``--recording FILE.rrd`` takes an existing recording instead.

How: the recording and a blueprint (the run's own layout, ``run_blueprint()``, whose first tab is "AR
overlay", or with ``--layout overlay`` that view alone; plus a time panel on the ``frame`` timeline,
paused) are served over HTTP on 127.0.0.1; the web viewer (``rr.serve_web_viewer``) opens both
(``?url=<rrd>&url=<rbl>``) in headless Chromium, which renders with its SwiftShader software rasteriser
(WebGL; the viewer says "Software rasterizer").
Chromium is driven over the DevTools protocol (``--remote-debugging-pipe``, standard library only):
the script waits until the viewer has loaded everything, moves the time cursor to ``--frame`` (default:
the middle of the ``frame`` timeline) through the viewer's control API (``window._handle.viewer_control``,
a protobuf ``SetTimeCursorRequest``; experimental in rerun 0.41), checks that the cursor is there, waits
for the picture to settle, and writes the PNG: the whole viewer (``--size``), or a part of it (``--crop``),
shrunk (``cv2``: smaller, then fewer colour levels) until it is at most ``--max-kb``.

The recording is served on 127.0.0.1 only; ``rr.serve_web_viewer`` (no bind option) serves the viewer's
static files on all interfaces while the script runs.

A load takes about a minute on two cores (``--timeout`` bounds it). Exit status: 0 written; 1 the viewer,
Chromium or the recording failed (the message says which, with the end of Chromium's log; ``--keep DIR``
keeps the recording, the raw PNG and that log); 2 bad arguments or Chromium missing (``--chromium PATH``
names another binary).
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
sys.path.insert(0, str(REPO))  # the DevTools driver is the browser test's (tests/browser.py)
from tests.browser import Browser, BrowserError  # noqa: E402

ShotError = BrowserError  # a step failed; the message says which, in one line


# ---------------------------------------------------------------------------------------------- recording
def make_recording(kind: str, out_dir: Path, realdata: Path) -> Path:
    """Record ``kind`` (``demo``: the synthetic demo, 60 frames; ``real``: chessboard.avi) into ``out_dir``."""
    ar_anchor = shutil.which("ar-anchor", path=str(Path(sys.executable).parent)) or shutil.which("ar-anchor")
    if ar_anchor is None:
        raise ShotError("ar-anchor is not on PATH: activate the project's venv (. .venv/bin/activate)")
    if kind == "demo":
        args = ["demo", "--frames", "60"]
    else:
        data = realdata / "aruco_testdata" / "chessboard"
        if not (data / "chessboard.avi").is_file():
            raise ShotError(f"{data / 'chessboard.avi'}: not found (--realdata names the realdata directory)")
        args = ["replay", str(data / "chessboard.avi"), "--camera", str(data / "intrinsics.yml")]
        args += ["--dictionary", "DICT_ARUCO_ORIGINAL", "--marker-length", "0.034"]
    print(f"recording: ar-anchor {' '.join(args)} --out {out_dir}", flush=True)
    done = subprocess.run([ar_anchor, "-q", *args, "--out", str(out_dir)], capture_output=True, text=True)
    if done.returncode != 0:
        raise ShotError(f"ar-anchor {args[0]} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    return out_dir / "recording.rrd"


def write_blueprint(path: Path, layout: str = "run") -> None:
    """The run's layout (its first tab is "AR overlay"), or (``overlay``) its "AR overlay" view alone, as the
    view's maximise button shows it; either with the time panel on ``frame``, paused."""
    import rerun.blueprint as rrb

    from ar_anchor.viz.blueprints import PROJECTED, run_blueprint

    if layout == "run":
        root = run_blueprint().root_container
    else:
        root = rrb.Spatial2DView(origin="world/camera", contents=list(PROJECTED), name="AR overlay")
    time_panel = rrb.TimePanel(state="collapsed", timeline="frame", play_state="paused")
    rrb.Blueprint(root, time_panel, collapse_panels=True).save("ar_anchor", path)


# ---------------------------------------------------------------------------------------------- serving
def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Files(http.server.SimpleHTTPRequestHandler):
    """Static files, readable from the viewer's origin (another port: CORS), without a request log."""

    def end_headers(self) -> None:
        """Allow any origin: the server only listens on 127.0.0.1."""
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (the base class's name)
        """Quiet."""


def serve_files(directory: Path) -> tuple[http.server.ThreadingHTTPServer, int]:
    """Serve ``directory`` on 127.0.0.1 from a thread; returns the server and its port."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Files, directory=str(directory)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, int(server.server_address[1])


# ---------------------------------------------------------------------------------------------- chromium
def find_chromium(explicit: str | None) -> str:
    """The Chromium binary: ``explicit``, or the first of :data:`CHROMIUM_NAMES` on PATH."""
    for name in [explicit] if explicit else CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    wanted = explicit or " / ".join(CHROMIUM_NAMES)
    raise ShotError(f"Chromium not found ({wanted}): install it (apt-get install chromium) or pass --chromium PATH")


# ---------------------------------------------------------------------------------------------- viewer control
# The web viewer's control API takes and returns protobuf (rerun.viewer_control.v1alpha1, experimental):
# the few fields used here are read with a minimal wire-format parser and written by hand.
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


def proto_fields(data: bytes) -> dict[int, list]:
    """A protobuf message's fields: number -> values (ints, or bytes for length-delimited ones)."""
    fields: dict[int, list] = {}
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        number, kind = key >> 3, key & 7
        if kind == 0:
            value, pos = _varint(data, pos)
        elif kind == 2:
            length, pos = _varint(data, pos)
            value, pos = data[pos : pos + length], pos + length
        elif kind in (1, 5):
            size = 8 if kind == 1 else 4
            value, pos = int.from_bytes(data[pos : pos + size], "little"), pos + size
        else:
            raise ShotError(f"viewer state: protobuf wire type {kind} not understood")
        fields.setdefault(number, []).append(value)
    return fields


def _one(fields: dict[int, list], number: int, default: object = None) -> object:
    """The (last) value of field ``number``."""
    return fields.get(number, [default])[-1]


def _timeline_time(message: bytes) -> int:
    """``TimelineTime.time`` (a sequence number on ``frame``), a signed int64."""
    value = int(_one(proto_fields(message), 1, 0))
    return value - (1 << 64) if value >= 1 << 63 else value


def viewer_state(browser: Browser) -> dict:
    """What the viewer shows: loading (sources still loading), frames (the ``frame`` range), cursor (on frame)."""
    encoded = browser.evaluate(
        "window._handle ? Array.from(window._handle.viewer_state(), b => String.fromCharCode(b)).join('') : null"
    )
    if encoded is None:
        return {"started": False}
    state = proto_fields(str(encoded).encode("latin-1"))  # GetViewerStateResponse
    active = _one(state, 2, b"")
    result: dict = {"started": True, "loading": len(state.get(7, [])), "frames": None, "cursor": None}
    for raw in state.get(3, []):  # ViewerRecording: store_id 1, timelines 2, current_time 3
        recording = proto_fields(raw)
        store = _one(recording, 1, b"")
        if (active and store != active) or not bytes(store).startswith(b"Recording:"):
            continue
        for timeline_raw in recording.get(2, []):  # ViewerTimeline: timeline 1 (name 1), time_range 3
            timeline = proto_fields(timeline_raw)
            if _one(proto_fields(_one(timeline, 1, b"")), 1) == b"frame" and 3 in timeline:
                span = proto_fields(_one(timeline, 3))
                result["frames"] = (int(_one(span, 1, 0)), int(_one(span, 2, 0)))
        cursor = proto_fields(_one(recording, 3, b""))  # TimeCursor: timeline 1, time 3
        if _one(proto_fields(_one(cursor, 1, b"")), 1) == b"frame" and 3 in cursor:
            result["cursor"] = _timeline_time(_one(cursor, 3))
    return result


def _length_delimited(number: int, payload: bytes) -> bytes:
    """Field ``number`` holding ``payload`` (a string or message)."""
    key, length, out = (number << 3) | 2, len(payload), bytearray()
    for value in (key, length):
        while True:
            out.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
            value >>= 7
            if not value:
                break
    return bytes(out) + payload


def set_frame(browser: Browser, frame: int) -> None:
    """Move the active recording's time cursor to ``frame`` on the ``frame`` timeline (SetTimeCursorRequest)."""
    time_value = bytearray([0x08])  # TimelineTime.time = frame (varint)
    value = frame & ((1 << 64) - 1)
    while True:
        time_value.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            break
    request = _length_delimited(2, _length_delimited(1, b"frame")) + _length_delimited(3, bytes(time_value))
    envelope = _length_delimited(6, request)  # ViewerControlRequest.set_time_cursor
    array = ",".join(str(b) for b in envelope)
    browser.evaluate(f"window._handle.viewer_control(new Uint8Array([{array}])).then(() => true)")


# ---------------------------------------------------------------------------------------------- the shot
def wait_loaded(browser: Browser, deadline: float) -> tuple[int, int]:
    """Wait until the viewer has started and loaded everything; returns the ``frame`` timeline's range."""
    last = None
    while time.monotonic() < deadline:
        state = viewer_state(browser)
        if state != last:
            print(f"  viewer: {state}", flush=True)
            last = state
        if state.get("started") and not state["loading"] and state["frames"] is not None:
            return state["frames"]
        time.sleep(2.0)
    raise ShotError(f"the viewer did not finish loading within --timeout (last state: {last})")


def settled_screenshot(browser: Browser, deadline: float, quiet_s: float = 6.0) -> np.ndarray:
    """A screenshot taken once the page has not changed for ``quiet_s`` seconds (or at ``deadline``)."""
    previous, still_since = browser.screenshot(), time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(2.0)
        image = browser.screenshot()
        if image.shape != previous.shape or np.any(image != previous):
            previous, still_since = image, time.monotonic()
        elif time.monotonic() - still_since >= quiet_s:
            break
    return previous


def take(rrd: Path, args: argparse.Namespace, work: Path) -> np.ndarray:
    """Serve ``rrd``, open it in the web viewer in headless Chromium, go to the frame and screenshot."""
    import rerun as rr

    chromium = find_chromium(args.chromium)
    served = work / "served"
    served.mkdir()
    os.symlink(rrd.resolve(), served / "recording.rrd")
    write_blueprint(served / "shot.rbl", args.layout)
    files, files_port = serve_files(served)
    viewer_port = free_port()
    rr.serve_web_viewer(web_port=viewer_port, open_browser=False)
    base = f"http://127.0.0.1:{files_port}"
    query = "&".join(f"url={urllib.parse.quote(f'{base}/{name}', safe='')}" for name in ("recording.rrd", "shot.rbl"))
    url = f"http://127.0.0.1:{viewer_port}/?{query}"
    print(f"viewer: {url}", flush=True)
    deadline = time.monotonic() + args.timeout
    log_path = work / "chromium.log"
    browser = Browser(args.size, log_path, binary=chromium, profile=work / "profile", dark=True)
    try:
        browser.send("Page.navigate", {"url": url})
        first, last = wait_loaded(browser, deadline)
        frame = args.frame if args.frame is not None else (first + last) // 2
        if not first <= frame <= last:
            raise ShotError(f"--frame {frame}: the recording's frames are {first}..{last}")
        set_frame(browser, frame)
        while viewer_state(browser)["cursor"] != frame:
            if time.monotonic() > deadline:
                raise ShotError(f"the viewer's time cursor did not move to frame {frame}")
            time.sleep(1.0)
        print(f"  time cursor on frame {frame} (frames {first}..{last})", flush=True)
        return settled_screenshot(browser, deadline)
    except ShotError as err:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-3:] if log_path.exists() else []
        raise ShotError(f"{err} (Chromium's log ends: {' | '.join(tail) or 'empty'})") from None
    finally:
        browser.close()
        files.shutdown()


def shrink(image: np.ndarray, crop: tuple[int, int, int, int] | None, max_bytes: int) -> bytes:
    """``image`` cropped (x, y, w, h) and encoded as PNG, made smaller, then given fewer colour levels per
    channel, until the PNG is at most ``max_bytes``."""
    if crop is not None:
        x, y, w, h = crop
        image = image[y : y + h, x : x + w]
    for scale in (1.0, 0.9, 0.8, 0.7, 0.6, 0.5):
        resized = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        for levels in (256, 64, 32, 16):
            step = 256 // levels
            reduced = resized if levels == 256 else (resized // step * step + step // 2).astype(np.uint8)
            ok, png = cv2.imencode(".png", reduced, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            if ok and len(png) <= max_bytes:
                print(f"  PNG: {reduced.shape[1]}x{reduced.shape[0]}, {levels} levels a channel", flush=True)
                return png.tobytes()
    raise ShotError(f"the PNG stays over --max-kb {max_bytes // 1000} even at half size: pass a --crop")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (see the module's docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--recording", type=Path, metavar="FILE.rrd", help="an existing recording")
    source.add_argument("--make", choices=("demo", "real"), help="record the demo (60 frames) or chessboard.avi")
    parser.add_argument("--out", type=Path, required=True, metavar="PNG", help="the screenshot to write")
    parser.add_argument("--frame", type=int, help="frame to show (default: the middle of the frame timeline)")
    parser.add_argument("--size", default="1600x900", help="browser window, WIDTHxHEIGHT (default 1600x900)")
    parser.add_argument("--crop", help="keep X,Y,W,H of the window (pixels)")
    parser.add_argument(
        "--layout", choices=("run", "overlay"), default="run", help="the run's layout, or the AR overlay view alone"
    )
    parser.add_argument("--max-kb", type=int, default=300, help="largest PNG, kilobytes (default 300)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds for the viewer (default 300)")
    parser.add_argument("--chromium", help="the Chromium binary (default: chromium on PATH)")
    default_realdata = os.environ.get("AR_ANCHOR_REALDATA", str(REPO.parent / "shared" / "realdata"))
    parser.add_argument("--realdata", type=Path, default=Path(default_realdata), help="for --make real")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="also keep the recording and the raw PNG in DIR")
    args = parser.parse_args(argv)
    try:
        args.size = tuple(int(v) for v in args.size.lower().split("x"))
        args.crop = tuple(int(v) for v in args.crop.split(",")) if args.crop else None
        assert len(args.size) == 2 and min(args.size) > 0 and (args.crop is None or len(args.crop) == 4)
    except (ValueError, AssertionError):
        parser.error("--size is WIDTHxHEIGHT and --crop X,Y,W,H, positive integers")
    if args.recording is not None and not args.recording.is_file():
        parser.error(f"--recording {args.recording}: no such file")
    return args


def main(argv: list[str] | None = None) -> int:
    """Make (or take) the recording, screenshot it in the viewer and write the PNG; the exit status."""
    args = parse_args(argv)
    try:
        find_chromium(args.chromium)
    except ShotError as err:
        print(f"make_viewer_screenshot: {err}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="viewer_shot_") as tmp:
        work = Path(tmp)
        try:
            rrd = args.recording or make_recording(args.make, work / "run", args.realdata)
            image = take(rrd, args, work)
            png = shrink(image, args.crop, args.max_kb * 1000)
        except ShotError as err:
            print(f"make_viewer_screenshot: {err}", file=sys.stderr)
            return 1
        if args.keep is not None:
            args.keep.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(args.keep / "raw.png"), image)
            if args.recording is None:
                shutil.copy(rrd, args.keep / "recording.rrd")
            shutil.copy(work / "chromium.log", args.keep / "chromium.log")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(png)
    print(f"wrote {args.out} ({len(png) // 1000} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
