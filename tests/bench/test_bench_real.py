"""``ar-anchor bench real``: the rigid-sheet scoring on hand-made poses, exact agreement with
``../shared/tools/rigid_sheet.py``, and one run on chessboard.avi (skips when the real data is absent)."""

from __future__ import annotations

import importlib.util
import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.bench.real import (
    layout_relative_poses,
    read_poses_csv,
    score_against_layout,
    score_rigid_sheet,
)
from ar_anchor.boards import layout_from_mapping
from ar_anchor.cli.main import main
from ar_anchor.geometry import marker_corners_in_marker

# ../shared/tools/rigid_sheet.py: beside $AR_ANCHOR_REALDATA when set, else beside the repository
RIGID_SHEET = (
    (
        Path(os.environ["AR_ANCHOR_REALDATA"]).parent
        if os.environ.get("AR_ANCHOR_REALDATA")
        else Path(__file__).resolve().parents[2].parent / "shared"
    )
    / "tools"
    / "rigid_sheet.py"
)
SCORE_KEYS = ("pair_frames", "flip_pct", "rel_rot_rms_deg", "rel_trans_rms_mm", "marker_frames")
LENGTH_M = 0.04
# marker id -> centre on the sheet (metres), x right, y up
CENTRES = {0: (0.0, 0.0), 1: (0.06, 0.0), 2: (0.0, 0.06), 3: (0.06, 0.06)}


@pytest.fixture(scope="module")
def rigid_sheet():
    if not RIGID_SHEET.is_file():
        pytest.skip(f"{RIGID_SHEET} not found")
    spec = importlib.util.spec_from_file_location("rigid_sheet", RIGID_SHEET)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _matrix(rvec, tvec) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    m[:3, 3] = tvec
    return m


