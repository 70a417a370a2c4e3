"""``ar-anchor batch``: recordings found from sources and manifests, bad input as exit 2, and (slow) six
synthetic clips and a broken one replayed locally and on a local Ray, each ``poses.csv`` identical to a
single ``ar-anchor replay`` of the same clip, the broken one failing only its row, a second run skipping."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ar_anchor.cli import runs_table
from ar_anchor.cli.recordings import Recording, find_recordings, read_manifest
from ar_anchor.cli.runs_table import write_runs
from ar_anchor.errors import InputError
from tests.helpers import run_main

CLIPS = 6
FRAMES = 25


def _touch(path: Path, data: bytes = b"x") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


# ============================================================================ what a recording is


def test_a_folder_of_videos_is_its_videos_and_an_image_folder_is_one_recording(tmp_path):
    # given a folder of videos (with a stray image) and a folder of images
    for name in ("b.mp4", "a.avi", "note.png"):
        _touch(tmp_path / "videos" / name)
    for name in ("0001.png", "0002.png"):
        _touch(tmp_path / "shots" / name)
    # when
    found = find_recordings([str(tmp_path / "videos"), str(tmp_path / "shots")], None)
    # then
    assert [(Path(r.source).name, r.name) for r in found] == [("a.avi", "a"), ("b.mp4", "b"), ("shots", "shots")]


def test_colliding_names_are_made_unique_and_a_glob_expands(tmp_path):
    # given two clip.mp4 in different folders, one also matched by a glob
    _touch(tmp_path / "day1" / "clip.mp4")
    _touch(tmp_path / "day2" / "clip.mp4")
    # when
    found = find_recordings([str(tmp_path / "day1" / "clip.mp4"), str(tmp_path / "day*" / "*.mp4")], None)
    # then: the file named twice is replayed once; the other gets clip_2
    assert [r.name for r in found] == ["clip", "clip_2"]
    assert Path(found[1].source).parent.name == "day2"


@pytest.mark.parametrize(
    "argument, message",
    [
        ("missing.mp4", "no such file or folder"),
        ("empty_dir", "no video or image files"),
        ("nothing*.mp4", "no file matches this pattern"),
    ],
)
def test_sources_that_match_nothing_are_input_errors(tmp_path, argument, message):
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(InputError, match=message):
        find_recordings([str(tmp_path / argument)], None)


def test_no_sources_at_all_is_an_input_error():
    with pytest.raises(InputError, match="no SOURCE"):
        find_recordings([], None)


def test_a_manifest_gives_each_recording_its_camera_config_and_name(tmp_path):
    # given a manifest with relative paths and an optional name
    _touch(tmp_path / "v" / "one.mp4")
    _touch(tmp_path / "v" / "two.mp4")
    _touch(tmp_path / "cam.yml")
    _touch(tmp_path / "t.toml")
    manifest = tmp_path / "runs.csv"
    manifest.write_text("source,camera,config,name\nv/one.mp4,cam.yml,,first\nv/two.mp4,,t.toml,\n")
    # when
    found = read_manifest(manifest)
    # then
    assert found == [
        Recording(str(tmp_path / "v" / "one.mp4"), "first", tmp_path / "cam.yml", None),
        Recording(str(tmp_path / "v" / "two.mp4"), "two", None, tmp_path / "t.toml"),
    ]


@pytest.mark.parametrize(
    "text, message",
    [
        ("camera,name\na,b\n", "no 'source' column"),
        ("source,speed\nx.mp4,1\n", "unknown column 'speed'"),
        ("source\n", "no recordings"),
        ("source\nmissing.mp4\n", "line 2: .*missing.mp4: no such file"),
    ],
)
def test_a_bad_manifest_is_an_input_error_naming_the_problem(tmp_path, text, message):
    manifest = tmp_path / "m.csv"
    manifest.write_text(text)
    with pytest.raises(InputError, match=message):
        read_manifest(manifest)


def test_an_unreadable_manifest_is_exit_2_in_one_line(tmp_path):
    result = run_main(["batch", "--manifest", str(tmp_path / "none.csv"), "--out", str(tmp_path / "out")])
    assert result.code == 2, result.describe()
    assert result.stderr.strip().count("\n") == 0 and "cannot read it" in result.stderr


def test_no_matching_source_is_exit_2_and_writes_nothing(tmp_path):
    result = run_main(["batch", str(tmp_path / "*.mp4"), "--out", str(tmp_path / "out")])
    assert result.code == 2, result.describe()
    assert not (tmp_path / "out").exists()


def test_ray_missing_is_exit_2_in_one_line(tmp_path, monkeypatch):
    # given a video and no ray module
    _touch(tmp_path / "a.mp4")
    monkeypatch.setitem(sys.modules, "ray", None)
    # when
    result = run_main(["batch", str(tmp_path / "a.mp4"), "--ray", "--out", str(tmp_path / "out")])
    # then
    assert result.code == 2, result.describe()
    assert "pip install 'ar-anchor[cluster]'" in result.stderr
    assert not (tmp_path / "out").exists()


def test_a_source_after_ray_is_not_taken_for_its_address(tmp_path):
    result = run_main(["batch", "--ray", "clip.mp4", "--out", str(tmp_path / "out")])
    assert result.code == 2 and "put --ray after the sources" in result.stderr, result.describe()


def test_the_runs_table_is_csv_without_pyarrow(tmp_path, monkeypatch):
    # given no pyarrow
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    row = runs_table.empty_row(Recording("a.mp4", "a"), tmp_path / "a")
    row.update(status="failed", error="broken", frames=3)
    # when
    path = write_runs(tmp_path, [row])
    # then
    assert path.name == "runs.csv"
    rows = list(csv.DictReader(path.open()))
    assert rows[0]["status"] == "failed" and rows[0]["frames"] == "3" and rows[0]["fps"] == ""


# ============================================================================ end to end (slow)


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> Path:
    """Six 25-frame 320x240 H.264 clips of the demo scene (hand-held camera), their camera and config, and a
    truncated broken.mp4."""
    from ar_anchor.bench.speed.scenes import encode_scene
    from ar_anchor.camera import CameraModel
    from ar_anchor.config import demo_config
    from ar_anchor.config.document import demo_toml
    from ar_anchor.synthetic import Trajectory, demo_scene

    root = tmp_path_factory.mktemp("batch_clips")
    videos = root / "videos"
    videos.mkdir()
    camera = CameraModel.from_fov(320, 240, 250.0)
    for k in range(CLIPS):
        trajectory = Trajectory(kind="handheld", near_m=0.35, far_m=1.0, look_at=(-0.01, 0, 0), seed=k, duration_s=1)
        scene = demo_scene(demo_config(), camera, frames=FRAMES, trajectory=trajectory, fps=25.0, seed=k)
        encode_scene(videos / f"clip{k}.mp4", scene)
    (videos / "broken.mp4").write_bytes((videos / "clip0.mp4").read_bytes()[:3000])
    camera.to_yaml(root / "camera.yml")
    (root / "demo.toml").write_text(demo_toml())
    return root


@pytest.fixture(scope="module")
def single_replays(clips) -> Path:
    """Each clip replayed alone by ``ar-anchor replay``, in-process (``main()``, as the command runs it): only
    its outputs are compared with the batch's, whose own processes are what is tested."""
    out = clips / "single"
    results = [
        run_main(["-q", "replay", str(clips / "videos" / f"clip{k}.mp4"), "--camera", str(clips / "camera.yml"),
                  "--config", str(clips / "demo.toml"), "--out", str(out / f"clip{k}")])
        for k in range(CLIPS)
    ]  # fmt: skip
    assert all(r.code == 0 for r in results), [r.describe() for r in results]
    return out


