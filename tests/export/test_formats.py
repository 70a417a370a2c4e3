"""The export's pieces without a run: reading poses.csv back, the quaternion and TUM conversions, the ROS 2 schema
text, and poses_ext.csv / tum/ written from a poses.csv made here from known poses (fast tier)."""

from __future__ import annotations

import json
import logging
import math

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ar_anchor.errors import InputError
from ar_anchor.targets import TargetId
from ar_anchor.tools.export import export_run
from ar_anchor.tools.export.poses import quaternion_xyzw_from_rvec, read_poses_csv, timestamp_ns_from_text
from ar_anchor.tools.export.ros2_msgs import CAMERA_INFO, COMPRESSED_IMAGE, TF_MESSAGE
from ar_anchor.tools.export.tables import FrameNames, frame_name
from tests.helpers import fuzz_settings

from .conftest import check_poses_ext, matrix_from_quaternion_xyzw, write_run

# ------------------------------------------------------------------------------------------ conversions


def _axis_angle_quaternion(rvec: np.ndarray) -> np.ndarray:
    """q = (axis sin(angle/2), cos(angle/2)), written out for the test (the library has its own code)."""
    angle = np.linalg.norm(rvec)
    if angle == 0:
        return np.array([0.0, 0.0, 0.0, 1.0])
    axis = rvec / angle
    return np.array([*(axis * math.sin(angle / 2)), math.cos(angle / 2)])


@pytest.mark.parametrize(
    "rvec",
    [
        np.zeros(3),
        np.array([1e-12, -2e-12, 0.0]),
        np.array([1e-7, 0.0, 3e-7]),
        np.array([0.3, -0.2, 0.1]),
        np.array([0.0, math.pi, 0.0]),
        np.array([-2.8667924919081154, -0.07397979598434935, 0.010758138993102052]),
        np.array([3.5, 1.0, -0.5]),  # longer than pi (w < 0 before the sign is fixed)
    ],
)
def test_quaternion_is_the_rotation_of_the_rvec(rvec):
    # when
    q = quaternion_xyzw_from_rvec(rvec)
    # then: unit, scalar last with w >= 0, and the same rotation as OpenCV's Rodrigues
    assert abs(np.linalg.norm(q) - 1.0) < 1e-15
    assert q[3] >= 0.0
    rotation, _ = cv2.Rodrigues(rvec)
    np.testing.assert_allclose(matrix_from_quaternion_xyzw(q), rotation, atol=1e-12)
    expected = _axis_angle_quaternion(rvec)
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-12


def test_random_quaternions_match_rodrigues():
    rng = np.random.default_rng(0)
    for rvec in rng.uniform(-3.0, 3.0, size=(200, 3)):
        rotation, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(matrix_from_quaternion_xyzw(quaternion_xyzw_from_rvec(rvec)), rotation, atol=1e-12)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0.000000000", 0),
        ("0.033333333", 33_333_333),
        ("1733146085.123456789", 1_733_146_085_123_456_789),
        ("2", 2e9),
        ("1.5e-8", 15),
        ("2147483647.999999999", 2_147_483_647_999_999_999),  # the last ROS 2 time
        ("1.000000000000000000000000000000000", 1e9),  # zeros below the nanosecond
        ("0e999999", 0),
    ],
)
def test_timestamps_are_read_to_the_nanosecond(text, expected):
    assert timestamp_ns_from_text(text) == int(expected)


@pytest.mark.parametrize(
    "text",
    [
        "",
        "nan",
        "inf",
        "abc",
        "0.0000000001",
        "1.0000000000000000000000000000001",  # (was rounded to 1 s by the decimal context)
        "1e-999999999",  # (was 0)
        "1e999999999",  # (was decimal.Overflow: an internal error)
        "2147483648",
        "-1e-9",
        "1" * 60000,
    ],
)
def test_timestamps_that_are_not_nanoseconds_are_refused(text):
    with pytest.raises(ValueError):
        timestamp_ns_from_text(text)


