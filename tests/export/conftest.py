"""Helpers of the export tests: a run folder written from known poses, and a quaternion's matrix written out."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ar_anchor.camera import CameraModel
from ar_anchor.run.outputs import POSES_CSV_HEADER


def matrix_from_quaternion_xyzw(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w; Hamilton), the textbook formula."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass
class KnownRun:
    path: Path
    rows: list[list[str]]
    camera: CameraModel


def write_run(path: Path) -> KnownRun:
    """A run folder as ar-anchor leaves it, as far as the export reads it: poses.csv (7 rows over 3 frames: a
    board with a space in its name, two markers, one row predicted without a raw pose) and summary.json
    (frames, camera)."""
    rng = np.random.default_rng(0)
    camera = CameraModel(
        np.array([[800.0, 0.0, 319.5], [0.0, 805.0, 239.5], [0.0, 0.0, 1.0]]),
        np.array([0.1, -0.05, 0.001, -0.002, 0.01]),
        640,
        480,
    )
    rows = []
    frames = [(0, "0.000000000"), (1, "0.033333333"), (2, "0.066666667")]
    for frame, stamp in frames:
        targets = [("board:my desk", "tracked"), ("marker:0", "ambiguous"), ("marker:7", "tracked")]
        if frame == 2:
            targets = [("marker:0", "predicted")]
        for target, state in targets:
            rvec = rng.uniform(-3, 3, 3)
            tvec = rng.uniform(-0.5, 0.5, 3) + [0, 0, 1.0]
            pose = [repr(float(v)) for v in (*rvec, *tvec)]
            raw = [""] * 6 if state == "predicted" else [repr(float(v + 1e-4)) for v in (*rvec, *tvec)]
            rows.append([str(frame), stamp, target, state, *pose, *raw, "" if state == "predicted" else "0.1", ""])
    path.mkdir(parents=True)
    with (path / "poses.csv").open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(POSES_CSV_HEADER)
        writer.writerows(rows)
    camera_entry = {
        "image_width": camera.width,
        "image_height": camera.height,
        "camera_matrix": camera.camera_matrix.tolist(),
        "distortion_coefficients": camera.dist_coeffs.tolist(),
    }
    summary = {"status": "completed", "frames": 3, "frames_with_pose": 3, "latency_ms": {}, "camera": camera_entry}
    (path / "summary.json").write_text(json.dumps(summary))
    return KnownRun(path, rows, camera)


def check_poses_ext(run_dir: Path) -> int:
    """``poses_ext.csv`` of ``run_dir`` row by row against its ``poses.csv``: same frame, time, target and state;
    the same rotation as quaternion and as matrix (against OpenCV's Rodrigues), the same translation; the raw
    pose's too. Returns the rows checked."""
    import cv2

    with (run_dir / "poses.csv").open() as f:
        original = list(csv.DictReader(f))
    with (run_dir / "poses_ext.csv").open() as f:
        exported = list(csv.DictReader(f))
    assert len(exported) == len(original) > 0
    keys = ("frame", "timestamp_s", "target", "state")
    for before, after in zip(original, exported):
        assert [after[k] for k in keys] == [before[k] for k in keys]
        rvec = np.array([float(before[f"rvec_{a}"]) for a in "xyz"])
        tvec = np.array([float(before[f"tvec_{a}"]) for a in "xyz"])
        rotation, _ = cv2.Rodrigues(rvec)
        q = np.array([float(after[k]) for k in ("qx", "qy", "qz", "qw")])
        assert q[3] >= 0
        np.testing.assert_allclose(matrix_from_quaternion_xyzw(q), rotation, atol=1e-9)
        assert [float(after[k]) for k in ("tx", "ty", "tz")] == list(tvec)
        matrix = np.array([float(after[f"m{r}{c}"]) for r in range(4) for c in range(4)]).reshape(4, 4)
        np.testing.assert_allclose(matrix[:3, :3], rotation, atol=1e-12)
        assert list(matrix[:3, 3]) == list(tvec) and list(matrix[3]) == [0.0, 0.0, 0.0, 1.0]
        raw_keys = ("raw_qx", "raw_qy", "raw_qz", "raw_qw", "raw_tx", "raw_ty", "raw_tz")
        if before["raw_rvec_x"] == "":
            assert all(after[k] == "" for k in raw_keys)
        else:
            raw_rotation, _ = cv2.Rodrigues(np.array([float(before[f"raw_rvec_{a}"]) for a in "xyz"]))
            raw_q = np.array([float(after[k]) for k in raw_keys[:4]])
            np.testing.assert_allclose(matrix_from_quaternion_xyzw(raw_q), raw_rotation, atol=1e-9)
            assert [float(after[k]) for k in raw_keys[4:]] == [float(before[f"raw_tvec_{a}"]) for a in "xyz"]
    return len(exported)
