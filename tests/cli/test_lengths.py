"""One way to give a length on every command: ``50mm``, ``5cm``, ``0.05m``, or a bare number in the option's
own unit; the marker side is ``--marker-length`` everywhere (the old names are aliases); a length that is not
one is a one-line usage error naming the option, exit 2."""

from __future__ import annotations

import csv
import subprocess
from pathlib import Path

import cv2
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.cli.main import build_parser
from ar_anchor.geometry import Pose
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from tests.helpers import assert_clean_exit, assert_no_traceback, cli, describe, run_main

# (command line, the namespace's attribute, its value): every length option, with a unit and bare
PARSED = [
    (["replay", "x", "--marker-length", "6cm"], "marker_length", 0.06),
    (["replay", "x", "--marker-length", "0.06"], "marker_length", 0.06),
    (["live", "--marker-length", "60mm"], "marker_length", 0.06),
    (["demo", "--marker-length", "0.04m"], "marker_length", 0.04),
    (["demo", "--near", "35cm", "--far", "2m"], "near", 0.35),
    (["demo", "--near", "35cm", "--far", "2m"], "far", 2.0),
    (["demo", "--far", "3"], "far", 3.0),
    (["batch", "x", "--marker-length", "5cm"], "marker_length", 0.05),
    (["bench", "real", "--marker-length", "4cm"], "marker_length", 0.04),
    (
        ["map", "x", "--camera", "c.yml", "--dictionary", "4x4_50", "--marker-length", "5cm", "--out", "m.yml"],
        "marker_length",
        0.05,
    ),
    (["markers", "--marker-length", "5cm"], "size_mm", 50.0),
    (["markers", "--marker-length", "0.05"], "size_mm", 50.0),  # a bare --marker-length is metres, here too
    (["markers", "--size-mm", "50"], "size_mm", 50.0),  # the old name keeps millimetres
    (["markers", "--size-mm", "5cm"], "size_mm", 50.0),
    (["markers", "--gap-mm", "1cm"], "gap_mm", 10.0),
    (["markers", "--square-length", "30mm"], "square_mm", 30.0),
    (["markers", "--square-mm", "3cm"], "square_mm", 30.0),
    (["calibrate", "x", "--out", "c.yml", "--square-length", "30mm"], "square_m", 0.03),
    (["calibrate", "x", "--out", "c.yml", "--square-m", "0.03"], "square_m", 0.03),
    (["calibrate", "x", "--out", "c.yml", "--marker-length", "22mm"], "marker_m", 0.022),
    (["calibrate", "x", "--out", "c.yml", "--marker-m", "2.2cm"], "marker_m", 0.022),
    (["study", "jitter", "--marker-m", "5cm"], "marker_m", 0.05),
    (["study", "jitter", "--marker-length", "0.08"], "marker_m", 0.08),
]


@pytest.mark.parametrize(("argv", "dest", "expected"), PARSED, ids=[" ".join(a[:4]) for a, _, _ in PARSED])
def test_every_length_option_reads_a_unit_and_a_bare_number_keeps_its_unit(argv, dest, expected) -> None:
    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == pytest.approx(expected, rel=1e-12)


def test_jitter_distances_read_units_too() -> None:
    from ar_anchor.tools.study.options import FULL, jitter_setup
    from tests.helpers import study_args

    setup = jitter_setup(study_args(["jitter", "--distances", "30cm,1m,1.5"]), FULL, None)
    assert setup.distances_m == pytest.approx((0.3, 1.0, 1.5))


def _run(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli(argv), cwd=cwd, capture_output=True, text=True, timeout=60, check=False)


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["replay", "missing.mp4", "--marker-length", "5 inches"], "--marker-length"),
        (["markers", "--ids", "0", "--size-mm", "abc"], "--size-mm"),
        (["calibrate", "x", "--out", "c.yml", "--square-length", "3furlongs"], "--square-length"),
        (["demo", "--near", "1cm"], "--near"),
    ],
)
def test_a_length_that_is_not_one_is_a_one_line_error_naming_the_option(argv, option, tmp_path) -> None:
    result = _run(argv, tmp_path)
    assert result.returncode == 2, describe(result)
    assert_no_traceback(result)
    errors = [line for line in result.stderr.splitlines() if ": error:" in line]
    assert len(errors) == 1 and f"argument {option}" in errors[0], describe(result)
    assert "50mm, 5cm or 0.05m" in errors[0] or "must be a length >= 0.02 m" in errors[0], errors[0]
    assert not list(tmp_path.iterdir()), "a refused command wrote something"