def _batch(clips: Path, out: Path, *engine: str) -> subprocess.CompletedProcess[str]:
    command = [
        sys.executable, "-m", "ar_anchor", "batch", str(clips / "videos"), "--camera", str(clips / "camera.yml"),
        "--config", str(clips / "demo.toml"), "--out", str(out), "--jobs", "2", *engine,
    ]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)


def _rows(out: Path) -> dict[str, dict]:
    import pyarrow.parquet as pq

    return {row["name"]: row for row in pq.read_table(out / "runs.parquet").to_pylist()}


def _check_batch(result: subprocess.CompletedProcess[str], out: Path, single: Path) -> None:
    # the broken clip fails its row only: exit 1, naming how many failed
    assert result.returncode == 1, result.stderr
    assert "1 of 7 recording(s) failed: broken" in result.stderr
    assert "Traceback" not in result.stderr
    rows = _rows(out)
    assert rows["broken"]["status"] == "failed" and "broken.mp4" in rows["broken"]["error"]
    assert "\n" not in rows["broken"]["error"]
    for k in range(CLIPS):
        row = rows[f"clip{k}"]
        assert row["status"] == "ok" and row["frames"] == FRAMES, row
        assert 0 <= row["detection_rate"] <= 1 and row["wall_s"] > 0
        assert set(json.loads(row["targets"])) >= {"marker:0", "board:desk"}
        # the same outputs as replay writes, poses.csv byte for byte
        assert (out / f"clip{k}" / "poses.csv").read_bytes() == (single / f"clip{k}" / "poses.csv").read_bytes()
        summary = json.loads((out / f"clip{k}" / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["command"] == "replay"
        assert (out / f"clip{k}" / "recording.rrd").is_file()
    # the last line names the table and every file of each run's folder (not the failed one's)
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith(f"outputs: {out}/ (runs.parquet, clip0/ (poses.csv, summary.json, recording"), last
    for k in range(CLIPS):
        files = sorted(p.name for p in (out / f"clip{k}").iterdir() if not p.name.startswith("."))
        listed = last.split(f"clip{k}/ (", 1)[1].split(")", 1)[0].split(", ")
        assert sorted(listed) == files, (files, last)
    assert "broken/" not in last


@pytest.mark.slow
def test_batch_on_local_processes_matches_single_replays_and_skips_on_a_second_run(clips, single_replays):
    out = clips / "out_local"
    # when
    result = _batch(clips, out)
    # then
    _check_batch(result, out, single_replays)
    # and a second run skips every completed recording (the broken one is tried again)
    again = _batch(clips, out)
    assert again.returncode == 1
    assert "0 replayed, 6 skipped (already done), 1 failed" in again.stdout, again.stdout
    assert [row["status"] for name, row in sorted(_rows(out).items())] == ["failed"] + ["skipped"] * CLIPS
    # and other options replay them again, as does --force
    options_changed = _batch(clips, out, "--max-frames", "5")
    assert "6 replayed, 0 skipped" in options_changed.stdout, options_changed.stdout
    forced = _batch(clips, out, "--max-frames", "5", "--force")
    assert "6 replayed, 0 skipped" in forced.stdout, forced.stdout
    assert {row["frames"] for name, row in _rows(out).items() if name != "broken"} == {5}


@pytest.mark.slow
def test_batch_on_a_local_ray_matches_single_replays(clips, single_replays):
    pytest.importorskip("ray")
    out = clips / "out_ray"
    before = _raylets()
    # when: a local Ray of 2 CPUs, started and shut down by the command
    result = _batch(clips, out, "--ray")
    # then
    _check_batch(result, out, single_replays)
    assert _raylets() <= before  # its Ray is gone


def _raylets() -> set[str]:
    found = subprocess.run(["pgrep", "-f", "raylet"], capture_output=True, text=True, check=False)
    return set(found.stdout.split())


@pytest.mark.slow
def test_ctrl_c_stops_the_batch_with_a_row_for_every_recording_and_exit_130(clips):
    out = clips / "out_interrupted"
    command = [
        sys.executable, "-m", "ar_anchor", "batch", str(clips / "videos"), "--camera", str(clips / "camera.yml"),
        "--config", str(clips / "demo.toml"), "--out", str(out), "--jobs", "2",
    ]  # fmt: skip
    # given a batch under way, one recording done
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + 300
    while not list(out.glob("*/batch.json")) and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.2)
    # when Ctrl-C reaches its process group (as from a terminal)
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    # then
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" in stderr
    statuses = [row["status"] for row in _rows(out).values()]
    assert len(statuses) == CLIPS + 1 and "ok" in statuses and "interrupted" in statuses, statuses


def test_a_row_holds_the_summary_figures_and_with_rigid_sheet_the_pair_flips(tmp_path):
    # given a run's summary.json (two markers, 20 frames) and a poses.csv of two markers on one sheet
    from ar_anchor.cli.batch_task import fill_row

    states = {"tracked": 15, "ambiguous": 3, "predicted": 0, "interpolated": 0}
    summary = {
        "frames": 20,
        "frames_with_pose": 18,
        "fps": 40.0,
        "ground_truth": True,
        "targets": {
            "marker:0": {
                "states": states,
                "rotation_error_deg": {"median": 0.5, "p95": 2.0},
                "wrong_frames": 1,
                "frames_scored": 16,
            },
            "board:group-1": {"states": {"tracked": 2}},  # a learned group, for 2 frames: not counted lost
            "marker:1": {
                "states": states,
                "rotation_error_deg": {"median": 0.5, "p95": 3.0},
                "wrong_frames": 3,
                "frames_scored": 24,
            },
        },
    }
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    header = "frame,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z\n"
    lines = [f"{f},marker:{m},tracked,0,0,0.0{f % 3},{0.1 * m},0,1\n" for f in range(15) for m in (0, 1)]
    (tmp_path / "poses.csv").write_text(header + "".join(lines))
    row = runs_table.empty_row(Recording("a.mp4", "a"), tmp_path)
    # when
    fill_row(row, tmp_path, rigid_sheet=True)
    # then
    assert row["frames"] == 20 and row["fps"] == 40.0 and row["detection_rate"] == 0.9
    assert row["tracked_fraction"] == 0.75 and row["ambiguous_fraction"] == 0.15
    assert row["lost_fraction"] == pytest.approx(0.1)
    assert json.loads(row["targets"])["marker:1"]["lost"] == 2
    assert row["rotation_error_p95_deg"] == 3.0 and row["wrong_frame_rate"] == 0.1
    assert row["pair_frames"] == 15 and row["pair_flip_pct"] == 0.0
