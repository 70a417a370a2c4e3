"""``batch`` ends with a table of its recordings on the console, from the rows of its runs table."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import describe

CAMERA = CameraModel.from_fov(320, 240, 300.0)


def _folder(root: Path, name: str, frames: int, with_marker: int) -> Path:
    """``frames`` stills, the first ``with_marker`` of them showing a 6 cm marker at 0.4 m (the others blank)."""
    folder = root / name
    folder.mkdir()
    scene = SyntheticScene(
        camera=CAMERA,
        markers=(PlacedMarker(0, 0.06, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=0.4, azimuth_deg=10.0, elevation_deg=0.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        seed=0,
    )
    (frame,) = SyntheticSource(scene)
    for index in range(frames):
        image = frame.image if index < with_marker else frame.image * 0 + 128
        assert cv2.imwrite(str(folder / f"f{index}.png"), image)
    return folder


def test_batch_prints_one_line_per_recording(tmp_path: Path) -> None:
    # given two image folders (markers in 3 of 3 and 1 of 2 images) and a broken video
    seen = _folder(tmp_path, "seen", 3, 3)
    partly = _folder(tmp_path, "partly", 2, 1)
    (tmp_path / "broken.avi").write_bytes(b"RIFF" + bytes(200))
    CAMERA.to_yaml(tmp_path / "cam.yml")
    sources = [str(seen), str(partly), str(tmp_path / "broken.avi")]
    options = ["--camera", str(tmp_path / "cam.yml"), "--marker-length", "0.06", "--out", "out", "--jobs", "2"]
    command = [sys.executable, "-m", "ar_anchor", "batch", *sources, *options]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 1, describe(result)
    # then the console has a line per recording: frames, status, markers found in N of M, speed, folder
    names = ("seen", "partly", "broken")
    rows = {line.split()[0]: line.split() for line in result.stdout.splitlines() if line.startswith(names)}
    assert set(rows) == {"seen", "partly", "broken"}, result.stdout
    assert rows["seen"][1:5] == ["3", "ok", "3", "of"] and rows["seen"][5] == "3"
    assert rows["partly"][1:6] == ["2", "ok", "1", "of", "2"]
    assert rows["broken"][1:3] == ["-", "failed"]
    assert rows["seen"][-1] == "out/seen/"
    # (the broken video failed before its run began: no folder, and the table names none)
    assert rows["broken"][-1] == "-" and not (tmp_path / "out" / "broken").exists(), result.stdout
    summary = json.loads((tmp_path / "out" / "seen" / "summary.json").read_text())
    assert float(rows["seen"][6]) == round(summary["fps"], 1)
    assert "markers in: frames with markers found" in result.stdout
    # and the runs table holds the same figures
    import pyarrow.parquet as pq

    table = {row["name"]: row for row in pq.read_table(tmp_path / "out" / "runs.parquet").to_pylist()}
    assert table["partly"]["frames_with_markers"] == 1 and table["seen"]["frames_with_markers"] == 3
    # -q: no table
    quiet = subprocess.run([*command[:3], "-q", *command[3:], "--force"], cwd=tmp_path, capture_output=True,
                           text=True, timeout=300, check=False)  # fmt: skip
    assert quiet.returncode == 1 and "markers in" not in quiet.stdout, describe(quiet)


def test_batch_images_out_gives_each_image_recording_its_folder(tmp_path: Path) -> None:
    # given two image folders and a video
    seen = _folder(tmp_path, "seen", 2, 2)
    partly = _folder(tmp_path, "partly", 2, 1)
    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (CAMERA.width, CAMERA.height))
    for image in sorted(seen.iterdir()):
        writer.write(cv2.imread(str(image)))
    writer.release()
    CAMERA.to_yaml(tmp_path / "cam.yml")
    command = [sys.executable, "-m", "ar_anchor", "-q", "batch", str(seen), str(partly), str(clip),
               "--camera", str(tmp_path / "cam.yml"), "--out", "out", "--images-out", "ann", "--jobs", "2"]  # fmt: skip
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, describe(result)
    # then each image recording has its annotated copies under DIR/<name>/, the video none
    assert sorted(p.name for p in (tmp_path / "ann").iterdir()) == ["partly", "seen"]
    for name in ("seen", "partly"):
        copies = sorted(p.name for p in (tmp_path / "ann" / name).iterdir() if not p.name.startswith("."))
        assert copies == ["f0.png", "f1.png"]
        summary = json.loads((tmp_path / "out" / name / "summary.json").read_text())
        assert summary["images_out"]["images"] == 2
    assert "images_out" not in json.loads((tmp_path / "out" / "clip" / "summary.json").read_text())