def _pose(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(matrix[:3, :3])[0].ravel(), matrix[:3, 3].copy()


def _sheet_poses(frames: int = 20, seed: int = 0, noise_deg: float = 0.0, noise_m: float = 0.0):
    """camera_from_marker for the 4 markers of CENTRES over ``frames`` random views of the sheet."""
    rng = np.random.default_rng(seed)
    poses: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {f"marker:{i}": {} for i in CENTRES}
    for f in range(frames):
        camera_from_sheet = _matrix(rng.normal(0, 0.3, 3) + [np.pi, 0, 0], [0.0, 0.0, 0.5] + rng.normal(0, 0.05, 3))
        for i, (x, y) in CENTRES.items():
            sheet_from_marker = np.eye(4)
            sheet_from_marker[:3, 3] = (x, y, 0.0)
            jitter = _matrix(np.radians(noise_deg) * rng.normal(size=3), noise_m * rng.normal(size=3))
            poses[f"marker:{i}"][f] = _pose(camera_from_sheet @ sheet_from_marker @ jitter)
    return poses


def _layout():
    return layout_from_mapping(
        {
            "markers": [
                {"id": i, "corners": (marker_corners_in_marker(LENGTH_M) + (x, y, 0.0)).tolist()}
                for i, (x, y) in CENTRES.items()
            ]
        },
        "test layout",
    )


def _flipped(pose, degrees: float = 30.0):
    """The marker turned about its own x axis (as a wrong planar solution is)."""
    return _pose(_matrix(*pose) @ _matrix([np.radians(degrees), 0.0, 0.0], [0.0, 0.0, 0.0]))


# ---------------------------------------------------------------------------- scoring, hand-made poses


def test_noise_free_rigid_sheet_scores_zero():
    score = score_rigid_sheet(_sheet_poses())
    assert score["pair_frames"] == 6 * 20 and score["pairs"] == 6
    assert score["flips"] == 0 and score["flip_pct"] == 0.0
    assert score["rel_rot_rms_deg"] == pytest.approx(0.0, abs=1e-5)
    assert score["rel_trans_rms_mm"] == pytest.approx(0.0, abs=1e-9)
    assert score["marker_frames"] == 4 * 20


def test_one_injected_flip_counts_its_pairs_exactly():
    poses = _sheet_poses()
    poses["marker:2"][7] = _flipped(poses["marker:2"][7])
    score = score_rigid_sheet(poses)
    # marker 2 in frame 7 pairs with markers 0, 1 and 3 in that frame: three flipped pair-frames
    assert score["flips"] == 3
    assert score["flip_pct"] == pytest.approx(100 * 3 / 120)
    assert score["rel_rot_rms_deg"] < 3.0  # the others only feel the flip through the pair mean


def test_noise_shows_in_the_rms_and_other_targets_are_ignored():
    poses = _sheet_poses(noise_deg=0.5, noise_m=0.001)
    poses["board:sheet"] = {0: (np.zeros(3), np.ones(3))}
    score = score_rigid_sheet(poses)
    assert score["flips"] == 0
    assert 0.3 < score["rel_rot_rms_deg"] < 2.0
    assert 0.5 < score["rel_trans_rms_mm"] < 5.0
    assert score["marker_frames"] == 80


def test_pairs_seen_together_too_rarely_are_not_scored():
    poses = _sheet_poses(frames=9)
    score = score_rigid_sheet(poses)
    assert score["pair_frames"] == 0 and score["flip_pct"] == 0.0
    assert math.isnan(score["rel_rot_rms_deg"]) and math.isnan(score["rel_trans_rms_mm"])
    assert score["marker_frames"] == 36
    assert score_rigid_sheet({})["pair_frames"] == 0


def test_layout_relative_poses_and_scoring_against_the_layout():
    board_from = layout_relative_poses(_layout())
    np.testing.assert_allclose(board_from[1][:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(board_from[1][:3, 3], (0.06, 0.0, 0.0), atol=1e-12)
    poses = _sheet_poses()
    clean = score_against_layout(poses, _layout())
    assert clean["pair_frames"] == 120 and clean["flips"] == 0
    assert clean["distance_ratio"] == pytest.approx(1.0) and clean["mean_offset_rms_deg"] == pytest.approx(0, abs=1e-5)
    assert clean["rel_rot_rms_deg"] == pytest.approx(0.0, abs=1e-5)
    assert clean["rel_trans_rms_mm"] == pytest.approx(0.0, abs=1e-9)
    # a marker the layout lacks: its pairs are left out
    poses["marker:9"] = dict(poses["marker:3"])
    assert score_against_layout(poses, _layout())["pairs_unknown"] == 4
    # a marker flipped in most frames pulls its pairs' mean, but the layout still sees every flip
    for f in range(15):
        poses["marker:2"][f] = _flipped(poses["marker:2"][f])
    assert score_against_layout(poses, _layout())["flips"] == 15 * 3
    assert score_rigid_sheet(poses)["flips"] < 15 * 3


# ---------------------------------------------------------------------------- agreement with rigid_sheet.py


def _write_csv(path: Path, poses, states=None) -> None:
    """rigid_sheet.py's poses.csv columns, numbers as repr (exact round trip)."""
    header = (
        "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
        "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
    )
    lines = [header]
    for target, frames in poses.items():
        for f, (rvec, tvec) in frames.items():
            state = (states or {}).get((target, f), "tracked")
            output = [repr(float(v)) for v in (*rvec, *tvec)]
            raw = ["", "", "", "", "", ""] if state == "predicted" else [repr(float(v)) for v in (*rvec, *tvec)]
            lines.append(",".join([str(f), "", target, state, *output, *raw, "", ""]))
    path.write_text("\n".join(lines) + "\n")


def _same(ours: dict, theirs: dict) -> None:
    for key in SCORE_KEYS:
        a, b = ours[key], theirs[key]
        assert (math.isnan(a) and math.isnan(b)) or a == b, (key, a, b)


def test_scores_agree_exactly_with_rigid_sheet_py(rigid_sheet, tmp_path):
    poses = _sheet_poses(frames=40, seed=3, noise_deg=1.0, noise_m=0.002)
    for f in (2, 11, 30):
        poses["marker:1"][f] = _flipped(poses["marker:1"][f], 25.0)
    del poses["marker:3"][5]
    states = {("marker:0", f): "predicted" for f in range(0, 40, 4)}
    states.update({("marker:2", f): "ambiguous" for f in range(1, 40, 3)})
    path = tmp_path / "poses.csv"
    _write_csv(path, poses, states)
    for raw in (False, True):
        for keep in (None, {"tracked"}, {"tracked", "ambiguous"}, {"predicted"}):
            ours = score_rigid_sheet(read_poses_csv(path, raw=raw, states=keep))
            _same(ours, rigid_sheet.score(rigid_sheet.read(str(path), raw, keep)))
    assert score_rigid_sheet(read_poses_csv(path))["flips"] >= 3 * 3


# ---------------------------------------------------------------------------- the command


def test_missing_default_data_is_a_clear_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(tmp_path / "nowhere"))
    out = tmp_path / "out"
    assert main(["-q", "bench", "real", "--out", str(out)]) == 2
    assert "chessboard.avi is missing" in capsys.readouterr().err
    assert not out.exists()
    assert main(["-q", "bench", "real", "--video", str(tmp_path / "none.avi"), "--out", str(out)]) == 2
    assert "--video" in capsys.readouterr().err


@pytest.mark.realdata
@pytest.mark.slow
def test_bench_real_on_chessboard_video(realdata, rigid_sheet, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AR_ANCHOR_REALDATA", str(realdata))
    out = tmp_path / "results"
    assert main(["-q", "bench", "real", "--out", str(out)]) == 0
    assert "plain OpenCV" in capsys.readouterr().out
    text = (out / "real.md").read_text()
    assert "ar-anchor bench real" in text and "Blind spot" in text and "flip" in text
    results = json.loads((out / "real.json").read_text())
    rows = {row["key"]: row for row in results["rows"]}
    assert set(rows) == {"output", "output_tracked", "output_ambiguous", "output_predicted", "raw", "plain_opencv"}

    # the plain baseline is rigid_sheet.py --plain, figure for figure
    folder = realdata / "aruco_testdata" / "chessboard"
    csv_path = tmp_path / "plain.csv"
    video, camera = str(folder / "chessboard.avi"), str(folder / "intrinsics.yml")
    rigid_sheet.plain(video, camera, "DICT_ARUCO_ORIGINAL", 0.034, csv_path)
    reference = rigid_sheet.score(rigid_sheet.read(str(csv_path)))
    plain = rows["plain_opencv"]
    assert plain["pair_frames"] == reference["pair_frames"]
    assert plain["marker_frames"] == reference["marker_frames"] == 2015
    for key in ("flip_pct", "rel_rot_rms_deg", "rel_trans_rms_mm"):
        assert plain[key] == pytest.approx(reference[key], rel=1e-9)
    assert plain["flip_pct"] == pytest.approx(5.5, abs=0.05)
    assert plain["rel_rot_rms_deg"] == pytest.approx(3.73, abs=0.01)
    assert plain["rel_trans_rms_mm"] == pytest.approx(13.2, abs=0.05)
    assert plain["vs_layout"]["pair_frames"] > 0
    assert 0.9 < plain["vs_layout"]["distance_ratio"] < 1.1 and plain["vs_layout"]["mean_offset_rms_deg"] < 10

    # the tracker: sanity only (the filter is being reworked)
    assert results["speed"]["frames"] == 149 and results["speed"]["tracker_fps"] > 0
    for key in ("output", "raw"):
        assert rows[key]["pair_frames"] > 1000 and 0 <= rows[key]["flip_pct"] <= 100
        assert rows[key]["marker_frames"] > 1000 and "vs_layout" in rows[key]
    detection = results["detection"]
    assert detection["plain_marker_frames"] == 2015
    assert detection["ours_marker_frames"] == rows["raw"]["marker_frames"]
    assert detection["plain_not_ours"] >= 0 and len(detection["worst_frames"]) <= 8
