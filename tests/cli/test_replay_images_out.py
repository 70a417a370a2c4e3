"""``replay --images-out DIR``: an image folder written back as annotated images (same names, same formats),
under the output rules (no source image and no file of the user's replaced); a video source is pointed to
``--video-out``, and ``--video-out x.png`` to ``--images-out``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, error_lines, run_main

CAMERA = CameraModel.from_fov(640, 480, 600.0)
NAMES = ("left.png", "centre.jpg", "right.png")


def _render(turn_deg: float, seed: int) -> np.ndarray:
    scene = SyntheticScene(
        camera=CAMERA,
        markers=(PlacedMarker(0, 0.06, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=0.5, azimuth_deg=turn_deg, elevation_deg=0.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        blur_sigma=0.5,
        seed=seed,
    )
    (frame,) = SyntheticSource(scene)
    return frame.image


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """Three photos of a 6 cm marker at 0.5 m (two PNG, one JPEG) and their camera file."""
    root = tmp_path_factory.mktemp("images_out")
    (root / "shots").mkdir()
    for index, (name, turn) in enumerate(zip(NAMES, (-30, 0, 30))):
        assert cv2.imwrite(str(root / "shots" / name), _render(turn, index))
    CAMERA.to_yaml(root / "cam.yml")
    return root


def _replay(photos: Path, source: Path | str, *options: str):
    return run_main(
        ["-q", "replay", str(source), "--camera", str(photos / "cam.yml"), "--marker-length", "0.06", *options]
    )


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_each_image_gets_its_annotated_copy_under_its_own_name(photos: Path, tmp_path: Path) -> None:
    # given a folder of two PNG photos and a JPEG one
    before = _files(photos / "shots")
    # when it is replayed with --images-out outside --out
    result = _replay(photos, photos / "shots", "--out", str(tmp_path / "run"), "--images-out", str(tmp_path / "ann"))
    assert_clean_exit(result, {0})
    # then each photo has a copy of the same name, format and size, with the overlay drawn on the marker only
    written = sorted(p.name for p in (tmp_path / "ann").iterdir() if not p.name.startswith("."))
    assert written == sorted(NAMES)
    for name in NAMES:
        source = cv2.imread(str(photos / "shots" / name))
        annotated = cv2.imread(str(tmp_path / "ann" / name))
        assert annotated is not None and annotated.shape == source.shape
        assert (tmp_path / "ann" / name).read_bytes()[:4] == (photos / "shots" / name).read_bytes()[:4]  # format
        changed = np.abs(annotated.astype(int) - source.astype(int)).max(axis=2) > 40
        assert changed.sum() > 500, name  # the cube and axes drawn
        ys, xs = np.nonzero(changed)
        assert 200 < np.median(xs) < 440 and 120 < np.median(ys) < 360, name  # where the marker is (centre)
    # the sources are untouched, the run says where the copies are, summary.json counts them
    assert _files(photos / "shots") == before
    assert f"annotated images: {tmp_path / 'ann'}/ (3 images)" in result.stdout
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["images_out"] == {"folder": str(tmp_path / "ann"), "images": 3}


def test_the_copies_are_the_frames_of_the_annotated_video(photos: Path, tmp_path: Path) -> None:
    # given one PNG photo replayed with both --images-out and --video-out (MJPG: every frame a keyframe)
    source = photos / "shots" / "left.png"
    out = tmp_path / "run"
    result = _replay(
        photos, source, "--out", str(out), "--images-out", str(out), "--video-out", str(tmp_path / "v.avi")
    )
    assert_clean_exit(result, {0})
    # then the still is the video's frame (up to the video's JPEG coding)
    capture = cv2.VideoCapture(str(tmp_path / "v.avi"))
    ok, frame = capture.read()
    capture.release()
    still = cv2.imread(str(out / "left.png"))
    assert ok and frame.shape == still.shape
    assert np.abs(frame.astype(int) - still.astype(int)).mean() < 3.0
    assert np.abs(still.astype(int) - cv2.imread(str(source)).astype(int)).mean() > 0.5


def test_a_second_run_replaces_its_own_copies_but_never_the_users_files(photos: Path, tmp_path: Path) -> None:
    ann = tmp_path / "ann"
    first = _replay(photos, photos / "shots", "--out", str(tmp_path / "a"), "--images-out", str(ann))
    assert_clean_exit(first, {0})
    again = _replay(photos, photos / "shots", "--out", str(tmp_path / "b"), "--images-out", str(ann))
    assert_clean_exit(again, {0})  # its own copies: replaced
    # given a file of the user's under one of the names
    (ann / "right.png").write_bytes(b"mine")
    result = _replay(photos, photos / "shots", "--out", str(tmp_path / "c"), "--images-out", str(ann))
    # then the run is refused in one line naming it, before anything is written
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "--images-out" in line and "right.png" in line and "no ar-anchor --images-out wrote" in line
    assert (ann / "right.png").read_bytes() == b"mine"
    assert not (tmp_path / "c").exists()


def test_the_source_folder_itself_is_refused(photos: Path, tmp_path: Path) -> None:
    before = _files(photos / "shots")
    result = _replay(photos, photos / "shots", "--out", str(tmp_path / "run"), "--images-out", str(photos / "shots"))
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "is the folder of the source images" in line, line
    assert _files(photos / "shots") == before
    # also reached through another spelling (a glob, a trailing "/.")
    glob = _replay(
        photos,
        str(photos / "shots" / "*.png"),
        "--out",
        str(tmp_path / "g"),
        "--images-out",
        str(photos / "shots" / "."),
    )
    assert_clean_exit(glob, {2})
    assert "is the folder of the source images" in error_lines(glob.stderr)[0]
    assert _files(photos / "shots") == before


def test_a_video_source_is_pointed_to_video_out(photos: Path, tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    for turn in (-10, 0, 10):
        writer.write(_render(turn, 0))
    writer.release()
    result = _replay(photos, clip, "--out", str(tmp_path / "run"), "--images-out", str(tmp_path / "ann"))
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "is a video" in line and "--video-out" in line, line
    assert not (tmp_path / "ann").exists()


def test_video_out_with_an_image_extension_suggests_images_out(photos: Path, tmp_path: Path) -> None:
    result = _replay(photos, photos / "shots", "--out", str(tmp_path / "run"), "--video-out", str(tmp_path / "x.png"))
    assert_clean_exit(result, {2})
    (line,) = error_lines(result.stderr)
    assert "--video-out" in line and "--images-out DIR" in line, line
    assert not (tmp_path / "run").exists()  # (exit 2: nothing written, not even frames.csv)


def test_a_folder_that_can_never_be_made_is_refused_before_the_run(photos: Path, tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("x")
    for folder in (tmp_path / "a_file", tmp_path / "a_file" / "ann"):
        result = _replay(photos, photos / "shots", "--out", str(tmp_path / "run"), "--images-out", str(folder))
        assert_clean_exit(result, {2})
        (line,) = error_lines(result.stderr)
        assert "--images-out" in line and "a file" in line, line
        assert not (tmp_path / "run").exists()
