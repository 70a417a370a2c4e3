"""``ar-anchor map`` on bad input: one line naming the file or option, exit code 2, no traceback, nothing
written; the hints for a wrong dictionary and a marker length in millimetres."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.cli.main import main

from .scenes import WEBCAM


@pytest.fixture
def camera_file(tmp_path):
    path = tmp_path / "camera.yml"
    WEBCAM.to_yaml(path)
    return path


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["-q", "map", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_missing_video(tmp_path, capsys, camera_file):
    code, _, err = run(
        capsys, str(tmp_path / "nope.mp4"), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    assert code == 2
    assert "nope.mp4: not found" in err and "Traceback" not in err
    assert not (tmp_path / "layout.yml").exists()


def test_marker_length_in_millimetres(tmp_path, capsys, camera_file):
    folder = tmp_path / "frames"
    folder.mkdir()
    code, _, err = run(
        capsys, str(folder), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "34", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    assert code == 2
    assert "--marker-length 34" in err and "millimetres" in err and "--marker-length 0.034" in err


def test_unknown_dictionary(tmp_path, capsys, camera_file):
    code, _, err = run(
        capsys, str(tmp_path), "--camera", str(camera_file), "--dictionary", "DICT_5X5_NOPE",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    assert code == 2 and "--dictionary" in err and "DICT_5X5_NOPE" in err


def test_no_marker_of_the_dictionary_hints_at_the_dictionary(tmp_path, capsys, camera_file):
    # given frames showing DICT_6X6_250 markers, searched for DICT_4X4_50 ones
    folder = tmp_path / "frames"
    folder.mkdir()
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    for index in range(3):
        image = np.full((480, 640), 255, np.uint8)
        for k, x in enumerate((120, 380)):
            image[150 : 150 + 160, x : x + 160] = cv2.aruco.generateImageMarker(dictionary, k + 10 * index, 160)
        cv2.imwrite(str(folder / f"{index:03d}.png"), image)
    code, _, err = run(
        capsys, str(folder), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    # then one line says none was found and suggests the dictionary
    assert code == 2
    assert "no marker of DICT_4X4_50 found in the 3 frame(s)" in err and "wrong --dictionary?" in err
    assert not any(tmp_path.glob("layout*"))


def test_one_marker_at_a_time_is_not_a_map(tmp_path, capsys, camera_file):
    folder = tmp_path / "frames"
    folder.mkdir()
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for index in range(2):
        image = np.full((480, 640), 255, np.uint8)
        image[150:310, 240:400] = cv2.aruco.generateImageMarker(dictionary, index, 160)
        cv2.imwrite(str(folder / f"{index:03d}.png"), image)
    code, _, err = run(
        capsys, str(folder), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    assert code == 2 and "fewer than two markers were ever seen together" in err and "ids seen: 0, 1" in err


def test_out_that_is_no_layout_file(tmp_path, capsys, camera_file):
    code, _, err = run(
        capsys, str(tmp_path), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.rrd"),
    )  # fmt: skip
    assert code == 2 and "--out" in err and ".yml" in err


def test_missing_camera_file(tmp_path, capsys):
    code, _, err = run(
        capsys, str(tmp_path), "--camera", str(tmp_path / "camera.yml"), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "layout.yml"),
    )  # fmt: skip
    assert code == 2 and "camera.yml" in err


def _sheet_images(folder, count: int, shift: int = 0) -> None:
    """``count`` frontal views of three DICT_4X4_50 markers (ids 0, 1, 2), each moved a little."""
    folder.mkdir()
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for index in range(count):
        image = np.full((480, 640), 255, np.uint8)
        dy, dx = 150 + 9 * index + shift, 6 * index + shift
        for k, x in enumerate((100, 250, 400)):
            image[dy : dy + 120, x + dx : x + dx + 120] = cv2.aruco.generateImageMarker(dictionary, k, 120)
        cv2.imwrite(str(folder / f"{index:03d}.png"), image)


def test_two_inputs_with_step_and_max_frames(tmp_path, capsys):
    # given two image folders of a sheet of three markers, filmed by an ideal 640x480 camera
    camera_file = tmp_path / "camera.yml"
    CameraModel.from_fov(640, 480, 600.0).to_yaml(camera_file)
    _sheet_images(tmp_path / "a", 6)
    _sheet_images(tmp_path / "b", 6, shift=20)
    # when mapped searching one frame in two, 5 frames at most, the TOML as --out, marker 1 the origin
    out = tmp_path / "map" / "sheet.toml"
    code, stdout, err = run(
        capsys, str(tmp_path / "a"), str(tmp_path / "b"), "--camera", str(camera_file), "--dictionary",
        "DICT_4X4_50", "--marker-length", "0.05", "--out", str(out), "--step", "2", "--max-frames", "5",
        "--origin", "1",
    )  # fmt: skip
    # then the map is written in both formats with its report and recording
    assert code == 0, err
    for name in ("sheet.toml", "sheet.yml", "sheet_report.md", "sheet.rrd"):
        assert (out.parent / name).is_file(), name
    assert "map: 3 markers from 5 frames" in stdout
    last = stdout.strip().splitlines()[-1]  # the last line names every file written
    assert last.startswith("outputs: ") and all(
        str(out.parent / name) in last for name in ("sheet.toml", "sheet.yml", "sheet_report.md", "sheet.rrd")
    ), last
    report = (out.parent / "sheet_report.md").read_text()
    assert "5 searched (one in 2)" in report and "map frame: marker 1's" in report
    assert 'kind = "custom"' in report and 'layout = "sheet.toml"' in report
    layout = dict(read_layout(out))
    assert sorted(layout) == [0, 1, 2]
    # frontal views of markers 150 px apart in the image at 600 px focal length, 120 px wide = 5 cm
    centres = {i: np.mean(layout[i], axis=0) for i in layout}
    assert centres[1] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
    assert centres[2][0] - centres[1][0] == pytest.approx(0.0625, abs=2e-4)


def test_a_file_beside_out_that_map_did_not_write_is_never_overwritten(tmp_path, capsys):
    # given the user's own tracker config where the map's TOML would go (beside --out layout.yml)
    camera_file = tmp_path / "camera.yml"
    CameraModel.from_fov(640, 480, 600.0).to_yaml(camera_file)
    _sheet_images(tmp_path / "a", 4)
    mine = tmp_path / "map.toml"
    mine.write_text("[detector]\ndictionary = 'DICT_4X4_50'\n")
    args = ["--camera", str(camera_file), "--dictionary", "DICT_4X4_50", "--marker-length", "0.05"]
    code, _, err = run(capsys, str(tmp_path / "a"), *args, "--out", str(tmp_path / "map.yml"))
    # then one line says so, nothing is written and the user's file is as it was
    assert code == 2 and "would overwrite" in err and "map.toml" in err
    assert mine.read_text() == "[detector]\ndictionary = 'DICT_4X4_50'\n"
    assert not (tmp_path / "map.yml").exists() and not (tmp_path / "map_report.md").exists()
    # a map written before is replaced by a new run, and --rrd may not be one of the layouts
    mine.unlink()
    assert run(capsys, str(tmp_path / "a"), *args, "--out", str(tmp_path / "map.yml"))[0] == 0
    assert run(capsys, str(tmp_path / "a"), *args, "--out", str(tmp_path / "map.yml"))[0] == 0
    code, _, err = run(capsys, str(tmp_path / "a"), *args, "--out", str(tmp_path / "map.yml"),
                       "--rrd", str(tmp_path / "map.toml"))  # fmt: skip
    assert code == 2 and "--rrd" in err


def test_a_failed_run_leaves_no_folder_behind(tmp_path, capsys, camera_file):
    folder = tmp_path / "frames"
    folder.mkdir()
    out = tmp_path / "new" / "deeper" / "layout.yml"
    code, _, err = run(
        capsys, str(folder), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(out),
    )  # fmt: skip
    assert code == 2 and not (tmp_path / "new").exists()
    # and an --out inside a file is bad input (exit 2), not a write failure
    (tmp_path / "afile").write_text("x")
    code, _, err = run(
        capsys, str(folder), "--camera", str(camera_file), "--dictionary", "DICT_4X4_50",
        "--marker-length", "0.05", "--out", str(tmp_path / "afile" / "layout.yml"),
    )  # fmt: skip
    assert code == 2 and "is a file" in err
