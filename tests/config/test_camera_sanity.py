"""Camera, config and layout files that are not what they claim: intrinsics no camera has (refused or
warned), files that are not small regular text files (refused before they are read, one clean line),
overlays on targets that never show up (warned), overlay sizes out of range (refused)."""

from __future__ import annotations

import logging
import os
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.camera.files import MAX_FILE_BYTES
from ar_anchor.config import TrackerConfig, load_config, parse_config
from ar_anchor.errors import CameraError, ConfigError
from ar_anchor.render.overlay import OverlayRenderer, unmatched_target_problem
from tests.helpers import distorted_camera


def write_camera(path: Path, k: list[float], dist: list[float] | None = None, size=(1280, 720)) -> Path:
    """A camera YAML with ``k`` (9 values) and ``dist``, written as text (any value, checked or not)."""
    dist = dist or [0.0] * 5
    path.write_text(
        "%YAML:1.0\n---\n"
        f"image_width: {size[0]}\nimage_height: {size[1]}\n"
        f"camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [{', '.join(map(repr, k))}]\n"
        "distortion_coefficients: !!opencv-matrix\n"
        f"   rows: 1\n   cols: {len(dist)}\n   dt: d\n   data: [{', '.join(map(repr, dist))}]\n"
    )
    return path


def k_of(fx=1000.0, fy=1000.0, cx=639.5, cy=359.5, skew=0.0) -> list[float]:
    return [fx, skew, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


# ---------------------------------------------------------------------------- intrinsics


@pytest.mark.parametrize(
    ("k", "dist", "message"),
    [
        (k_of(cx=-50000.0), None, r"principal point \(cx, cy\) = \(-50000, 359.5\) lies far outside the 1280x720"),
        (k_of(cy=2000.0), None, "lies far outside"),
        (k_of(skew=1e9), None, r"skew K\[0\]\[1\] = 1e\+09"),
        (k_of(fx=1e300, fy=1e300), None, "fx = 1e\\+300 px is no focal length for a 1280x720 image"),
        (k_of(fy=1e-3), None, "fy = 0.001 px is no focal length"),
        (k_of(), [-1e6, 0.0, 0.0, 0.0, 0.0], "distortion_coefficients fold the image"),
        (k_of(), [0.0, 0.0, 5.0, 0.0, 0.0], "distortion_coefficients fold the image"),  # tangential
        (k_of(), [2.0, -30.0, 0.0, 0.0, 0.0], "distortion_coefficients fold the image"),  # turns in the image
    ],
)
def test_intrinsics_no_camera_has_are_refused(tmp_path, k, dist, message):
    path = write_camera(tmp_path / "camera.yml", k, dist)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on the way (1e300, -1e6)
        with pytest.raises(CameraError, match=f"camera file {path}: .*{message}"):
            CameraModel.from_yaml(path)


@pytest.mark.parametrize(
    ("k", "message"),
    [
        (k_of(cx=-100.0), r"principal point \(cx, cy\) = \(-100, 359.5\) lies outside the 1280x720 image"),
        (k_of(cx=1500.0), "lies outside the 1280x720 image"),
        (k_of(skew=0.5), r"skew K\[0\]\[1\] = 0.5 is ignored"),
    ],
)
def test_odd_intrinsics_are_used_with_a_warning(tmp_path, caplog, k, message):
    path = write_camera(tmp_path / "camera.yml", k)
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        CameraModel.from_yaml(path)
    assert len(caplog.records) == 1 and caplog.records[0].levelno == logging.WARNING
    assert re.search(message, caplog.records[0].getMessage())


def test_plausible_cameras_pass_without_a_word(tmp_path, caplog, realdata_or_none):
    files = [Path("configs/camera_synthetic.yml")]
    camera = distorted_camera()  # a real lens's barrel distortion (k1 -0.32)
    camera.to_yaml(tmp_path / "distorted.yml")
    files.append(tmp_path / "distorted.yml")
    strong = write_camera(
        tmp_path / "chessboard_like.yml", k_of(653, 651, 347.6, 199.3), [-0.44, 0.28, 0, 0, -0.13], (640, 480)
    )
    files.append(strong)
    if realdata_or_none is not None:
        files += sorted(realdata_or_none.glob("**/intrinsics.yml"))
    with caplog.at_level(logging.WARNING, logger="ar_anchor"), warnings.catch_warnings():
        warnings.simplefilter("error")
        for path in files:
            CameraModel.from_yaml(path)
    assert not caplog.records


@pytest.fixture
def realdata_or_none() -> Path | None:
    root = Path(
        os.environ.get("AR_ANCHOR_REALDATA", Path(__file__).resolve().parents[2].parent / "shared" / "realdata")
    )
    return root if root.is_dir() else None


# ---------------------------------------------------------------------------- files that are not camera files


def test_a_huge_camera_file_is_refused_without_being_read(tmp_path, monkeypatch):
    path = tmp_path / "camera.yml"
    with open(path, "wb") as handle:
        handle.truncate(2 * 2**30)  # sparse: 2 GiB that take no disk
    monkeypatch.setattr(Path, "read_bytes", lambda self: pytest.fail(f"{self} was read"))
    start = time.perf_counter()
    with pytest.raises(CameraError, match=r"is 2048 MiB, too large to be one \(at most 16 MiB\); not read"):
        CameraModel.from_yaml(path)
    assert time.perf_counter() - start < 1.0


def test_binary_and_xml_bomb_camera_files_get_one_clean_line(tmp_path):
    binary = tmp_path / "binary.yml"
    binary.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8)) + b"\0")
    with pytest.raises(CameraError, match="binary data, not a camera file") as info:
        CameraModel.from_yaml(binary)
    bomb = tmp_path / "bomb.xml"
    bomb.write_text(
        '<?xml version="1.0"?>\n<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;">]>\n'
        "<opencv_storage><image_width>&lol2;</image_width></opencv_storage>\n"
    )
    with pytest.raises(CameraError, match="DOCTYPE or entity declarations") as info:
        CameraModel.from_yaml(bomb)
    garbage = tmp_path / "garbage.yml"
    garbage.write_bytes(b"%YAML:1.0\n---\ncamera_matrix: [1, 2\n\xff\xfe{{{\n")
    with pytest.raises(CameraError) as info:
        CameraModel.from_yaml(garbage)
    message = str(info.value)
    assert "exception set" not in message and "OpenCV(" not in message and "\n" not in message, message