@pytest.mark.parametrize(
    ("target", "name"),
    [("marker:3", "marker_3"), ("board:desk", "board_desk"), ("board:my desk/2", "board_my_desk_2")],
)
def test_frame_names(target, name):
    assert frame_name(TargetId.parse(target)) == name


def test_two_targets_that_would_share_a_frame_name_are_refused():
    names = FrameNames()
    names(TargetId.parse("board:a b"))
    with pytest.raises(InputError, match="^poses.csv: line 3: targets 'board:a b' and 'board:a_b'.*board_a_b"):
        names(TargetId.parse("board:a_b"), "poses.csv: line 3")


# ------------------------------------------------------------------------------------------ ROS 2 schemas


def _fields(typestore, name: str) -> list[tuple[str, str]]:
    """(field, type text) of ``name`` in ``typestore``, nested types followed."""
    return [(field, repr(kind)) for field, kind in typestore.fielddefs[name][1]]


@pytest.mark.parametrize("definition", [TF_MESSAGE, CAMERA_INFO, COMPRESSED_IMAGE], ids=lambda d: d[0])
def test_schemas_match_the_ros2_humble_definitions_rosbags_ships(definition):
    # given our schema text, parsed by rosbags (not the parser of mcap-ros2-support that writes with it)
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    name, text = definition
    ours = get_typestore(Stores.EMPTY)
    parts = text.split("\n" + "=" * 80 + "\n")
    types = get_types_from_msg(parts[0], name)
    for part in parts[1:]:
        header, _, body = part.partition("\n")
        package, _, message = header.removeprefix("MSG: ").partition("/")
        types.update(get_types_from_msg(body, f"{package}/msg/{message}"))
    ours.register(types)
    humble = get_typestore(Stores.ROS2_HUMBLE)
    # then every type, the message and those it uses, has Humble's fields, in Humble's order
    for full_name in types:
        assert _fields(ours, full_name) == _fields(humble, full_name), full_name
    assert len(types) == {"tf2_msgs/msg/TFMessage": 7, "sensor_msgs/msg/CameraInfo": 4}.get(name, 3)


# ------------------------------------------------------------------------------------------ reading poses.csv


def test_read_back_equals_what_was_written(tmp_path):
    run = write_run(tmp_path / "run")
    rows = list(read_poses_csv(run.path / "poses.csv"))
    assert [(str(r.frame), r.timestamp_text, r.target, r.state.value) for r in rows] == [tuple(r[:4]) for r in run.rows]
    assert [r.raw is None for r in rows] == [r[10] == "" for r in run.rows]
    for row, written in zip(rows, run.rows):
        assert list(row.pose.rvec) + list(row.pose.tvec) == [float(v) for v in written[4:10]]


def _cell(line: str, column: int, text: str) -> str:
    cells = line.rstrip("\n").split(",")
    cells[column] = text
    return ",".join(cells) + "\n"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda lines: ["frame,time,target\n", *lines[1:]], r"line 1: not the header of a poses.csv"),
        (lambda lines: [], r"line 1: not the header of a poses.csv .*an empty file"),
        (lambda lines: [*lines[:2], lines[2].replace(",ambiguous,", ",lost,"), *lines[3:]], r"line 3, column state"),
        (lambda lines: [*lines[:2], _cell(lines[2], 8, "1.5e"), *lines[3:]], r"line 3, column tvec_y: expected a numb"),
        (lambda lines: [*lines[:3], lines[3][:40] + "\n"], r"line 4: expected 18 columns, got \d+ \(a row cut short"),
        (lambda lines: [lines[0], lines[4], lines[1]], r"line 3, column frame: frame 0 after frame 1"),
        (lambda lines: [*lines[:3], lines[3].replace("marker:7", "marker:x"), *lines[4:]], r"line 4, column target"),
    ],
    ids=["header", "empty", "state", "number", "cut", "order", "target"],
)
def test_a_malformed_poses_csv_is_refused_naming_file_line_and_column(tmp_path, edit, message):
    # given a poses.csv with one fault
    run = write_run(tmp_path / "run")
    path = run.path / "poses.csv"
    path.write_text("".join(edit(path.read_text().splitlines(keepends=True))))
    # then reading it says where
    with pytest.raises(InputError, match=r"poses\.csv: " + message):
        list(read_poses_csv(path))


