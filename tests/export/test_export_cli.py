"""`ar-anchor export` on run folders made here from known poses (fast tier): the MCAP read back with rosbags, the
options, and bad input (exit 2, one line naming the file)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.helpers import assert_clean_exit, error_lines, run_main

from .conftest import matrix_from_quaternion_xyzw, write_run


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message of an MCAP file by topic, (log time, message), read with rosbags and deserialised with the
    ROS 2 Humble definitions rosbags ships (not with the schema text the file carries)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    humble = get_typestore(Stores.ROS2_HUMBLE)
    messages: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path], default_typestore=humble) as reader:
        for connection, timestamp, raw in reader.messages():
            message = humble.deserialize_cdr(raw, connection.msgtype)
            # the file's own schema reads the same message: re-encoded with Humble's definitions, the same bytes
            assert humble.serialize_cdr(reader.deserialize(raw, connection.msgtype), connection.msgtype) == raw
            messages.setdefault(connection.topic, []).append((timestamp, message))
    return messages


def check_tf_against_poses_csv(bag: dict, poses_csv: Path) -> int:
    """Every frame of ``poses_csv`` has one /tf message at its time holding its rows' poses (to 1e-9), in order;
    returns the frames checked."""
    with poses_csv.open() as f:
        rows = list(csv.DictReader(f))
    frames: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        frames.setdefault(row["frame"], []).append(row)
    tf = bag.get("/tf", [])
    assert len(tf) == len(frames)
    for (timestamp, message), frame_rows in zip(tf, frames.values()):
        seconds, _, fraction = frame_rows[0]["timestamp_s"].partition(".")
        stamp_ns = int(seconds) * 1_000_000_000 + int(fraction.ljust(9, "0"))
        assert timestamp == stamp_ns
        assert [t.child_frame_id for t in message.transforms] == [
            r["target"].replace(":", "_").replace(" ", "_") for r in frame_rows
        ]
        for transform, row in zip(message.transforms, frame_rows):
            assert transform.header.frame_id == "camera"
            assert transform.header.stamp.sec * 1_000_000_000 + transform.header.stamp.nanosec == stamp_ns
            rotation, _ = cv2.Rodrigues(np.array([float(row[f"rvec_{a}"]) for a in "xyz"]))
            r = transform.transform.rotation
            np.testing.assert_allclose(matrix_from_quaternion_xyzw([r.x, r.y, r.z, r.w]), rotation, atol=1e-9)
            t = transform.transform.translation
            np.testing.assert_allclose([t.x, t.y, t.z], [float(row[f"tvec_{a}"]) for a in "xyz"], atol=1e-9)
    return len(frames)


def check_camera_info(messages: list, camera, distortion: list[float]) -> None:
    for _timestamp, info in messages:
        assert (info.width, info.height) == camera.size
        np.testing.assert_array_equal(info.k.reshape(3, 3), camera.camera_matrix)
        assert info.distortion_model == "plumb_bob"
        np.testing.assert_array_equal(info.d, distortion)
        np.testing.assert_array_equal(info.r.reshape(3, 3), np.eye(3))
        np.testing.assert_array_equal(info.p.reshape(3, 4)[:, :3], camera.camera_matrix)
        assert info.header.frame_id == "camera"


def test_export_writes_every_format_and_the_bag_reads_back_as_poses_csv(tmp_path):
    # given a run folder with known poses and a camera with distortion
    run = write_run(tmp_path / "run")
    # when exported with the defaults
    result = run_main(["export", str(run.path)])
    # then it succeeds, says what it wrote, and the bag holds poses.csv's poses and the calibration
    assert result.code == 0, result.describe()
    assert "poses_ext.csv, tum/ (3 files), run.mcap" in result.stdout
    bag = read_bag(run.path / "run.mcap")
    assert check_tf_against_poses_csv(bag, run.path / "poses.csv") == 3
    info = bag["/camera/camera_info"]
    assert [t for t, _ in info] == [t for t, _ in bag["/tf"]]  # one per frame with a pose, at its time
    check_camera_info(info, run.camera, list(run.camera.dist_coeffs))
    assert "/camera/image/compressed" not in bag


def test_export_into_another_folder_with_some_formats_and_a_camera_file(tmp_path):
    run = write_run(tmp_path / "run")
    camera_file = tmp_path / "cam.yml"
    run.camera.to_yaml(camera_file)
    result = run_main(["-q", "export", str(run.path), "--out", str(tmp_path / "x"), "--formats", "mcap,tum"])
    assert result.code == 0, result.describe()
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == [".ar-anchor-export.json", "run.mcap", "tum"]
    assert not (run.path / "run.mcap").exists()
    # a --camera without a file of the run: it is the one in CameraInfo
    summary = json.loads((run.path / "summary.json").read_text())
    del summary["camera"]
    (run.path / "summary.json").write_text(json.dumps(summary))
    result = run_main(["-q", "export", str(run.path), "--formats", "mcap", "--camera", str(camera_file)])
    assert result.code == 0, result.describe()
    check_camera_info(read_bag(run.path / "run.mcap")["/camera/camera_info"], run.camera, list(run.camera.dist_coeffs))


def _not_a_run(tmp_path: Path) -> list[str]:
    (tmp_path / "empty").mkdir()
    return ["export", str(tmp_path / "empty")]


def _poses(tmp_path: Path, text: str | None, *, camera: bool = True) -> list[str]:
    run = write_run(tmp_path / "run")
    if text is not None:
        (run.path / "poses.csv").write_text(text)
    if not camera:
        summary = json.loads((run.path / "summary.json").read_text())
        del summary["camera"]
        (run.path / "summary.json").write_text(json.dumps(summary))
    return ["export", str(run.path)]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: ["export", str(tmp / "missing")], r"RUN_DIR .*missing: no such directory"),
        (lambda tmp: (tmp / "f").write_text("x") and ["export", str(tmp / "f")], r"RUN_DIR .*f: is a file"),
        (_not_a_run, r"RUN_DIR .*empty: has no poses\.csv: not the output directory of an ar-anchor run"),
        (lambda tmp: _poses(tmp, ""), r"run/poses\.csv: line 1: not the header of a poses\.csv"),
        (lambda tmp: _poses(tmp, "frame,timestamp_s\n0,0\n"), r"run/poses\.csv: line 1: not the header"),
        (lambda tmp: _poses(tmp, "\x00\xff\xfe garbage"), r"run/poses\.csv: (not UTF-8|line 1)"),
        (lambda tmp: _poses(tmp, None, camera=False), r"neither a camera\.yml nor a camera in its summary\.json"),
        (lambda tmp: _poses(tmp, None) + ["--images"], r"--images: RUN_DIR .* has no raw\.mkv"),
        (lambda tmp: _poses(tmp, None) + ["--video", str(tmp / "nope.mp4")], r"nope\.mp4"),
        (lambda tmp: _poses(tmp, None) + ["--images", "--formats", "csv"], r"add mcap to --formats"),
        (lambda tmp: _poses(tmp, None) + ["--camera", str(tmp / "no.yml")], r"no\.yml"),
        (lambda tmp: _poses(tmp, None) + ["--out", str(tmp / "run" / "poses.csv")], r"poses\.csv.* is a file"),
    ],
    ids=[
        "missing",
        "file",
        "not-a-run",
        "empty-csv",
        "other-header",
        "binary",
        "no-camera",
        "no-raw-video",
        "no-video",
        "images-without-mcap",
        "no-camera-file",
        "out-is-a-file",
    ],
)
def test_bad_input_is_exit_2_with_one_line_naming_the_file(tmp_path, make, message):
    # when export is given bad input
    result = run_main(make(tmp_path))
    # then exit 2, one error line that names what is wrong, no traceback
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and result.stderr.strip() == lines[0], result.describe()
    import re

    assert re.search(message, lines[0]), result.describe()


def test_bad_formats_are_a_usage_error():
    result = run_main(["export", "somewhere", "--formats", "csv,ply"])
    assert result.code == 2 and result.system_exit
    assert "expected formats among csv,tum,mcap" in result.stderr


def test_live_export_images_needs_record(tmp_path):
    result = run_main(["live", "--device", "synthetic", "--export-images", "--out", str(tmp_path / "o")])
    assert result.code == 2, result.describe()
    assert error_lines(result.stderr) == [
        "ar-anchor: error: --export-images: a live run's frames are kept only with --record (raw.mkv)"
    ]
    assert not (tmp_path / "o").exists()


def _raw_video(run, stamps_ns: list[int]) -> None:
    """RUN/raw.mkv (+ timestamps) as `live --record` writes it: one frame per stamp, the camera's size."""
    from ar_anchor.run.outputs import RawVideoWriter

    writer = RawVideoWriter(run.path / "raw.mkv")
    try:
        for index, stamp in enumerate(stamps_ns):
            image = np.full((run.camera.height, run.camera.width, 3), 40 * index, np.uint8)
            writer.write(image, index, stamp)
    finally:
        writer.close()


