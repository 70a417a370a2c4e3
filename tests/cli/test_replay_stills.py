"""``replay`` of an image folder: independent stills by default, each decided alone (the answer of
``--no-filter``, in the default and ``--causal`` modes), a sequence when told; ``frames.csv`` traces each
frame to its file (issue 32)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, run_main

CAMERA = CameraModel.from_fov(640, 480, 600.0)
TURNS = (-60, -40, -20, 0, 20, 40, 60)


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """Seven photos of a 6 cm marker at 0.5 m turned from -60 to 60 deg (one render each), and a camera file."""
    root = tmp_path_factory.mktemp("stills")
    (root / "shots").mkdir()
    for index, turn in enumerate(TURNS):
        scene = SyntheticScene(
            camera=CAMERA,
            markers=(PlacedMarker(0, 0.06, Pose.identity()),),
            trajectory=Trajectory(kind="static", near_m=0.5, azimuth_deg=turn, elevation_deg=0.0, roll_deg=0.0),
            frames=1,
            noise_sigma=1.5,
            blur_sigma=0.5,
            seed=index,
        )
        (frame,) = SyntheticSource(scene)
        assert cv2.imwrite(str(root / "shots" / f"turn_{index}.png"), frame.image)
    CAMERA.to_yaml(root / "cam.yml")
    return root


def _replay(photos: Path, name: str, *options: str, quiet: bool = True):
    out = photos / name
    source, camera = str(photos / "shots"), str(photos / "cam.yml")
    quiet_flag = ["-q"] if quiet else []
    result = run_main(
        [*quiet_flag, "replay", source, "--camera", camera, "--marker-length", "0.06", "--out", str(out), *options]
    )
    assert_clean_exit(result, {0})
    with open(out / "poses.csv", newline="") as file:
        rows = [row for row in csv.DictReader(file)]
    return result, out, rows


def _answers(rows: list[dict[str, str]]) -> list[tuple[str, ...]]:
    keys = ("frame", "target", "state", "rvec_x", "rvec_y", "rvec_z", "tvec_x", "tvec_y", "tvec_z")
    return [tuple(row[key] for key in keys) for row in rows]


def test_a_folder_is_independent_stills_with_the_answer_of_no_filter(photos: Path) -> None:
    # given a folder of photos replayed by default, --causal and --no-filter
    _, _, alone = _replay(photos, "no_filter", "--no-filter")
    for mode in ((), ("--causal",)):
        result, out, rows = _replay(photos, "default" if not mode else "causal", *mode, quiet=False)
        # then every photo gets exactly the per-frame answer, and the run says what it assumed, in one line
        assert _answers(rows) == _answers(alone)
        assert len(_answers(rows)) == len(TURNS)
        notes = [line for line in result.stdout.splitlines() if "independent stills" in line]
        assert len(notes) == 1 and "--sequence" in notes[0], result.stdout
        summary = json.loads((out / "summary.json").read_text())
        assert summary["decided_with"] == "each image alone (independent stills)"


def test_frames_csv_traces_each_row_to_its_file(photos: Path) -> None:
    _, out, rows = _replay(photos, "traced")
    with open(out / "frames.csv", newline="") as file:
        frames = {int(row["frame"]): row for row in csv.DictReader(file)}
    assert [Path(frames[i]["file"]).name for i in range(len(TURNS))] == [f"turn_{i}.png" for i in range(len(TURNS))]
    for row in rows:  # every poses.csv row names a frame of frames.csv, at the same time
        assert float(frames[int(row["frame"])]["timestamp_s"]) == pytest.approx(float(row["timestamp_s"]))


def test_a_later_video_replay_into_the_same_folder_leaves_no_stale_frames_csv(photos: Path, tmp_path: Path) -> None:
    """frames.csv belongs to its run: a video replayed into the same --out removes it with the other files."""
    _, out, _ = _replay(photos, "reused")
    assert (out / "frames.csv").is_file()
    video = _video_of(photos, tmp_path / "clip.avi")
    result = run_main(
        ["-q", "replay", str(video), "--camera", str(photos / "cam.yml"), "--marker-length", "0.06", "--out", str(out)]
    )
    assert_clean_exit(result, {0})
    assert not (out / "frames.csv").exists()


def _video_of(photos: Path, video: Path) -> Path:
    """The photos as the frames of an MJPG video at 30 fps."""
    images = [cv2.imread(str(path)) for path in sorted((photos / "shots").iterdir())]
    writer = cv2.VideoWriter(
        str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (images[0].shape[1], images[0].shape[0])
    )
    for image in images:
        writer.write(image)
    writer.release()
    return video


def test_a_video_given_the_image_options_says_they_are_ignored(photos: Path, tmp_path: Path) -> None:
    """Found by trying the tool as a new user: --fps 10 on a video ran at the video's own 30 fps, without a word."""
    video = _video_of(photos, tmp_path / "clip.avi")
    out = tmp_path / "out"
    argv = ["replay", str(video), "--camera", str(photos / "cam.yml"), "--marker-length", "0.06", "--out", str(out)]
    result = run_main(["-q", *argv, "--fps", "10", "--sequence"])
    assert_clean_exit(result, {0})
    warned = [line for line in result.stderr.splitlines() if "ignored" in line]
    assert len(warned) == 1 and "--fps and --sequence" in warned[0] and "clip.avi is a video" in warned[0], result
    with open(out / "poses.csv", newline="") as file:  # the video's own timing
        times = sorted({float(row["timestamp_s"]) for row in csv.DictReader(file)})
    assert times[1] - times[0] == pytest.approx(1 / 30, rel=1e-3)
    # and without them, nothing is said
    plain = run_main(["-q", *argv[:-1], str(tmp_path / "plain")])
    assert_clean_exit(plain, {0})
    assert "ignored" not in plain.stderr


@pytest.mark.parametrize("option", [("--sequence",), ("--fps", "10")])
def test_a_folder_said_to_be_a_sequence_is_tracked_as_one(photos: Path, option: tuple[str, ...]) -> None:
    result, out, rows = _replay(photos, "sequence" + option[0].strip("-"), *option, quiet=False)
    assert "tracked as one sequence" in result.stdout
    assert json.loads((out / "summary.json").read_text())["decided_with"] == "the whole recording"
    assert len(rows) >= len(TURNS)


@pytest.mark.realdata
def test_real_photos_get_the_answer_of_no_filter(realdata: Path, tmp_path: Path) -> None:
    """Five real photos of one ChArUco board from one camera, taken from unrelated viewpoints (OpenCV's
    calibration views): every marker of every photo gets the --no-filter answer, default and --causal."""
    import shutil

    folder = realdata / "opencv_contrib"
    (tmp_path / "shots").mkdir()
    for name in ("img_00.jpg", "img_01.jpg", "img_02.jpg", "img_03.jpg", "chocclusion_original.jpg"):
        shutil.copyfile(folder / name, tmp_path / "shots" / name)
    shutil.copyfile(folder / "tutorial_camera_charuco.yml", tmp_path / "cam.yml")
    common = ["--dictionary", "DICT_6X6_250"]
    _, _, alone = _replay(tmp_path, "alone", "--marker-length", "0.02", *common, "--no-filter")
    assert len(alone) >= 60  # (the --marker-length given twice: the last one counts)
    for mode in ((), ("--causal",)):
        _, _, rows = _replay(tmp_path, "run" + "".join(mode), "--marker-length", "0.02", *common, *mode)
        assert _answers(rows) == _answers(alone)