# ------------------------------------------------------------------------------------------ the text exports


def test_poses_ext_agrees_with_poses_csv(tmp_path):
    # given a run's poses.csv with known poses
    run = write_run(tmp_path / "run")
    # when it is exported
    export_run(run.path, formats=("csv",))
    # then every row has the same frame, time, target and state, and the same pose as quaternion and as matrix
    assert check_poses_ext(run.path) == len(run.rows)


def test_the_export_of_a_run_that_did_not_complete_or_holds_no_pose_says_so(tmp_path, caplog):
    """Found by trying the tool as a new user: the export of an interrupted run with no pose said nothing."""
    run = write_run(tmp_path / "run")
    summary = json.loads((run.path / "summary.json").read_text())

    def warnings(status: str, *, empty: bool = False) -> list[str]:
        (run.path / "summary.json").write_text(json.dumps({**summary, "status": status}))
        if empty:
            lines = (run.path / "poses.csv").read_text().splitlines(keepends=True)
            (run.path / "poses.csv").write_text(lines[0])
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="ar_anchor"):
            export_run(run.path, tmp_path / f"out_{status}_{empty}", formats=("csv",))
        return [record.getMessage() for record in caplog.records if record.levelno >= logging.WARNING]

    assert warnings("completed") == []
    (interrupted,) = warnings("interrupted")
    assert "the run was interrupted (its summary.json): the exports hold the 7 pose(s) it wrote" in interrupted
    assert "the run did not finish" in warnings("running")[0] and "the run failed" in warnings("failed")[0]
    assert warnings("completed", empty=True) == [
        f"RUN_DIR {run.path}: its poses.csv holds no pose: the exports are empty"
    ]


def test_tum_files_hold_the_camera_in_each_target_frame(tmp_path):
    # given known camera_from_target poses
    run = write_run(tmp_path / "run")
    # when exported as TUM
    export_run(run.path, formats=("tum",))
    # then one file per target, one line per row of that target: C = -R^T t and the orientation R^T
    files = sorted(p.name for p in (run.path / "tum").iterdir())
    assert files == ["board_my_desk.txt", "marker_0.txt", "marker_7.txt"]
    for target, file_name in (("marker:0", "marker_0.txt"), ("marker:7", "marker_7.txt")):
        lines = [ln for ln in (run.path / "tum" / file_name).read_text().splitlines() if not ln.startswith("#")]
        expected = [row for row in run.rows if row[2] == target]
        assert len(lines) == len(expected)
        for line, row in zip(lines, expected):
            values = line.split(" ")
            assert values[0] == row[1] and len(values) == 8
            rotation, _ = cv2.Rodrigues(np.array([float(v) for v in row[4:7]]))
            centre = -rotation.T @ np.array([float(v) for v in row[7:10]])
            np.testing.assert_allclose([float(v) for v in values[1:4]], centre, atol=1e-12)
            q = np.array([float(v) for v in values[4:8]])
            np.testing.assert_allclose(matrix_from_quaternion_xyzw(q), rotation.T, atol=1e-12)


