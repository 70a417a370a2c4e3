"""Dictionary names in any common spelling (``tag36h11``, ``36h11``, ``4x4_50``, ``original``, any case) map to
OpenCV's constants in one place, are stored in OpenCV's canonical spelling, and an unknown one suggests the
closest; ``--dictionary tag36h11`` tracks an AprilTag end to end."""

from __future__ import annotations

import csv
import subprocess
from pathlib import Path

import cv2
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.cli.main import build_parser
from ar_anchor.cli.options import load_tracker_config
from ar_anchor.config import ConfigValueError, canonical_dictionary, dictionary_id, parse_config
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, assert_no_traceback, cli, describe, run_main


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("DICT_4X4_50", "DICT_4X4_50"),
        ("dict_4x4_50", "DICT_4X4_50"),
        ("4x4_50", "DICT_4X4_50"),
        ("4X4_50", "DICT_4X4_50"),
        ("6x6_250", "DICT_6X6_250"),
        ("tag36h11", "DICT_APRILTAG_36H11"),
        ("36h11", "DICT_APRILTAG_36H11"),
        ("apriltag_36h11", "DICT_APRILTAG_36H11"),
        ("DICT_APRILTAG_36h11", "DICT_APRILTAG_36H11"),
        ("tag25h9", "DICT_APRILTAG_25H9"),
        ("tag16h5", "DICT_APRILTAG_16H5"),
        ("tag36h10", "DICT_APRILTAG_36H10"),
        ("Tag36H10", "DICT_APRILTAG_36H10"),
        ("aruco_original", "DICT_ARUCO_ORIGINAL"),
        ("original", "DICT_ARUCO_ORIGINAL"),
        ("mip_36h12", "DICT_ARUCO_MIP_36H12"),
        (" tag36h11 ", "DICT_APRILTAG_36H11"),
    ],
)
def test_every_spelling_maps_to_the_opencv_constant(name: str, canonical: str) -> None:
    assert canonical_dictionary(name) == canonical
    assert dictionary_id(name) == int(getattr(cv2.aruco, canonical))


@pytest.mark.parametrize(
    ("name", "closest"),
    [("tag36h12", "tag36h11"), ("4x4_51", "4x4_50"), ("DICT_5X5_51", "5x5_50"), ("orignal", "original")],
)
def test_an_unknown_name_lists_the_forms_and_suggests_the_closest(name: str, closest: str) -> None:
    with pytest.raises(ConfigValueError) as info:
        canonical_dictionary(name)
    message = str(info.value)
    assert message.startswith(f"unknown dictionary {name!r} (known: DICT_4X4_50 or 4x4_50")
    assert "tag36h11" in message and message.endswith(f"did you mean {closest}?")
    assert "\n" not in message and info.value.key == "dictionary"


def test_nothing_close_gets_no_suggestion() -> None:
    with pytest.raises(ConfigValueError) as info:
        canonical_dictionary("qqqqqqqq")
    assert "did you mean" not in str(info.value)


def test_the_config_stores_the_canonical_name() -> None:
    config = parse_config(
        {
            "detector": {"dictionary": "tag36h11"},
            "boards": [
                {
                    "name": "b",
                    "kind": "charuco",
                    "squares_x": 5,
                    "squares_y": 7,
                    "square_length_m": 0.04,
                    "marker_length_m": 0.02,
                    "dictionary": "36h11",  # the board's own copy, spelt otherwise: the same dictionary
                }
            ],
        },
        "x.toml",
    )
    assert config.detector.dictionary == "DICT_APRILTAG_36H11"
    assert config.boards[0].dictionary == "DICT_APRILTAG_36H11"
    assert config.with_overrides(dictionary="4x4_1000").detector.dictionary == "DICT_4X4_1000"
    with pytest.raises(ConfigValueError, match=r"must be the detector's dictionary \(DICT_APRILTAG_36H11\)"):
        parse_config(
            {
                "detector": {"dictionary": "tag36h11"},
                "boards": [
                    {
                        "name": "b",
                        "kind": "charuco",
                        "square_length_m": 0.04,
                        "marker_length_m": 0.02,
                        "dictionary": "tag25h9",
                    }
                ],
            },
            "x.toml",
        )