def test_images_come_from_the_runs_raw_video_at_the_frames_times(tmp_path):
    # given a run with its raw video (frame times those of poses.csv)
    run = write_run(tmp_path / "run")
    _raw_video(run, [0, 33_333_333, 66_666_667])
    # when exported with --images
    result = run_main(["-q", "export", str(run.path), "--images", "--formats", "mcap"])
    # then each frame is an image with its camera info, at the frame's time, beside that frame's /tf
    assert result.code == 0, result.describe()
    bag = read_bag(run.path / "run.mcap")
    images = bag["/camera/image/compressed"]
    assert [t for t, _ in images] == [0, 33_333_333, 66_666_667] == [t for t, _ in bag["/camera/camera_info"]]
    assert check_tf_against_poses_csv(bag, run.path / "poses.csv") == 3
    decoded = [cv2.imdecode(np.frombuffer(m.data.tobytes(), np.uint8), cv2.IMREAD_COLOR) for _, m in images]
    assert [d.shape for d in decoded] == [(480, 640, 3)] * 3
    assert [round(float(d.mean())) for d in decoded] == [0, 40, 80]


def test_a_video_that_is_not_the_runs_is_refused_naming_the_frame(tmp_path):
    # given a raw video whose second frame is at another time than poses.csv's
    run = write_run(tmp_path / "run")
    _raw_video(run, [0, 40_000_000, 80_000_000])
    # when exported with its images
    result = run_main(["-q", "export", str(run.path), "--images"])
    # then exit 2 naming the frame, and nothing written
    assert result.code == 2, result.describe()
    assert error_lines(result.stderr) == [
        f"ar-anchor: error: {run.path / 'raw.mkv'}: frame 1 is at 0.040000000 s, in poses.csv (line 5) at "
        "0.033333333 s: not the frames of this run"
    ]
    names = sorted(p.name for p in run.path.iterdir())
    assert names == ["poses.csv", "raw.mkv", "raw.mkv.timestamps.csv", "summary.json"]
