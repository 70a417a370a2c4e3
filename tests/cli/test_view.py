"""`ar-anchor view` and `--serve`: recordings in the native or web viewer, served on 127.0.0.1 only; and
the web viewer in headless Chromium showing the overlay in the camera view."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.cli import view
from ar_anchor.errors import EXIT_INTERRUPTED, EXIT_USAGE, InputError
from ar_anchor.viz import viewer
from tests.browser import Browser, find_chromium
from tests.helpers import cli, describe, run_main

REPO = Path(__file__).resolve().parents[2]
URL_LINE = re.compile(r"(?:view: open|watch the run at) (http://\S+)")


def _fake_rrd(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"RRF2" + bytes(60))  # the header is all `view` checks before rerun opens it
    return path


def _small_recording(path: Path) -> Path:
    """A real .rrd (a few points), written with the SDK: quicker than a demo run."""
    import rerun as rr

    stream = rr.RecordingStream("ar_anchor_test")
    stream.save(str(path))
    stream.log("points", rr.Points3D(np.zeros((3, 3))))
    stream.flush()
    stream.disconnect()
    return path


def _no_display() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}


def _listening_pids_addresses(pid_tree: set[int]) -> list[str]:
    """The local addresses (host:port) that the processes ``pid_tree`` listen on, from ``ss -ltnp``."""
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, timeout=30, check=True).stdout
    found = []
    for line in out.splitlines():
        pids = {int(p) for p in re.findall(r"pid=(\d+)", line)}
        if pids & pid_tree:
            found.append(line.split()[3])
    return found


def _descendants(pid: int) -> set[int]:
    out = subprocess.run(["ps", "-eo", "pid=,ppid="], capture_output=True, text=True, check=True).stdout
    children: dict[int, list[int]] = {}
    for line in out.splitlines():
        child, parent = (int(x) for x in line.split())
        children.setdefault(parent, []).append(child)
    tree, todo = {pid}, [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in tree:
                tree.add(child)
                todo.append(child)
    return tree


def _read_url(process: subprocess.Popen[str], timeout_s: float = 120.0) -> str:
    """The URL the command prints first (on stdout)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = process.stdout.readline()  # type: ignore[union-attr]
        if not line:
            break
        match = URL_LINE.search(line)
        if match:
            return match.group(1)
    process.kill()
    raise AssertionError(f"no URL printed; stderr: {process.stderr.read()!r}")  # type: ignore[union-attr]


def _interrupt(process: subprocess.Popen[str]) -> tuple[int, str]:
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=30)
    return process.returncode, stderr


# ---------------------------------------------------------------------------- recordings and errors


