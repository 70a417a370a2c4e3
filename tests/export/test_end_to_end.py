"""Exports of real runs (slow: each tracks a synthetic scene): the MCAP of `demo --export-images` read back with
rosbags, TUM trajectories against the synthetic scene's exact truth, and an export that fails after a good run."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.geometry import angle_between_deg
from ar_anchor.run.loop import run_session
from ar_anchor.run.options import RunOptions
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import Trajectory, demo_scene
from ar_anchor.targets import TargetId
from ar_anchor.tools.export import export_run
from ar_anchor.track.tracker import Tracker
from tests.helpers import error_lines, run_main

from .conftest import check_poses_ext, matrix_from_quaternion_xyzw
from .test_export_cli import check_camera_info, check_tf_against_poses_csv, read_bag

pytestmark = pytest.mark.slow

FRAMES = 30
DEMO_TARGETS = ["board:desk", "marker:0", "marker:7", "marker:10", "marker:11", "marker:12", "marker:13"]


def _calibration_file() -> CameraModel:
    """configs/camera_synthetic.yml (the demo's camera), read with OpenCV's FileStorage directly."""
    from pathlib import Path

    path = Path(__file__).parents[2] / "configs" / "camera_synthetic.yml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        matrix = storage.getNode("camera_matrix").mat()
        dist = storage.getNode("distortion_coefficients").mat().reshape(-1)
        size = int(storage.getNode("image_width").real()), int(storage.getNode("image_height").real())
    finally:
        storage.release()
    return CameraModel(matrix, dist, *size)


def test_demo_export_images_reads_back_as_poses_csv_with_the_calibration_and_the_frames(tmp_path):
    # given a demo run with --export-images
    out = tmp_path / "run"
    result = run_main(["-q", "demo", "--frames", str(FRAMES), "--export-images", "--out", str(out)])
    assert result.code == 0, result.describe()
    assert f"run.mcap: {FRAMES} /tf, {FRAMES} camera_info, {FRAMES} images" in result.stdout
    # then the bag, read with rosbags, holds poses.csv's poses frame by frame (to 1e-9)
    bag = read_bag(out / "run.mcap")
    assert check_tf_against_poses_csv(bag, out / "poses.csv") == FRAMES
    # and one camera info per frame, equal to the calibration file the demo renders with
    calibration = _calibration_file()
    check_camera_info(bag["/camera/camera_info"], calibration, list(calibration.dist_coeffs))
    # and every frame as a JPEG of the camera's size, stamped with the frame's time
    images = bag["/camera/image/compressed"]
    frame_times = [round(i * 1e9 / 30) for i in range(FRAMES)]
    assert [t for t, _ in images] == [t for t, _ in bag["/camera/camera_info"]]
    assert [t for t, _ in images] == pytest.approx(frame_times, abs=1)
    for _t, message in images[:: FRAMES // 3]:
        assert message.format == "jpeg"
        image = cv2.imdecode(np.frombuffer(message.data.tobytes(), np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (calibration.height, calibration.width, 3)
    # and poses_ext.csv agrees with poses.csv
    assert check_poses_ext(out) > FRAMES


def test_tum_trajectories_follow_the_true_camera(tmp_path):
    # given a synthetic run with exact truth, the camera 0.35 to 1 m from the targets
    camera, config = CameraModel.default_synthetic(), demo_config()
    trajectory = Trajectory(kind="sweep", near_m=0.35, far_m=1.0, look_at=(-0.01, 0.0, 0.0))
    scene = demo_scene(config, camera, frames=FRAMES, seed=0, trajectory=trajectory)
    out = tmp_path / "run"
    with SyntheticSource(scene) as source:
        run_session(source, Tracker(config, camera), out, RunOptions(overlays=False))
    # when exported as TUM
    export_run(out, formats=("tum",))
    # then each file's camera position and orientation are the true camera's in that target's frame (the true
    # target_from_camera), within the tracker's error: measured on this scene for `tracked` rows, at most 5.8 mm
    # and 0.39 degrees (a marker at 1 m), medians 0.3 mm and 0.03 degrees; the board at most 0.9 mm
    states = {(r["timestamp_s"], r["target"]): r["state"] for r in csv.DictReader((out / "poses.csv").open())}
    truth_source = SyntheticSource(scene)
    position_errors, angle_errors, compared, lines_read = [], [], 0, 0
    files = sorted((out / "tum").iterdir())
    assert {f.name for f in files} == {f"{TargetId.parse(t).path_part}.txt" for t in DEMO_TARGETS}
    for path in files:
        kind, _, name = path.stem.partition("_")
        target = TargetId(kind, name)
        for line in path.read_text().splitlines():
            if line.startswith("#"):
                continue
            lines_read += 1
            stamp, *values = line.split(" ")
            if states[(stamp, target)] != "tracked":
                continue
            index = round(float(stamp) * scene.fps)
            true_pose = truth_source.truth(truth_source.camera_from_world(index))[target]
            true_centre = -true_pose.rotation.T @ true_pose.tvec
            position = np.array([float(v) for v in values[:3]])
            orientation = matrix_from_quaternion_xyzw(np.array([float(v) for v in values[3:]]))
            position_errors.append(np.linalg.norm(position - true_centre))
            angle_errors.append(angle_between_deg(orientation, true_pose.rotation.T))
            limit_m = 0.002 if target.is_board else 0.010
            assert position_errors[-1] < limit_m, (target, stamp, position, true_centre)
            assert angle_errors[-1] < 1.0, (target, stamp)
            compared += 1
    assert lines_read == len(states) and compared >= 0.9 * lines_read
    assert np.median(position_errors) < 0.001 and np.median(angle_errors) < 0.1


def test_a_failed_export_after_a_good_run_is_one_line_and_exit_1_and_the_run_stays(tmp_path):
    # given a previous run's folder in which a file named tum is in the way of the TUM export
    out = tmp_path / "run"
    assert run_main(["-q", "demo", "--frames", "2", "--out", str(out)]).code == 0
    (out / "tum").write_text("in the way")
    # when a run with --export goes into it
    result = run_main(["-q", "demo", "--frames", "3", "--export", "--out", str(out)])
    # then the run's outputs are complete, and the export's failure is one line and exit code 1
    assert result.code == 1, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and "export of" in lines[0] and "tum: is not a folder" in lines[0], result.describe()
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"
    rows = list(csv.DictReader((out / "poses.csv").open()))
    assert {row["frame"] for row in rows} == {"0", "1", "2"}
    assert not (out / "poses_ext.csv").exists() and not (out / "run.mcap").exists()
    # and once the way is clear, `ar-anchor export` of that run works
    (out / "tum").unlink()
    result = run_main(["-q", "export", str(out)])
    assert result.code == 0, result.describe()
    assert check_tf_against_poses_csv(read_bag(out / "run.mcap"), out / "poses.csv") == 3