def test_a_fifo_or_a_directory_is_named_as_such(tmp_path):
    fifo = tmp_path / "camera.yml"
    os.mkfifo(fifo)
    with pytest.raises(CameraError, match="is a FIFO"):
        CameraModel.from_yaml(fifo)  # and does not wait for a writer
    with pytest.raises(CameraError, match="is a directory, not a file"):
        CameraModel.from_yaml(tmp_path)
    with pytest.raises(ConfigError, match="config file .*: is a FIFO"):
        load_config(fifo)
    with pytest.raises(ConfigError, match="config file .*: is a directory"):
        load_config(tmp_path)


def test_huge_config_and_layout_files_are_refused_unread(tmp_path):
    big = tmp_path / "big.toml"
    with open(big, "wb") as handle:
        handle.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(ConfigError, match="config file .*big.toml: is 16 MiB, too large"):
        load_config(big)
    config = tmp_path / "board.toml"
    config.write_text('[[boards]]\nname = "cube"\nkind = "custom"\nlayout = "big.toml"\n')
    with pytest.raises(ConfigError, match="layout: layout file .*big.toml: is 16 MiB, too large"):
        load_config(config)


# ---------------------------------------------------------------------------- overlays


def test_overlay_targets_that_match_nothing_are_warned(caplog):
    config = parse_config(
        {
            "markers": {"ids": [1, 2]},
            "boards": [{"name": "desk", "first_id": 10}],
            "overlays": [
                {"target": "board:dsek"},
                {"target": "marker:77"},
                {"target": "marker:5"},
                {"target": "marker:11"},  # a board's marker: reported, drawn
                {"target": "marker:1"},
                {"target": "board:desk"},
                {"target": "marker:*"},
            ],
        },
        "x.toml",
    )
    with caplog.at_level(logging.WARNING, logger="ar_anchor"):
        OverlayRenderer(config)
    assert [r.getMessage() for r in caplog.records] == [
        "[[overlays]] target 'board:dsek' is never drawn: no such board (boards: desk; did you mean board:desk?)",
        "[[overlays]] target 'marker:77' is never drawn: DICT_4X4_50 has ids 0 to 49",
        "[[overlays]] target 'marker:5' is never drawn: only markers 1, 2 are tracked ([markers] ids)",
    ]
    assert "no [[boards]] are configured" in unmatched_target_problem(TrackerConfig(), "board:desk")


def test_marker_007_is_refused_with_the_spelling_to_use():
    with pytest.raises(ConfigError, match="write marker:7, not marker:007"):
        parse_config({"overlays": [{"target": "marker:007"}]}, "x.toml")


@pytest.mark.parametrize(("name", "value"), [("size_m", 1e300), ("size_m", 101.0), ("scale", 1e300), ("scale", 0.0)])
def test_overlay_sizes_out_of_range_are_refused_where_they_enter(name, value):
    overlay = {"target": "marker:*", "kind": "mesh", "path": "builtin:pin", name: value}
    with pytest.raises(ConfigError, match=f"\\[\\[overlays\\]\\] #1 {name}: must be in"):
        parse_config({"overlays": [overlay]}, "x.toml")