def test_a_run_directory_means_its_recording_parts_in_order(tmp_path):
    # given a long run's parts (part10 after part2, not as text sorts them) and other files
    for name in ("recording.part10.rrd", "recording.rrd", "recording.part2.rrd"):
        _fake_rrd(tmp_path / "run" / name)
    (tmp_path / "run" / "poses.csv").write_text("frame\n")
    # when / then
    names = [p.name for p in view.recording_files([str(tmp_path / "run")])]
    assert names == ["recording.rrd", "recording.part2.rrd", "recording.part10.rrd"]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "missing.rrd", "missing.rrd: no such file"),
        (lambda d: (d / "notes.rrd").write_text("hello") and d / "notes.rrd", "notes.rrd: not a rerun recording"),
        (lambda d: (d / "empty.rrd").touch() or d / "empty.rrd", "empty.rrd: not a rerun recording"),
        (lambda d: (d / "empty_dir").mkdir() or d / "empty_dir", "empty_dir: no recording"),
    ],
    ids=["missing", "text", "empty", "empty-directory"],
)
def test_a_file_that_is_not_a_recording_is_named(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(InputError, match=re.escape(message)):
        view.recording_files([str(path)])


@pytest.mark.parametrize("in_a_run_folder", [False, True], ids=["file", "run-folder"])
def test_view_of_a_named_pipe_is_refused_at_once_not_opened(tmp_path, in_a_run_folder):
    """A FIFO as the recording (given, or a run folder's recording.rrd) blocked for ever in open() (issue 34)."""
    (tmp_path / "run").mkdir()
    pipe = tmp_path / "run" / "recording.rrd" if in_a_run_folder else tmp_path / "pipe.rrd"
    os.mkfifo(pipe)
    target = pipe.parent if in_a_run_folder else pipe
    started = time.monotonic()
    result = subprocess.run(cli(["view", "--web", str(target)]), capture_output=True, text=True, timeout=60)
    assert result.returncode == EXIT_USAGE, describe(result)
    assert result.stderr.strip().splitlines() == [
        f"ar-anchor: error: {pipe}: is a named pipe (FIFO), not a rerun recording (.rrd)"
    ]
    assert time.monotonic() - started < 30


def test_a_device_or_a_folder_named_as_a_part_is_refused_by_what_it_is(tmp_path):
    with pytest.raises(InputError, match=re.escape("/dev/null: is a character device, not a rerun recording")):
        view.recording_files(["/dev/null"])
    (tmp_path / "run" / "recording.rrd").mkdir(parents=True)
    with pytest.raises(InputError, match=re.escape("recording.rrd: is a folder, not a rerun recording")):
        view.recording_files([str(tmp_path / "run")])


def test_view_of_a_missing_file_is_one_line_and_exit_2(tmp_path):
    result = subprocess.run(
        cli(["view", "--web", str(tmp_path / "nope.rrd")]), capture_output=True, text=True, timeout=120
    )
    assert result.returncode == EXIT_USAGE, describe(result)
    assert result.stderr.strip().splitlines() == [f"ar-anchor: error: {tmp_path / 'nope.rrd'}: no such file"]


def test_the_native_viewer_without_a_display_says_to_use_web(tmp_path):
    rrd = _fake_rrd(tmp_path / "recording.rrd")
    result = subprocess.run(cli(["view", str(rrd)]), capture_output=True, text=True, timeout=120, env=_no_display())
    assert result.returncode == EXIT_USAGE, describe(result)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "no display" in lines[0] and "--web" in lines[0], describe(result)


@pytest.mark.parametrize(
    "argv",
    [["view", "--bind", "example.org", "x.rrd"], ["view", "--port", "70000", "x.rrd"]],
    ids=["bind-not-an-address", "port-out-of-range"],
)
def test_bad_view_options_are_usage_errors(argv):
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=120)
    assert result.returncode == EXIT_USAGE, describe(result)


def test_serve_port_without_serve_is_refused(tmp_path):
    argv = ["-q", "demo", "--frames", "1", "--serve-port", "9999", "--out", str(tmp_path / "run")]
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=120)
    assert result.returncode == EXIT_USAGE, describe(result)
    assert "--serve-port" in result.stderr and "--serve" in result.stderr


def test_serve_is_exclusive_with_spawn_and_connect():
    for other in (["--spawn"], ["--connect"]):
        result = subprocess.run(cli(["demo", "--serve", *other]), capture_output=True, text=True, timeout=120)
        assert result.returncode == EXIT_USAGE and "not allowed with" in result.stderr, describe(result)


def test_a_bind_beyond_this_machine_is_warned_about(tmp_path, monkeypatch, caplog):
    # given a viewer that would serve (stubbed: nothing is started)
    class Served:
        url, grpc_url = "http://0.0.0.0:1/", "rerun+http://0.0.0.0:2/proxy"

        def wait(self) -> int:
            raise KeyboardInterrupt

        def stop(self) -> None:
            pass

    started = {}
    monkeypatch.setattr(viewer, "serve_web_viewer", lambda files, **kw: started.update(kw) or Served())
    args = argparse.Namespace(
        recordings=[str(_fake_rrd(tmp_path / "r.rrd"))], web=True, port=None, grpc_port=None, bind="0.0.0.0", quiet=True
    )
    # when
    assert view.cmd_view(args) == EXIT_INTERRUPTED
    # then
    assert started["bind"] == "0.0.0.0"
    assert any("--bind 0.0.0.0" in r.getMessage() and "network" in r.getMessage() for r in caplog.records)