def test_two_names_of_one_length_are_refused(tmp_path) -> None:
    result = _run(["markers", "--ids", "0", "--size-mm", "50", "--marker-length", "5cm"], tmp_path)
    assert result.returncode == 2, describe(result)
    assert "argument --marker-length: the same length as --size-mm: give one of them" in result.stderr


def test_markers_prints_the_same_sheet_for_every_spelling_of_a_length(tmp_path) -> None:
    tomls = []
    for index, argv in enumerate(
        (
            ["--marker-length", "5cm", "--gap-mm", "1cm"],
            ["--size-mm", "50", "--gap-mm", "10"],
            ["--marker-length", "0.05", "--gap-mm", "0.01m"],
        )
    ):
        out = tmp_path / f"sheet{index}"
        result = run_main(["-q", "markers", "--board", "grid", "--cols", "2", "--rows", "2", *argv, "--out", str(out)])
        assert_clean_exit(result, {0})
        (toml,) = out.glob("*.toml")
        tomls.append((toml.name, toml.read_text()))
    assert tomls[0] == tomls[1] == tomls[2]
    assert "marker_length_m = 0.05\n" in tomls[0][1] and "separation_m = 0.01\n" in tomls[0][1]


def test_markers_bare_marker_length_in_millimetres_gets_the_hint(tmp_path) -> None:
    # a bare --marker-length is metres everywhere: 50 is a 50 m marker, most likely 50 mm
    result = run_main(["markers", "--ids", "0", "--marker-length", "50", "--out", str(tmp_path / "m")])
    assert result.code == 2, result.describe()
    assert (
        "--marker-length 50: a marker 50 m wide? did you give millimetres? 50 mm is --marker-length 0.05 (or 50mm)"
        in (result.stderr)
    )
    # and metres given to the millimetre option: the other way round
    result = run_main(["markers", "--ids", "0", "--size-mm", "0.05", "--out", str(tmp_path / "m")])
    assert result.code == 2 and "did you give metres? 0.05 m is --size-mm 50 (or 0.05m)" in result.stderr
    # the sheet's own messages name the flag the user typed
    result = run_main(
        [
            "markers",
            "--board",
            "charuco",
            "--cols",
            "5",
            "--rows",
            "7",
            "--square-length",
            "2cm",
            "--marker-length",
            "2cm",
        ]
    )
    assert result.code == 2 and "--marker-length: the marker (20 mm) must be smaller" in result.stderr
    assert "(--square-length 20 mm)" in result.stderr and "--size-mm" not in result.stderr


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> Path:
    """A photo of a 6 cm marker at 0.5 m, and its camera file."""
    root = tmp_path_factory.mktemp("length_photo")
    camera = CameraModel.from_fov(640, 480, 600.0)
    scene = SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(0, 0.06, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=0.5, azimuth_deg=25.0, elevation_deg=0.0, roll_deg=0.0),
        frames=1,
        noise_sigma=1.0,
        blur_sigma=0.5,
        seed=3,
    )
    (frame,) = SyntheticSource(scene)
    (root / "shots").mkdir()
    assert cv2.imwrite(str(root / "shots" / "marker.png"), frame.image)
    camera.to_yaml(root / "cam.yml")
    return root


def _distance(photo: Path, name: str, length: str) -> tuple[float, str]:
    out = photo / name
    result = run_main(
        [
            "replay",
            str(photo / "shots"),
            "--camera",
            str(photo / "cam.yml"),
            "--marker-length",
            length,
            "--out",
            str(out),
        ]
    )
    assert_clean_exit(result, {0})
    with open(out / "poses.csv", newline="") as file:
        (row,) = list(csv.DictReader(file))
    return float(row["tvec_z"]), result.stderr


def test_replay_reads_the_marker_side_in_any_unit(photo: Path) -> None:
    metres, _ = _distance(photo, "m", "0.06")
    assert metres == pytest.approx(0.5, rel=0.02)
    for name, length in (("mm", "60mm"), ("cm", "6cm"), ("m_unit", "0.06m")):
        assert _distance(photo, name, length)[0] == pytest.approx(metres, rel=1e-12), length
    # a bare 60 is still metres, and still gets today's hint
    far, stderr = _distance(photo, "slip", "60")
    assert far == pytest.approx(1000 * metres, rel=1e-9)
    assert "--marker-length 60: a marker 60 m wide? did you give millimetres?" in stderr and "(or 60mm)" in stderr
