"""Media faults: damaged videos and odd images, through ``ar-anchor replay`` (in-process ``main()``).

Videos (H.264 MP4 with the index at the end and at the front, MJPG AVI; 30 frames of a marker seen
in every frame): zero bytes, truncated at five points, 2 kB overwritten with random bytes or zeros
at three points, wrong extensions, a garbage timestamp sidecar. Image folders (12 frames): one
image mid-stream of another size, bit depth, channel count or format, corrupt, truncated, empty;
non-image files and folders among the images; every image unreadable.

Expected every time: exit 0 (all there is was tracked), 1 (the stream was damaged: outputs cover
what could be read, and one error line says so, naming the file) or 2 (nothing could be read:
one error line naming the file, no outputs); no traceback; and nothing lost: every frame the
decoder can deliver is in poses.csv (header intact, every row well formed), summary.json says how
the run ended, and recording.rrd verifies.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import CliResult, assert_clean_exit, error_lines, run_main

pytestmark = pytest.mark.slow  # fuzzing and end-to-end CLI runs: the full suite, not the fast tier

FRAMES = 30
SIZE = (320, 240)
RERUN = Path(sys.executable).with_name("rerun")
POSES_HEADER = (
    "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
    "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
).split(",")


# ============================================================================ media


class Media:
    """One rendered clip (a 5 cm marker orbited at 30 cm, visible in every frame) in every container."""

    def __init__(self, root: Path) -> None:
        self.root = root
        camera = CameraModel.from_fov(*SIZE, 300.0)
        scene = SyntheticScene(
            camera=camera,
            markers=(PlacedMarker(0, 0.05, Pose.identity()),),
            trajectory=Trajectory(kind="orbit", near_m=0.30, azimuth_deg=20, elevation_deg=10),
            frames=FRAMES,
            noise_sigma=1.0,
            blur_sigma=0.0,
            seed=1,
        )
        self.images = [frame.image for frame in SyntheticSource(scene)]
        self.camera = root / "cam.yml"
        camera.to_yaml(self.camera)
        self.videos: dict[str, Path] = {}
        for name, faststart in (("moov_end.mp4", False), ("moov_front.mp4", True)):
            if self._h264(root / name, faststart):
                self.videos[name] = root / name
        writer = cv2.VideoWriter(str(root / "mjpg.avi"), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, SIZE)
        for image in self.images:
            writer.write(image)
        writer.release()
        self.videos["mjpg.avi"] = root / "mjpg.avi"
        for path in self.videos.values():
            assert decodable_frames(path) == FRAMES, path

    def _h264(self, path: Path, faststart: bool) -> bool:
        try:
            import av

            options = {"movflags": "+faststart"} if faststart else {}
            with av.open(str(path), "w", options=options) as container:
                stream = container.add_stream("libx264", rate=30)
                stream.width, stream.height, stream.pix_fmt = *SIZE, "yuv420p"
                stream.options = {"g": "10"}  # a keyframe every 10 frames: damage costs a GOP, not the clip
                for image in self.images:
                    for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                        container.mux(packet)
                for packet in stream.encode():
                    container.mux(packet)
        except Exception:  # noqa: BLE001 - no H.264 encoder in this PyAV: the MJPG cases still run
            return False
        return True

    def folder(self, name: str, count: int = 12) -> Path:
        folder = self.root / name
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        for index, image in enumerate(self.images[:count]):
            assert cv2.imwrite(str(folder / f"f_{index}.png"), image)
        return folder


@pytest.fixture(scope="module")
def media(tmp_path_factory) -> Media:
    return Media(tmp_path_factory.mktemp("media"))


def decodable_frames(path: Path) -> int:
    """Frames FFmpeg (through OpenCV, as the tool reads them) can deliver from ``path``."""
    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    count = 0
    try:
        while capture.isOpened() and capture.read()[0]:
            count += 1
    finally:
        capture.release()
    return count


def replay(media: Media, source: Path, name: str) -> tuple[CliResult, Path]:
    out = media.root / f"out_{name}"
    shutil.rmtree(out, ignore_errors=True)
    cwd = Path.cwd()
    os.chdir(media.root)
    try:
        result = run_main(
            ["-q", "replay", str(source.relative_to(media.root)), "--camera", "cam.yml", "--out", out.name]
        )
    finally:
        os.chdir(cwd)
    assert_clean_exit(result)
    return result, out


def poses_frames(out: Path) -> list[int]:
    """Frame indices of poses.csv's rows, after checking the file is well formed CSV with its header."""
    with (out / "poses.csv").open(newline="", encoding="utf-8") as handle:
        rows = list(csv.reader(handle))
    assert rows and rows[0] == POSES_HEADER, rows[:1]
    assert all(len(row) == len(POSES_HEADER) for row in rows), "a ragged row"
    frames = [int(row[0]) for row in rows[1:]]
    assert frames == sorted(frames)
    return frames