def test_the_native_viewer_opens_the_files_listening_on_localhost(tmp_path, monkeypatch):
    # given a display and a stand-in for the viewer process
    monkeypatch.setenv("DISPLAY", ":0")
    started = []

    class Window:
        def __init__(self, command, **_kwargs) -> None:
            started.append(command)

        def wait(self) -> int:  # the user closed it
            return 0

    monkeypatch.setattr(viewer.subprocess, "Popen", Window)
    parts = [_fake_rrd(tmp_path / "run" / name) for name in ("recording.rrd", "recording.part2.rrd")]
    args = argparse.Namespace(
        recordings=[str(tmp_path / "run")], web=False, port=None, grpc_port=None, bind="127.0.0.1", quiet=True
    )
    # when / then
    assert view.cmd_view(args) == 0
    command = started[0]
    assert command[command.index("--bind") + 1] == "127.0.0.1"
    assert command[-2:] == [str(p) for p in parts]


def test_viewer_urls_name_a_loopback_host_for_an_unspecified_bind():
    assert viewer._url_host("0.0.0.0") == "127.0.0.1"
    assert viewer._url_host("::1") == "[::1]"
    assert viewer.is_loopback("127.0.0.1") and viewer.is_loopback("::1") and not viewer.is_loopback("0.0.0.0")


def test_a_taken_default_port_is_replaced_and_a_taken_chosen_one_refused():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        assert viewer._pick_port("127.0.0.1", None, port, "--port") != port
        with pytest.raises(InputError, match=f"--port {port}: 127.0.0.1:{port} is in use"):
            viewer._pick_port("127.0.0.1", port, 9090, "--port")


# ---------------------------------------------------------------------------- what listens