def test_the_command_line_override_is_canonical() -> None:
    args = build_parser().parse_args(["replay", "x", "--dictionary", "tag36h11"])
    assert load_tracker_config(args).detector.dictionary == "DICT_APRILTAG_36H11"


@pytest.fixture(scope="module")
def apriltag_photo(tmp_path_factory) -> Path:
    """A photo of tag36h11 id 5 (8 cm) at 0.6 m, turned 20 degrees, and its camera file."""
    root = tmp_path_factory.mktemp("apriltag")
    camera = CameraModel.from_fov(640, 480, 600.0)
    scene = SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(5, 0.08, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=0.6, azimuth_deg=20.0, elevation_deg=0.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        blur_sigma=0.5,
        seed=0,
        dictionary="DICT_APRILTAG_36H11",
    )
    (frame,) = SyntheticSource(scene)
    (root / "shots").mkdir()
    assert cv2.imwrite(str(root / "shots" / "tag.png"), frame.image)
    camera.to_yaml(root / "cam.yml")
    return root


def test_tag36h11_tracks_an_apriltag_photo(apriltag_photo: Path) -> None:
    # given a photo of an AprilTag 36h11 marker
    rows = {}
    for name in ("tag36h11", "36h11", "DICT_APRILTAG_36H11"):
        out = apriltag_photo / name
        # when it is replayed with the family's name
        result = run_main(
            [
                "-q",
                "replay",
                str(apriltag_photo / "shots"),
                "--camera",
                str(apriltag_photo / "cam.yml"),
                "--dictionary",
                name,
                "--marker-length",
                "8cm",
                "--out",
                str(out),
            ]
        )
        assert_clean_exit(result, {0})
        with open(out / "poses.csv", newline="") as file:
            (row,) = list(csv.DictReader(file))
        rows[name] = row
    # then the marker is found with its id at its distance, the same whatever the spelling
    row = rows["tag36h11"]
    assert row["target"] == "marker:5"
    distance = sum(float(row[f"tvec_{axis}"]) ** 2 for axis in "xyz") ** 0.5
    assert distance == pytest.approx(0.6, rel=0.02)
    assert rows["36h11"] == rows["DICT_APRILTAG_36H11"] == row


def test_the_default_dictionary_does_not_see_it(apriltag_photo: Path) -> None:
    # the control: with DICT_4X4_50 the same photo holds no marker (the name above did the work)
    out = apriltag_photo / "default"
    result = run_main(
        [
            "-q",
            "replay",
            str(apriltag_photo / "shots"),
            "--camera",
            str(apriltag_photo / "cam.yml"),
            "--marker-length",
            "8cm",
            "--out",
            str(out),
        ]
    )
    assert_clean_exit(result, {0})
    with open(out / "poses.csv", newline="") as file:
        assert not list(csv.DictReader(file))


def test_an_unknown_dictionary_on_the_command_line_is_one_line_exit_2(tmp_path: Path) -> None:
    result = subprocess.run(
        cli(["replay", "missing.mp4", "--dictionary", "tag36h12"]),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2, describe(result)
    assert_no_traceback(result)
    errors = [line for line in result.stderr.splitlines() if ": error:" in line]
    assert len(errors) == 1, describe(result)
    assert "--dictionary" in errors[0] and "did you mean tag36h11?" in errors[0], errors[0]


def test_map_names_the_dictionary_canonically(tmp_path: Path) -> None:
    from ar_anchor.tools.map.command import _check_options

    argv = ["map", str(tmp_path), "--camera", "c.yml", "--dictionary", "tag36h11", "--marker-length", "5cm"]
    args = build_parser().parse_args([*argv, "--out", "m.yml"])
    _check_options(args)  # what its outputs and the config snippet it prints name
    assert args.dictionary == "DICT_APRILTAG_36H11" and args.marker_length == pytest.approx(0.05)