def verify_rrd(path: Path) -> None:
    assert path.is_file() and path.stat().st_size > 0, f"{path} missing or empty"
    if not RERUN.exists():
        return
    result = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def assert_outputs_complete(out: Path, frames: int) -> dict:
    """What a run that started leaves: summary.json (completed, ``frames`` frames), rows in poses.csv for
    those frames (the marker is in view throughout; a frame whose damage hides it may have none: the
    tracker does not publish a blind prediction for a turning marker), a recording that verifies."""
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["status"] == "completed"
    assert summary["frames"] == frames, f"{summary['frames']} frames tracked, {frames} deliverable"
    rows = set(poses_frames(out))
    assert frames - max(2, frames // 10) <= len(rows) <= frames, sorted(rows)
    verify_rrd(out / "recording.rrd")
    return summary


def assert_refused(result: CliResult, out: Path, name: str) -> None:
    errors = error_lines(result.stderr)
    assert result.code == 2 and len(errors) == 1 and name in errors[0], result.describe()
    assert not (out / "poses.csv").exists(), "outputs for a run that never started"


def assert_damaged_video_outcome(result: CliResult, out: Path, path: Path) -> str:
    """Refused (exit 2), or every deliverable frame tracked: exit 0 when that is the whole clip, else
    exit 1 with one error line naming the file. Returns the outcome for the record."""
    if result.code == 2:
        assert_refused(result, out, path.name)
        return "refused (exit 2)"
    deliverable = decodable_frames(path)
    summary = assert_outputs_complete(out, deliverable)
    errors = error_lines(result.stderr)
    if deliverable < FRAMES:  # frames are missing: never a silent success
        assert result.code == 1, result.describe()
        assert len(errors) == 1 and path.name in errors[0] and "ended early" in errors[0], result.describe()
        assert summary["source_ended_early"] is True
        return "partial (exit 1)"
    assert result.code == 0 and not errors, result.describe()
    return "all frames (exit 0)"


# ============================================================================ videos

VIDEOS = ["moov_end.mp4", "moov_front.mp4", "mjpg.avi"]


def _video(media: Media, name: str) -> Path:
    if name not in media.videos:
        pytest.skip(f"{name}: no H.264 encoder in this PyAV build")
    return media.videos[name]


@pytest.mark.parametrize("suffix", [".mp4", ".avi", ".mkv"])
def test_zero_byte_video_is_refused_naming_it(media, suffix):
    path = media.root / f"zero{suffix}"
    path.write_bytes(b"")
    result, out = replay(media, path, f"zero{suffix}")
    assert_refused(result, out, path.name)
    assert "empty" in error_lines(result.stderr)[0]


@pytest.mark.parametrize("fraction", [0.05, 0.25, 0.5, 0.75, 0.95])
@pytest.mark.parametrize("video", VIDEOS)
def test_truncated_video(media, video, fraction):
    data = _video(media, video).read_bytes()
    path = media.root / f"cut{int(fraction * 100)}_{video}"
    path.write_bytes(data[: int(len(data) * fraction)])
    result, out = replay(media, path, path.name)
    assert_damaged_video_outcome(result, out, path)


@pytest.mark.parametrize("pattern", ["random", "zeros"])
@pytest.mark.parametrize("fraction", [0.3, 0.5, 0.7])
@pytest.mark.parametrize("video", VIDEOS)
def test_video_corrupted_in_the_middle(media, video, fraction, pattern):
    data = bytearray(_video(media, video).read_bytes())
    start = int(len(data) * fraction)
    damage = np.random.default_rng(start).integers(0, 256, 2000, dtype=np.uint8).tobytes()
    data[start : start + 2000] = damage if pattern == "random" else bytes(2000)
    path = media.root / f"mid{int(fraction * 100)}{pattern}_{video}"
    path.write_bytes(bytes(data))
    result, out = replay(media, path, path.name)
    assert_damaged_video_outcome(result, out, path)


@pytest.mark.parametrize(
    ("content", "name", "expected"),
    [
        pytest.param("moov_front.mp4", "h264_named.avi", FRAMES, id="mp4-named-avi"),
        pytest.param("moov_end.mp4", "h264_named.mkv", FRAMES, id="mp4-named-mkv"),
        pytest.param("mjpg.avi", "mjpg_named.mp4", FRAMES, id="avi-named-mp4"),
        pytest.param("png", "image_named.mp4", 1, id="png-named-mp4"),
        pytest.param("moov_end.mp4", "video_named.png", 0, id="mp4-named-png"),
        pytest.param("text", "notes_named.mkv", 0, id="text-named-mkv"),
    ],
)
def test_wrong_extension_is_read_by_content(media, content, name, expected):
    path = media.root / name
    if content == "png":
        assert cv2.imwrite(str(media.root / "frame.png"), media.images[0])
        shutil.copy(media.root / "frame.png", path)
    elif content == "text":
        path.write_text("this is not a video\n" * 50)
    else:
        shutil.copy(_video(media, content), path)
    result, out = replay(media, path, name)
    if expected == 0:
        assert_refused(result, out, name)
    else:
        assert result.code == 0, result.describe()
        assert_outputs_complete(out, expected)


def test_garbage_timestamp_sidecar_is_refused_naming_it(media):
    path = media.root / "sidecar.avi"
    shutil.copy(media.videos["mjpg.avi"], path)
    (media.root / "sidecar.avi.timestamps.csv").write_text("frame,timestamp_ns\n0,zero\n")
    result, out = replay(media, path, "sidecar")
    assert_refused(result, out, "sidecar.avi.timestamps.csv")


# ============================================================================ image folders


def _grey(image):
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _pil(image, mode: str, path: Path) -> None:
    from PIL import Image

    Image.fromarray(image[:, :, ::-1]).convert(mode).save(path)


MID = 5  # the frame that is odd
# name -> (what is done to the folder, frames tracked, whether a warning must name the odd file)
IMAGE_FAULTS = {
    "other-size": (lambda f, im: cv2.imwrite(str(f / "f_5.png"), cv2.resize(im, (160, 120))), 11, True),
    "other-aspect": (lambda f, im: cv2.imwrite(str(f / "f_5.png"), cv2.resize(im, (320, 180))), 11, True),
    "16-bit": (lambda f, im: cv2.imwrite(str(f / "f_5.png"), im.astype(np.uint16) * 257), 12, False),
    "grey": (lambda f, im: cv2.imwrite(str(f / "f_5.png"), _grey(im)), 12, False),
    "bgra": (lambda f, im: cv2.imwrite(str(f / "f_5.png"), cv2.cvtColor(im, cv2.COLOR_BGR2BGRA)), 12, False),
    "grey+alpha": (lambda f, im: _pil(im, "LA", f / "f_5.png"), 12, False),
    "palette": (lambda f, im: _pil(im, "P", f / "f_5.png"), 12, False),
    "grey-16-bit": (lambda f, im: _pil(im, "I;16", f / "f_5.png"), 12, False),
    "float-tiff": (
        lambda f, im: (os.remove(f / "f_5.png"), cv2.imwrite(str(f / "f_5.tiff"), im.astype(np.float32) / 255)),
        12,
        False,
    ),
    "48-bit-tiff": (
        lambda f, im: (os.remove(f / "f_5.png"), cv2.imwrite(str(f / "f_5.tif"), im.astype(np.uint16) * 257)),
        12,
        False,
    ),
    "png-named-jpg": (lambda f, im: os.rename(f / "f_5.png", f / "f_5.jpg"), 12, False),
    "corrupt": (lambda f, im: (f / "f_5.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 2), 11, True),
    "truncated": (lambda f, im: (f / "f_5.png").write_bytes((f / "f_5.png").read_bytes()[:300]), 11, True),
    "zero-bytes": (lambda f, im: (f / "f_5.png").write_bytes(b""), 11, True),
    "text-file": (lambda f, im: (f / "notes.txt").write_text("not an image\n"), 12, False),
    "folder-named-png": (lambda f, im: (f / "sub.png").mkdir(), 12, False),
    "first-corrupt": (lambda f, im: (f / "f_0.png").write_bytes(b"garbage"), 11, True),
}


@pytest.mark.parametrize("fault", list(IMAGE_FAULTS))
def test_image_folder_with_an_odd_file_mid_stream(media, fault):
    change, frames, warned = IMAGE_FAULTS[fault]
    folder = media.folder(f"images_{fault}")
    change(folder, media.images[MID])
    result, out = replay(media, folder, fault)
    # the run completes: the odd image is converted, or skipped with a warning naming it
    assert result.code == 0 and not error_lines(result.stderr), result.describe()
    assert_outputs_complete(out, frames)
    tracked = set(poses_frames(out))
    odd = {"first-corrupt": 0}.get(fault, MID)
    expected = set(range(12)) - ({odd} if frames == 11 else set())
    # (the odd image itself may be too dark or small to measure; the tracker publishes no blind guess)
    assert tracked <= expected and expected - tracked <= {odd}, "a readable image was lost"
    warnings = [line for line in result.stderr.splitlines() if "WARNING" in line]
    if warned:
        assert len(warnings) == 1 and f"f_{odd}." in warnings[0], result.describe()
    else:
        assert not warnings, result.describe()


def test_image_folder_with_no_readable_image_is_refused(media):
    folder = media.folder("images_all_corrupt", count=4)
    for path in folder.iterdir():
        path.write_bytes(b"garbage")
    result, out = replay(media, folder, "all_corrupt")
    assert_refused(result, out, folder.name)


# ============================================================================ the user's screen

SCRIPT = "import sys; from ar_anchor.cli.main import main; sys.exit(main(sys.argv[1:]))"


@pytest.mark.parametrize("fault", ["corrupt-image", "truncated-video"])
def test_a_damaged_input_shows_our_lines_only(media, fault):
    # a real process: OpenCV and FFmpeg print to the file descriptor, below anything in-process can capture
    if fault == "corrupt-image":
        source = media.folder("screen_images")
        change, _, _ = IMAGE_FAULTS["corrupt"]
        change(source, None)
        expected = ["ar-anchor: WARNING: screen_images/f_5.png: not a readable image, skipped (frame 5)"]
    else:
        data = media.videos["mjpg.avi"].read_bytes()
        source = media.root / "screen_cut.avi"
        source.write_bytes(data[: len(data) // 2])
        expected = ["ar-anchor: WARNING: screen_cut.avi: stream ended", "ar-anchor: error: screen_cut.avi: the stream"]
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT, "-q", "replay", source.name, "--camera", "cam.yml", "--out", f"screen_{fault}"],
        cwd=media.root,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    lines = result.stderr.splitlines()
    assert len(lines) == len(expected), lines
    assert all(line.startswith(prefix) for line, prefix in zip(lines, expected)), lines
    assert result.returncode == (0 if fault == "corrupt-image" else 1)