@pytest.mark.skipif(shutil.which("ss") is None, reason="ss (iproute2) not installed")
def test_view_web_listens_on_127_0_0_1_only_and_ends_on_ctrl_c(tmp_path):
    # given a recording
    rrd = _small_recording(tmp_path / "recording.rrd")
    # when it is served
    process = subprocess.Popen(
        cli(["view", "--web", "--port", "0", "--grpc-port", "0", str(rrd)]),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        url = _read_url(process)
        addresses = _listening_pids_addresses(_descendants(process.pid))
    finally:
        code, stderr = _interrupt(process)
    # then both its ports (the page's and the gRPC server's) are on 127.0.0.1, and nothing else
    assert len(addresses) == 2, addresses
    assert all(a.startswith("127.0.0.1:") for a in addresses), addresses
    assert url.startswith("http://127.0.0.1:") and "url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in url
    # and Ctrl-C ends it in one line, exit 130, the server gone with it
    assert code == EXIT_INTERRUPTED
    assert stderr.strip().splitlines()[-1] == "ar-anchor: interrupted; web viewer stopped"
    time.sleep(0.5)
    assert not _listening_pids_addresses(_descendants(process.pid) | {process.pid}), "the server outlived the command"


def _run_ended(out: Path) -> bool:
    """Has the run in ``out`` ended (its summary.json no longer says ``running``)?"""
    try:
        return json.loads((out / "summary.json").read_text())["status"] != "running"
    except (OSError, ValueError, KeyError):
        return False


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("ss") is None, reason="ss (iproute2) not installed")
def test_serve_streams_the_run_and_keeps_serving_until_ctrl_c(tmp_path):
    out = tmp_path / "run"
    argv = ["-q", "demo", "--frames", "3", "--serve", "--serve-port", "0", "--out", str(out)]
    process = subprocess.Popen(cli(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = _read_url(process)
        deadline = time.monotonic() + 120
        while not _run_ended(out) and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)  # (summary.json exists from the run's start, saying "running")
        time.sleep(1.0)
        # the run is over, its files complete; the viewer still serves, on 127.0.0.1 only
        assert process.poll() is None, "the command ended with the run"
        addresses = _listening_pids_addresses(_descendants(process.pid))
    finally:
        code, stderr = _interrupt(process)
    assert (out / "recording.rrd").stat().st_size > 0
    assert url.startswith("http://127.0.0.1:")
    assert len(addresses) == 2 and all(a.startswith("127.0.0.1:") for a in addresses), addresses
    # Ctrl-C then stops the viewer; the exit code is the run's
    assert code == 0, stderr
    assert "the web viewer keeps serving" in stderr
    assert stderr.strip().splitlines()[-1] == "ar-anchor: web viewer stopped"


@pytest.mark.slow
def test_a_run_interrupted_while_serving_takes_the_viewer_with_it(tmp_path):
    argv = ["-q", "live", "--device", "synthetic", "--width", "320", "--height", "180", "--serve", "--serve-port", "0"]
    argv += ["--out", str(tmp_path / "run")]
    process = subprocess.Popen(cli(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _read_url(process)
        time.sleep(3.0)
        tree = _descendants(process.pid)
    finally:
        code, stderr = _interrupt(process)
    assert code == EXIT_INTERRUPTED, stderr
    assert "ar-anchor: interrupted" in stderr
    time.sleep(0.5)
    alive = subprocess.run(["ps", "-o", "pid=", "-p", ",".join(map(str, tree))], capture_output=True, text=True)
    assert not alive.stdout.strip(), f"left running: {alive.stdout}"


# ---------------------------------------------------------------------------- in a browser

# the window: headless Chromium draws the viewer on the CPU (swiftshader), and a screenshot of a 1600x1000
# window took ~5 s (the test ~40 s); at 1024x640 the viewer's default layout is the same and the overlay's
# parts are still hundreds of pixels
SIZE = (1024, 640)
BROWSER_TIMEOUT_S = 150.0
CUBE_HUE = (98, 116)  # OpenCV hue (0-180) of the demo's cube overlay, RGB (70, 140, 240), under any shading
MIN_BLOB_PX = 800  # an overlay part (a cube face, the pin's ball) at 1024x640, thin lines opened away


def _blobs(mask: np.ndarray) -> list[tuple[int, tuple[float, float]]]:
    """(area, centroid) of the blobs of ``mask`` at least 9 px thick."""
    opened = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((9, 9), np.uint8))
    count, _, stats, centroids = cv2.connectedComponentsWithStats(opened)
    return [(int(stats[i, cv2.CC_STAT_AREA]), tuple(centroids[i])) for i in range(1, count)]


def overlay_in_camera_view(shot: np.ndarray) -> dict:
    """What the main (left) view of a screenshot shows: ``camera`` the bounding box of the camera image
    (a large textured, non-background area) or None; ``cubes`` and ``pins`` the overlay's blue cube and red pin
    blobs inside it. ``ok`` when the camera image fills much of the view and both overlay kinds are drawn on it."""
    height, width = shot.shape[:2]
    left = shot[int(0.05 * height) : int(0.8 * height), : int(0.4 * width)]
    hsv = cv2.cvtColor(left, cv2.COLOR_BGR2HSV)
    hue, sat, val = (hsv[..., i].astype(int) for i in range(3))
    # the camera image: pixels far from the viewer's light-grey or near-black backgrounds, as one large area
    content = ((val < 215) & (val > 40)) | (sat > 60)
    closed = cv2.morphologyEx(content.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((15, 15), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(closed)
    result: dict = {"ok": False, "camera": None, "cubes": [], "pins": []}
    if count < 2:
        return result
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h, area = (int(v) for v in stats[biggest])
    if area < 0.25 * left.shape[0] * left.shape[1] or w < 0.6 * left.shape[1]:
        return result  # a loading screen, an empty or a blank view: no large image
    patch = cv2.cvtColor(left[y : y + h, x : x + w], cv2.COLOR_BGR2GRAY)
    if float(patch.std()) < 15.0:
        return result  # a flat area, not a camera image
    result["camera"] = (x, y, w, h)

    def inside(centroid: tuple[float, float]) -> bool:
        return x <= centroid[0] <= x + w and y <= centroid[1] <= y + h

    cube = (hue >= CUBE_HUE[0]) & (hue <= CUBE_HUE[1]) & (sat > 120) & (val > 60)
    pin = ((hue <= 6) | (hue >= 172)) & (sat > 130) & (val > 60)
    result["cubes"] = [b for b in _blobs(cube) if b[0] >= MIN_BLOB_PX and inside(b[1])]
    result["pins"] = [b for b in _blobs(pin) if b[0] >= MIN_BLOB_PX and inside(b[1])]
    result["ok"] = bool(result["cubes"] and result["pins"])
    return result


def test_the_screenshot_check_refuses_blank_and_loading_pages():
    light = np.full((SIZE[1], SIZE[0], 3), 248, np.uint8)
    assert not overlay_in_camera_view(light)["ok"]
    welcome = light.copy()
    cv2.putText(welcome, "The data layer for physical AI", (400, 140), cv2.FONT_HERSHEY_SIMPLEX, 2, (20, 20, 20), 3)
    cv2.rectangle(welcome, (8, 60), (190, 90), (235, 120, 30), -1)  # the blue "Welcome" button
    assert not overlay_in_camera_view(welcome)["ok"]
    # a camera image with no overlay on it
    rng = np.random.default_rng(0)
    image = light.copy()
    image[150:410, :400] = rng.integers(60, 200, (260, 400, 3), dtype=np.uint8)
    assert overlay_in_camera_view(image)["camera"] is not None and not overlay_in_camera_view(image)["ok"]
    # ... and with a blue cube and a red ball drawn on it
    cv2.rectangle(image, (130, 190), (195, 255), (240, 140, 70), -1)
    cv2.circle(image, (300, 320), 40, (50, 40, 220), -1)
    assert overlay_in_camera_view(image)["ok"]


@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="chromium not installed (apt-get install chromium; .ci/run does)")
def test_the_web_viewer_shows_the_overlay_in_the_camera_view(tmp_path):
    started = time.monotonic()
    # given a short demo run (a still camera near the markers: the overlay is large; every frame shows it)
    out = tmp_path / "run"
    demo = run_main(["-q", "demo", "--frames", "10", "--trajectory", "static", "--out", str(out)])  # (its files only)
    assert demo.code == 0, demo.describe()
    # when its recording is served and opened in headless Chromium
    process = subprocess.Popen(
        cli(["view", "--web", "--port", "0", "--grpc-port", "0", str(out / "recording.rrd")]),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    browser = None
    found: dict = {}
    try:
        url = _read_url(process)
        browser = Browser(SIZE, tmp_path / "chromium.log")
        browser.navigate(url)
        deadline = time.monotonic() + BROWSER_TIMEOUT_S
        shots = 0
        while time.monotonic() < deadline:
            time.sleep(1.0)
            shot = browser.screenshot()
            shots += 1
            cv2.imwrite(str(tmp_path / "web_viewer.png"), shot)
            found = overlay_in_camera_view(shot)
            if found["ok"]:
                break
    finally:
        if browser is not None:
            browser.close()
        code, _ = _interrupt(process)
    elapsed = time.monotonic() - started
    print(f"web viewer: {shots} screenshots, {elapsed:.0f} s in all; {found}")
    # then the main view shows the camera image with the cubes and the pin drawn on it
    last = tmp_path / "web_viewer.png"
    assert found.get("ok"), f"the overlay is not drawn in the camera view (last screenshot: {last}): {found}"
    assert code == EXIT_INTERRUPTED


@pytest.mark.parametrize(("argv", "option"), [(["view", "--help"], "--web"), (["demo", "--help"], "--serve")])
def test_the_help_says_what_127_0_0_1_lets_in(argv, option):
    """ "This machine only" was read as "only me" (issue 34): rerun 0.41's servers take no token and no Unix
    socket, so the help of --web, --bind and --serve says what any local process can do."""
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, describe(result)
    text = " ".join(result.stdout.split())
    assert option in text
    assert "not other users: any process on this machine can connect" in text
    assert "write entries into" in text and "no authentication" in text


# ---------------------------------------------------------------------------- view --screenshot

# a new recording part every 0.6 s of the frames' own time (or of wall time): a 60-frame demo (2 s at 30 fps) has
# at least 4 however fast it runs (1.2 s parts made 3 only when the run took 2.4 s of wall time or more)
PARTS_TOML = "[recording]\npart_minutes = 0.01\n"


def test_the_time_cursor_request_says_frame_and_the_state_parser_reads_it_back():
    from ar_anchor.viz import screenshot

    # given the request that moves the cursor to a frame far beyond one varint byte
    request = screenshot.set_time_cursor_request(300)
    # then it is field 6 holding the timeline name and the time
    inner = screenshot.proto_fields(screenshot.proto_fields(request)[6][0])
    assert screenshot.proto_fields(inner[2][0])[1] == [b"frame"]
    assert screenshot.proto_fields(inner[3][0])[1] == [300]
    # and a viewer state built of the same parts reads back as frames 0..59, cursor 300, nothing loading
    field = screenshot._field
    timeline = field(1, field(1, b"frame")) + field(3, b"\x08\x00\x10\x3b")
    cursor = field(1, field(1, b"frame")) + field(3, b"\x08" + screenshot._encode_varint(300))
    recording = field(1, b"Recording:abc") + field(2, timeline) + field(3, cursor)
    state = screenshot.parse_viewer_state(field(2, b"Recording:abc") + field(3, recording))
    assert state == {"started": True, "loading": 0, "frames": (0, 59), "cursor": 300}


@pytest.mark.parametrize("layout", ["full", "overlay", "camera", "3d"])
def test_every_layout_has_a_blueprint_paused_on_the_frame_timeline(tmp_path, layout):
    from ar_anchor.viz.screenshot import layout_blueprint

    path = tmp_path / f"{layout}.rbl"
    layout_blueprint(layout).save("ar_anchor", path)
    assert path.read_bytes().startswith(b"RRF")


def test_a_screenshot_without_chromium_says_how_to_install_it(tmp_path):
    rrd = _small_recording(tmp_path / "recording.rrd")
    argv = ["view", str(rrd), "--screenshot", str(tmp_path / "shot.png"), "--chromium", "no-such-chromium"]
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=120)
    assert result.returncode == EXIT_USAGE, describe(result)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "apt install chromium" in lines[0] and "Traceback" not in result.stderr
    assert not (tmp_path / "shot.png").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--frame", "3"], "--frame is --screenshot's"),
        (["--layout", "overlay"], "--layout is --screenshot's"),
        (["--screenshot", "shot.jpg"], "is a PNG"),
        (["--screenshot", "shot.png", "--web"], "--screenshot and --web"),
    ],
)
def test_screenshot_options_out_of_place_are_one_line_and_exit_2(tmp_path, extra, message):
    rrd = _fake_rrd(tmp_path / "recording.rrd")
    result = subprocess.run(cli(["view", str(rrd), *extra]), capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == EXIT_USAGE, describe(result)
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1, describe(result)


def test_view_help_documents_the_screenshot():
    result = subprocess.run(cli(["view", "--help"]), capture_output=True, text=True, timeout=120)
    text = " ".join(result.stdout.split())
    for option in ("--screenshot OUT.png", "--frame N", "--layout {full,overlay,camera,3d}", "--chromium PATH"):
        assert option in text
    assert "apt install chromium" in text and "every part of a split run" in text


def _image_box(shot: np.ndarray) -> tuple[int, int, int, int]:
    """The camera image in a screenshot of the camera layout: the bounding box (x, y, w, h) of the bright,
    textured pixels between the viewer's top bars and its time panel."""
    height = shot.shape[0]
    top, bottom = int(0.08 * height), int(0.95 * height)
    grey = cv2.cvtColor(shot[top:bottom], cv2.COLOR_BGR2GRAY)
    ys, xs = np.nonzero(grey > 60)  # the viewer's background is near black (dark theme)
    x0, x1, y0, y1 = np.percentile(xs, 0.5), np.percentile(xs, 99.5), np.percentile(ys, 0.5), np.percentile(ys, 99.5)
    return int(x0), int(y0) + top, int(x1 - x0), int(y1 - y0)


def _demo_frames(tmp_path: Path, indices: list[int]) -> dict[int, np.ndarray]:
    """The demo's frames ``indices`` as ``ar-anchor demo --frames 60 --config parts.toml`` renders them."""
    from ar_anchor.camera import CameraModel
    from ar_anchor.config import load_config
    from ar_anchor.sources.synthetic import SyntheticSource
    from ar_anchor.synthetic import Trajectory, demo_scene

    config = load_config(tmp_path / "parts.toml", demo=True)
    trajectory = Trajectory(kind="sweep", near_m=0.35, far_m=3.0, look_at=(-0.01, 0.0, 0.0))
    scene = demo_scene(config, CameraModel.default_synthetic(), frames=60, seed=0, trajectory=trajectory)
    with SyntheticSource(scene) as source:  # each frame rendered alone is the one the run rendered in turn
        return {index: source.frame(index).image for index in indices}


def _best_match(region: np.ndarray, frames: dict[int, np.ndarray]) -> tuple[int, dict[int, float]]:
    """Which of ``frames`` the screenshot's image ``region`` is (normalised correlation of grey levels)."""
    grey = cv2.cvtColor(region, cv2.COLOR_BGR2GRAY).astype(np.float32)
    scores = {}
    for index, image in frames.items():
        resized = cv2.resize(image, (grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_AREA)
        candidate = cv2.cvtColor(resized, cv2.COLOR_BGR2GRAY).astype(np.float32)
        scores[index] = float(cv2.matchTemplate(grey, candidate, cv2.TM_CCOEFF_NORMED)[0, 0])
    return max(scores, key=scores.__getitem__), scores


@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="chromium not installed (apt-get install chromium; .ci/run does)")
def test_a_screenshot_of_a_split_recording_draws_exactly_the_frame_asked_for(tmp_path):
    # given a demo run recorded in several parts (the frame asked for is in a later one)
    (tmp_path / "parts.toml").write_text(PARTS_TOML)
    # (in-process: only the run's files are the given)
    demo = run_main(["-q", "demo", "--frames", "60", "--config", "parts.toml", "--out", "run"], tmp_path)
    assert demo.code == 0, demo.describe()
    parts = json.loads((tmp_path / "run" / "summary.json").read_text())["recording_parts"]
    assert len(parts) >= 3, parts
    # when the run's folder is screenshot at frame 45 in the camera layout (in a smaller window than the default
    # 1600x900: headless Chromium draws the viewer on the CPU, 15 s of CPU to load the recording at 1024x576, 10 s
    # at 640x360; at 800x450 frame 45 still correlates 0.88 with the shot against 0.68 for its neighbours)
    shot_png = tmp_path / "shot.png"
    argv = ["view", "run", "--screenshot", str(shot_png), "--frame", "45", "--layout", "camera", "--size", "800x450"]
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert result.returncode == 0, describe(result)
    assert f"{len(parts)} file(s)" in result.stderr and "frame 45 of 0..59" in result.stdout, describe(result)
    shot = cv2.imread(str(shot_png))
    # then the camera image alone fills the window's width (the layout asked for, not the run's own) ...
    x, y, w, h = _image_box(shot)
    assert w > 0.7 * shot.shape[1], (x, y, w, h)
    # ... and it is frame 45, not one before or after it (the last part starts before 45: all parts were read)
    frames = _demo_frames(tmp_path, [0, 15, 30, 40, 44, 46, 50, 59, 45])
    best, scores = _best_match(shot[y : y + h, x : x + w], frames)
    print(f"correlation with each frame: {scores}")
    assert best == 45, scores


@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="chromium not installed (apt-get install chromium; .ci/run does)")
def test_a_frame_outside_the_recording_is_one_line_and_exit_2(tmp_path):
    import rerun as rr

    # given a recording of frames 0..4
    stream = rr.RecordingStream("ar_anchor_test")
    stream.save(str(tmp_path / "recording.rrd"))
    for frame in range(5):
        stream.set_time("frame", sequence=frame)
        stream.log("points", rr.Points3D(np.zeros((3, 3)) + frame))
    stream.flush()
    stream.disconnect()
    # when frame 99 is asked for
    argv = ["view", str(tmp_path / "recording.rrd"), "--screenshot", str(tmp_path / "shot.png"), "--frame", "99"]
    argv += ["--size", "800x450"]  # (no picture is taken: the window's size does not matter)
    result = subprocess.run(cli(argv), capture_output=True, text=True, timeout=600)
    # then the command says which frames there are, and writes nothing
    assert result.returncode == EXIT_USAGE, describe(result)
    assert "--frame 99: not in the recording (its frames are 0..4)" in result.stderr, describe(result)
    assert "Traceback" not in result.stderr and not (tmp_path / "shot.png").exists()


def test_the_help_describes_every_layout_the_screenshot_builds():
    from ar_anchor.cli.view import LAYOUTS
    from ar_anchor.viz.screenshot import LAYOUT_NAMES

    assert tuple(LAYOUTS) == LAYOUT_NAMES