def test_a_new_export_replaces_the_old_files_and_a_failed_one_leaves_them(tmp_path):
    # given a run exported when it had a target marker:99 (now marker:7), and files of the user's in tum/
    run = write_run(tmp_path / "run")
    poses = run.path / "poses.csv"
    good = poses.read_text()
    poses.write_text(good.replace("marker:7", "marker:99"))
    export_run(run.path, formats=("csv", "tum"))
    assert (run.path / "tum" / "marker_99.txt").is_file()
    (run.path / "tum" / "notes.txt").write_text("the user's")
    (run.path / "tum" / "marker_5.txt").write_text("the user's, named like an export")
    before = (run.path / "poses_ext.csv").read_text()
    # when poses.csv is damaged and exported again
    poses.write_text(good.replace(",tracked,", ",lost,", 1))
    with pytest.raises(InputError):
        export_run(run.path, formats=("csv", "tum"))
    # then the previous export is intact and no temporary folder is left
    assert (run.path / "poses_ext.csv").read_text() == before
    assert not [p for p in run.path.iterdir() if p.name.startswith(".export")]
    # and when exported from the good file again, the old export's TUM file is gone (the user's files stay)
    poses.write_text(good)
    export_run(run.path, formats=("tum",))
    names = sorted(p.name for p in (run.path / "tum").iterdir())
    assert names == ["board_my_desk.txt", "marker_0.txt", "marker_5.txt", "marker_7.txt", "notes.txt"]


def test_the_camera_comes_from_summary_json_or_camera_yml(tmp_path):
    from ar_anchor.tools.export.run import run_camera

    run = write_run(tmp_path / "run")
    camera = run_camera(run.path)
    np.testing.assert_array_equal(camera.camera_matrix, run.camera.camera_matrix)
    summary = json.loads((run.path / "summary.json").read_text())
    del summary["camera"]
    (run.path / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(InputError, match="give --camera FILE"):
        run_camera(run.path)
    run.camera.to_yaml(run.path / "camera.yml")
    assert run_camera(run.path).size == run.camera.size


def test_a_new_run_removes_the_previous_runs_exports_and_only_them(tmp_path):
    from ar_anchor.tools.export.run import clear_previous_exports

    # given an exported run, with a file of the user's in tum/
    run = write_run(tmp_path / "run")
    export_run(run.path)
    (run.path / "tum" / "notes.txt").write_text("the user's")
    # when a new run starts in the folder
    removed = clear_previous_exports(run.path)
    # then the exports are gone, the rest stays
    tum = ["tum/board_my_desk.txt", "tum/marker_0.txt", "tum/marker_7.txt"]
    assert sorted(removed) == ["poses_ext.csv", "run.mcap", *tum]
    assert sorted(p.name for p in run.path.iterdir()) == ["poses.csv", "summary.json", "tum"]
    assert [p.name for p in (run.path / "tum").iterdir()] == ["notes.txt"]


@pytest.mark.slow  # fuzzing: the full suite
@fuzz_settings(150)
@given(data=st.data())
def test_a_damaged_poses_csv_is_exported_or_refused_never_a_crash(tmp_path_factory, data):
    # given a run whose poses.csv is damaged: characters replaced, inserted, removed, lines cut or repeated
    run = write_run(tmp_path_factory.mktemp("fuzz") / "run")
    path = run.path / "poses.csv"
    text = path.read_text()
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(text)))
        kind = data.draw(st.sampled_from(["replace", "insert", "delete", "cut", "repeat"]))
        junk = data.draw(st.text(alphabet=st.sampled_from(list(',.-e\n"0123456789 :xnaif\x00é')), max_size=6))
        if kind == "replace":
            text = text[:at] + junk + text[at + len(junk) :]
        elif kind == "insert":
            text = text[:at] + junk + text[at:]
        elif kind == "delete":
            text = text[:at] + text[at + data.draw(st.integers(1, 20)) :]
        elif kind == "cut":
            text = text[:at]
        else:
            line_start = text.rfind("\n", 0, at) + 1
            line_end = text.find("\n", at)
            text = text[:line_end] + text[line_start - 1 : line_end] + text[line_end:] if line_end > 0 else text
    path.write_text(text)
    # when it is exported: it is, or it is refused with an InputError naming poses.csv
    try:
        result = export_run(run.path)
    except InputError as err:
        assert "poses.csv" in str(err) and "\n" not in str(err)
        assert sorted(p.name for p in run.path.iterdir()) == ["poses.csv", "summary.json"]
    else:
        assert result.rows == sum(1 for _ in read_poses_csv(path))
