"""Nothing the user owns is ever overwritten: every output is checked against every input and against the
other outputs before anything is written (exit 2 naming both), one run per ``--out`` (a lock file), a reused
``--out`` cleared of the previous run's own files only, ``--out ''`` and a bad ``--video-out`` refused."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.errors import InputError
from ar_anchor.run.paths import LOCK_NAME, OutDirLock, check_paths, clear_previous_run
from tests.helpers import assert_clean_exit, error_lines, run_main

CAMERA = Path(__file__).resolve().parents[2] / "configs" / "camera_synthetic.yml"
CHARUCO = ["--charuco", "5x7", "--square-m", "0.04", "--marker-m", "0.02", "--dictionary", "DICT_4X4_50"]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def video(tmp_path: Path) -> Path:
    """A three-frame 160x90 MJPG video (the synthetic camera's aspect)."""
    path = tmp_path / "in.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 90))
    for i in range(3):
        writer.write(np.full((90, 160, 3), 40 * i, np.uint8))
    writer.release()
    return path


def _replay(video: Path, *extra: str):
    return run_main(["-q", "replay", str(video), "--camera", str(CAMERA), *extra])


def _refused(result, *names: str) -> str:
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1, result.describe()
    for name in names:
        assert name in lines[0], result.describe()
    return lines[0]


# ------------------------------------------------------------------------------------ outputs vs inputs
def test_video_out_on_the_input_video_is_refused_and_the_video_untouched(tmp_path, video):
    before = _digest(video)
    line = _refused(_replay(video, "--out", str(tmp_path / "o"), "--video-out", str(video)), "--video-out", "SOURCE")
    assert str(video) in line
    assert _digest(video) == before
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_video_out_through_a_symlink_or_a_hard_link_to_the_input_is_refused(tmp_path, video):
    before = _digest(video)
    (tmp_path / "link.avi").symlink_to(video)
    os.link(video, tmp_path / "hard.avi")
    for other in ("link.avi", "hard.avi", "sub/../in.avi"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        _refused(_replay(video, "--out", str(tmp_path / "o"), "--video-out", str(tmp_path / other)), "--video-out")
    assert _digest(video) == before


def test_video_out_on_the_camera_file_is_refused(tmp_path, video):
    camera = tmp_path / "camera.mkv"  # a camera file named like a video: still an input
    camera.write_bytes(CAMERA.read_bytes())
    result = run_main(["-q", "replay", str(video), "--camera", str(camera), "--video-out", str(camera)])
    _refused(result, "--video-out", "--camera")
    assert camera.read_bytes() == CAMERA.read_bytes()


def test_out_over_the_source_folder_keeps_its_raw_video_input(tmp_path, video):
    # replay OUT/raw.mkv --out OUT: the reused --out is cleared, but never of this run's input
    out = tmp_path / "o"
    out.mkdir()
    raw = out / "raw.mkv"
    raw.write_bytes(video.read_bytes())
    before = _digest(raw)
    result = _replay(raw, "--out", str(out))
    assert result.code == 0, result.describe()
    assert _digest(raw) == before


def test_live_record_with_video_out_on_the_raw_recording_is_refused(tmp_path):
    out = tmp_path / "o"
    result = run_main(
        ["-q", "live", "--device", "synthetic", "--width", "320", "--height", "180", "--record", "--out", str(out)]
        + ["--video-out", str(out / "raw.mkv")]
    )
    _refused(result, "--video-out", "--record", "raw.mkv")
    assert not (out / "raw.mkv").exists()


def test_an_input_named_like_a_recording_part_in_out_is_refused(tmp_path, video):
    out = tmp_path / "o"
    out.mkdir()
    part = out / "recording.part2.rrd"
    part.write_bytes(video.read_bytes())
    _refused(_replay(part, "--out", str(out)), "recording.part2.rrd")
    assert part.read_bytes() == video.read_bytes()


def test_calibrate_rrd_on_its_own_out_is_refused(tmp_path, video):
    camera = tmp_path / "cam.yml"
    camera.write_text("keep me\n")
    result = run_main(["-q", "calibrate", str(video), *CHARUCO, "--out", str(camera), "--rrd", str(camera)])
    _refused(result, "--rrd", "--out")
    assert camera.read_text() == "keep me\n"


def test_calibrate_rrd_on_the_source_video_is_refused(tmp_path, video):
    before = _digest(video)
    result = run_main(["-q", "calibrate", str(video), *CHARUCO, "--out", str(tmp_path / "c.yml"), "--rrd", str(video)])
    _refused(result, "--rrd", "SOURCE")
    assert _digest(video) == before


@pytest.mark.parametrize("source", ["folder", "glob"])
def test_calibrate_out_on_a_source_photo_is_refused(tmp_path, source):
    shots = tmp_path / "shots"
    shots.mkdir()
    photo = shots / "a.png"
    cv2.imwrite(str(photo), np.zeros((30, 40, 3), np.uint8))
    before = _digest(photo)
    spec = str(shots) if source == "folder" else str(shots / "*.png")
    result = run_main(["-q", "calibrate", spec, *CHARUCO, "--out", str(photo)])
    _refused(result, "--out", "SOURCE", "a.png")
    assert _digest(photo) == before


def test_check_paths_names_both_and_allows_distinct_files(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.write_text("x")
    check_paths([("--out", b)], [("SOURCE", a)])  # distinct: fine
    with pytest.raises(InputError, match=r"--video-out .*b: is also --rrd .*b"):
        check_paths([("--rrd", b), ("--video-out", b)], [("SOURCE", a)])
    with pytest.raises(InputError, match=r"--rrd .*a: is the input SOURCE .*a"):
        check_paths([("--rrd", a)], [("SOURCE", a)])


# ------------------------------------------------------------------------------------ --out and --video-out
def test_empty_out_is_refused_not_the_current_folder(tmp_path, video, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = _replay(video, "--out", "")
    assert result.code == 2 and "--out" in result.stderr and "empty" in result.stderr, result.describe()
    assert not (tmp_path / "poses.csv").exists()


def test_video_out_to_a_directory_is_refused_before_the_run(tmp_path, video):
    (tmp_path / "d.mp4").mkdir()
    _refused(_replay(video, "--out", str(tmp_path / "o"), "--video-out", str(tmp_path / "d.mp4")), "--video-out")
    assert not (tmp_path / "o").exists()


def test_video_out_into_a_missing_folder_is_refused_before_the_run(tmp_path, video):
    line = _refused(_replay(video, "--out", str(tmp_path / "o"), "--video-out", str(tmp_path / "no" / "v.mp4")))
    assert "--video-out" in line and "does not exist" in line
    assert not (tmp_path / "o").exists()


def test_video_out_into_the_out_folder_it_creates_is_fine(tmp_path, video):
    out = tmp_path / "o"
    result = _replay(video, "--out", str(out), "--video-out", str(out / "v.mp4"))
    assert result.code == 0, result.describe()
    assert (out / "v.mp4").is_file()


# ------------------------------------------------------------------------------------ one run per --out
def test_a_second_run_on_a_busy_out_is_refused(tmp_path, video):
    out = tmp_path / "o"
    out.mkdir()
    sleeper = subprocess.Popen(["sleep", "30"])  # a live process that "holds" the lock
    try:
        (out / LOCK_NAME).write_text(f"{sleeper.pid} {os.uname().nodename}\n")
        line = _refused(_replay(video, "--out", str(out)), "--out", "another run")
        assert str(sleeper.pid) in line
        assert not (out / "poses.csv").exists() and not (out / "summary.json").exists()
    finally:
        sleeper.kill()
        sleeper.wait()
    assert (out / LOCK_NAME).exists()  # not ours to remove


def test_a_stale_lock_of_a_dead_process_is_taken_over_with_a_note(tmp_path, video):
    out = tmp_path / "o"
    out.mkdir()
    dead = subprocess.Popen(["true"])
    dead.wait()
    (out / LOCK_NAME).write_text(f"{dead.pid} {os.uname().nodename}\n")
    result = run_main(["replay", str(video), "--camera", str(CAMERA), "--out", str(out)])
    assert result.code == 0, result.describe()
    assert "taking over the lock" in result.stderr
    assert not (out / LOCK_NAME).exists()  # removed when the run ended


def test_the_lock_is_exclusive_between_holders_and_reentrant_within_one(tmp_path):
    lock = OutDirLock(tmp_path)
    with lock:
        assert (tmp_path / LOCK_NAME).read_text().split()[0] == str(os.getpid())
        with OutDirLock(tmp_path):  # the same process again (the CLI, then the run's outputs)
            pass
        assert (tmp_path / LOCK_NAME).exists()
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_reused_out_is_cleared_of_the_previous_runs_files_only(tmp_path, video):
    out = tmp_path / "o"
    out.mkdir()
    stale = ["recording.part2.rrd", "recording.part7.rrd", "raw.mkv", "raw.mkv.timestamps.csv", "old.mp4"]
    for name in stale:
        (out / name).write_text("previous run")
    previous = {
        "status": "completed",
        "frames_with_pose": 3,
        "latency_ms": {},
        "video_out": {"path": str(out / "old.mp4")},
    }
    (out / "summary.json").write_text(json.dumps(previous))
    mine = ["notes.txt", "recording.partX.rrd", "camera.yml", "other.mp4"]
    for name in mine:
        (out / name).write_text("the user's")
    result = _replay(video, "--out", str(out))
    assert result.code == 0, result.describe()
    for name in stale:
        assert not (out / name).exists(), name
    for name in mine:
        assert (out / name).read_text() == "the user's", name
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def test_clearing_never_removes_an_input_or_a_symlink(tmp_path):
    (tmp_path / "summary.json").write_text(json.dumps({"status": "completed", "frames_with_pose": 0, "latency_ms": {}}))
    (tmp_path / "raw.mkv").write_text("input")
    target = tmp_path / "elsewhere.rrd"
    target.write_text("keep")
    (tmp_path / "recording.rrd").symlink_to(target)
    removed = clear_previous_run(tmp_path, keep=[("SOURCE", tmp_path / "raw.mkv")])
    assert removed == []
    assert (tmp_path / "raw.mkv").read_text() == "input" and target.read_text() == "keep"


def test_a_folder_no_run_wrote_is_never_cleared(tmp_path):
    # given a folder of the user's own files that happen to carry a run's file names, and no run's summary
    for name in ("poses.csv", "recording.rrd", "recording.part1.rrd", "raw.mkv"):
        (tmp_path / name).write_text("the user's")
    (tmp_path / "summary.json").write_text("[1, 2]")  # JSON, but not a run's summary
    # then nothing is removed
    assert clear_previous_run(tmp_path) == []
    assert all((tmp_path / name).read_text() == "the user's" for name in ("poses.csv", "recording.rrd", "raw.mkv"))


def test_bad_input_found_after_the_out_folder_was_made_leaves_no_folder(tmp_path):
    # given a config whose overlay mesh does not exist (found only when the run builds its renderer)
    config = tmp_path / "c.toml"
    config.write_text('[markers]\nlength_m = 0.05\n\n[[overlays]]\ntarget = "marker:*"\nkind = "mesh"\npath = "x.glb"')
    result = run_main(["demo", "--frames", "3", "--config", str(config), "--out", str(tmp_path / "new" / "run")])
    # then exit 2 and the folder the run made is gone again
    assert result.code == 2, result.describe()
    assert not (tmp_path / "new" / "run").exists()


def test_out_holding_the_users_own_files_of_a_runs_names_is_refused(tmp_path, video):
    # given a folder of the user's own poses.csv, summary.json and recording.rrd (no run wrote them)
    out = tmp_path / "mine"
    out.mkdir()
    for name in ("poses.csv", "summary.json", "recording.rrd", "notes.txt"):
        (out / name).write_text("the user's")
    result = _replay(video, "--out", str(out))
    # then the run is refused naming them, and every file is untouched
    assert result.code == 2, result.describe()
    assert "poses.csv" in result.stderr and "no ar-anchor run wrote" in result.stderr, result.describe()
    assert all((out / name).read_text() == "the user's" for name in ("poses.csv", "summary.json", "recording.rrd"))
