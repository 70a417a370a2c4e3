"""Hypothesis-generated command lines for every ``ar-anchor`` subcommand, run in-process.

Each argv is a random mix of the command's options with plausible, extreme and malformed values,
junk tokens and files that are good, bad or missing, always ending in limits that keep a run to
one frame (``--max-frames 1``, ``--reconnect-s 0``), with outputs in a temporary folder. The
outcome must be an exit code of the documented set {0, 1, 2, 130} (argparse's own usage errors
are ``SystemExit(2)``), no traceback and no "internal error" (main()'s catch-all for exceptions
nobody expected) on stdout or stderr, exactly one ``ar-anchor: error:`` line for a failure, no
outputs for a run refused as bad input, and complete outputs for a run that succeeded.

``bench`` runs for minutes, so its report writers are replaced by stubs: what is fuzzed is the
parsing and validation in front of them.

Bugs the fuzzing found are pinned by the named tests at the end (extreme ``demo --near/--far/--blur/
--noise``, a malformed ``live --connect``, ``bench --out`` a file, a non-UTF-8 ``--video-out``).

Budgets: tests/helpers.py (CI: the counts below; ``HYPOTHESIS_PROFILE=long``: 20x).
"""

from __future__ import annotations

import csv
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ar_anchor.camera import CameraModel
from tests.helpers import (
    CliResult,
    assert_clean_exit,
    error_lines,
    fuzz_settings,
    outcome,
    run_main,
    working_directory,
)

pytestmark = pytest.mark.slow  # fuzzing and end-to-end CLI runs: the full suite, not the fast tier

REPO = Path(__file__).resolve().parents[2]
POSES_HEADER = (
    "frame,timestamp_s,target,state,rvec_x,rvec_y,rvec_z,tvec_x,tvec_y,tvec_z,"
    "raw_rvec_x,raw_rvec_y,raw_rvec_z,raw_tvec_x,raw_tvec_y,raw_tvec_z,reproj_px,ambiguity"
)
SURROGATE = "\udcff"  # a non-UTF-8 byte in argv, as Python decodes it (surrogateescape)

# ============================================================================ workspace


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """Inputs the command lines may name, good and bad, relative to this folder (the cwd of every run)."""
    root = tmp_path_factory.mktemp("cli")
    images = root / "imgs"
    images.mkdir()
    for i in range(3):
        cv2.imwrite(str(images / f"f{i}.png"), np.full((48, 64, 3), 60 * i, np.uint8))
    (images / "notes.txt").write_text("not an image\n")
    writer = cv2.VideoWriter(str(root / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for i in range(4):
        writer.write(np.full((48, 64, 3), 50 * i, np.uint8))
    writer.release()
    (root / f"clip{SURROGATE}.avi").write_bytes((root / "clip.avi").read_bytes())
    (root / "empty.mp4").write_bytes(b"")
    (root / "text.mp4").write_text("not a video\n" * 10)
    camera = CameraModel.from_fov(64, 48, 60.0)
    camera.to_yaml(root / "cam64.yml")
    camera.to_yaml(images / "camera.yml")  # replay finds it beside the images
    CameraModel.default_synthetic().to_yaml(root / "cam_hd.yml")  # wrong aspect for the clips
    (root / "cam_ros.yaml").write_text(
        "image_width: 64\nimage_height: 48\ncamera_name: c\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [60.0, 0.0, 31.5, 0.0, 60.0, 23.5, 0.0, 0.0, 1.0]\ndistortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.0, 0.0, 0.0, 0.0, 0.0]\n"
    )
    (root / "cam_bad.yml").write_text("%YAML:1.0\n---\nimage_width: 64\n")
    (root / "default.toml").write_text((REPO / "configs" / "default.toml").read_text())
    (root / "bad.toml").write_text("[markers]\nlength_m = -1\n")
    (root / "pin.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (root / "mesh.toml").write_text('[[overlays]]\nkind = "mesh"\npath = "pin.obj"\n')
    (root / "nomesh.toml").write_text('[[overlays]]\nkind = "mesh"\npath = "gone.obj"\n')
    (root / "a_file").write_text("a file where a folder is expected\n")
    return root


_counter = itertools.count()


@pytest.fixture(autouse=True)
def _no_display(monkeypatch):
    # --spawn must not start a viewer here: without a display the tool records to file only
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


@pytest.fixture
def stub_benchmarks(monkeypatch):
    """bench's report writers, replaced: they record their arguments and write tiny reports."""
    import ar_anchor.bench.boards as bench_boards
    import ar_anchor.bench.overlay as bench_overlay
    import ar_anchor.bench.speed as bench_speed
    import ar_anchor.bench.stability as bench

    calls = []

    def stub(name):
        def write(out, *args, **kwargs):
            calls.append((name, out, kwargs))
            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / f"{name}.md").write_text("stub\n")

        return write

    for module, name in [
        (bench, "write_stability_report"),
        (bench_boards, "write_board_report"),
        (bench_overlay, "write_overlay_report"),
        (bench_speed, "write_speed_report"),
    ]:
        monkeypatch.setattr(module, name, stub(name))
    return calls


# ============================================================================ token strategies

JUNK = st.one_of(
    st.sampled_from(["", "-", "--", "--bogus", "-x", "=", "--max-frames=", "-vv", "nan", "inf", "-1", SURROGATE]),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=6),
)


def opt(valid: st.SearchStrategy, invalid: st.SearchStrategy | None = None) -> st.SearchStrategy:
    """An option's value: valid six times in seven (so that runs get past argparse), else anything."""
    wrong = JUNK if invalid is None else st.one_of(invalid, invalid, JUNK)
    return st.one_of(valid, valid, valid, valid, valid, valid, wrong)


def ints(lo: int, hi: int) -> st.SearchStrategy:
    return opt(st.integers(lo, hi).map(str), st.sampled_from([str(lo - 1), "1e3", "2.5", "x", "99999999999999999999"]))


def floats(lo: float, hi: float) -> st.SearchStrategy:
    return opt(st.floats(lo, hi).map(repr), st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e300", "1e-300", "x"]))


FLAG = st.just(None)
PATHS = st.sampled_from(
    ["missing.yml", "a_file", "imgs", "", ".", "..", f"x{SURROGATE}", "/dev/null", "/nonexistent/x"]
)
CAMERAS = opt(st.sampled_from(["cam64.yml", "cam_ros.yaml"]), st.sampled_from(["cam_hd.yml", "cam_bad.yml"]) | PATHS)
CONFIGS = opt(st.sampled_from(["default.toml", "mesh.toml"]), st.sampled_from(["bad.toml", "nomesh.toml"]) | PATHS)
DICTIONARIES = opt(
    st.sampled_from(["DICT_4X4_50", "dict_5x5_100", "DICT_ARUCO_ORIGINAL", "DICT_4X4_1000"]),
    st.sampled_from(["DICT_APRILTAG_16h5", "DICT_9X9", "DICT_4X4_50 "]),
)
VIDEO_OUT = opt(
    st.sampled_from(["v.mp4", "v.avi", "v.mkv", "sub/v.mov"]),
    st.sampled_from(["v.txt", "v", "a_file/v.mp4", "/dev/null/v.mp4", f"{SURROGATE}.mp4", f"{SURROGATE}.avi"]),
)
TRACKER_OPTIONS = {
    "--config": CONFIGS,
    "--dictionary": DICTIONARIES,
    "--marker-length": floats(0.001, 1.0),
    "--no-filter": FLAG,
}
RUN_OPTIONS = {
    "--max-frames": ints(1, 3),
    "--video-out": VIDEO_OUT,
    "--no-overlay": FLAG,
    "--spawn": FLAG,
}
COMMON = {"-v": FLAG, "-q": FLAG, "--quiet": FLAG, "--verbose": FLAG}

# demo --near/--far/--blur/--noise: valid values, and extremes argparse must refuse
OPTIONS = {
    "demo": {
        "--frames": ints(1, 40),
        "--seed": ints(0, 2**40),
        "--camera": CAMERAS,
        "--trajectory": opt(st.sampled_from(["sweep", "orbit", "static"]), st.sampled_from(["spiral", ""])),
        "--near": floats(0.05, 20.0),
        "--far": floats(0.05, 20.0),
        "--noise": opt(st.floats(0.0, 50.0).map(repr), st.sampled_from(["-1", "nan", "x", "1e300", "101"])),
        "--blur": opt(st.floats(0.0, 5.0).map(repr), st.sampled_from(["-1", "nan", "x", "1e300", "51"])),
        **TRACKER_OPTIONS,
        **RUN_OPTIONS,
        **COMMON,
    },
    "replay": {
        "--camera": CAMERAS,
        "--fps": floats(0.001, 1e6),
        "--images-out": opt(st.sampled_from(["ann", "sub/ann"]), PATHS | st.sampled_from(["a_file/ann", "imgs/."])),
        **TRACKER_OPTIONS,
        **RUN_OPTIONS,
        **COMMON,
    },
    "live": {
        "--device": opt(st.just("synthetic"), st.sampled_from(["/dev/video9", "9", "/nonexistent", "", SURROGATE])),
        "--camera": CAMERAS,
        "--width": ints(16, 640),
        "--height": ints(16, 480),
        "--fps": floats(5.0, 120.0),
        "--fourcc": opt(st.sampled_from(["MJPG", "YUYV"]), st.sampled_from(["", "TOOLONG", SURROGATE])),
        "--queue": ints(1, 8),
        "--reconnect-s": floats(0.0, 1.0),
        "--stall-s": floats(0.5, 5.0),
        "--seed": ints(0, 1000),
        "--record": FLAG,
        **TRACKER_OPTIONS,
        "--max-frames": ints(1, 3),
        "--video-out": VIDEO_OUT,
        "--no-overlay": FLAG,
        "--spawn": FLAG,
        # malformed only: a well-formed URL with no viewer behind it waits out the flush timeout
        "--connect": st.sampled_from(["garbage", "http://x", "rerun+http://", "rerun+http://h:99999999/proxy", ""]),
        **COMMON,
    },
    "bench": {
        "--quick": FLAG,
        "--config": CONFIGS,
        "--out": st.sampled_from(["b", "b/sub", ".", "a_file", "a_file/sub"]),
        **COMMON,
    },
    "markers": {
        "--dictionary": DICTIONARIES,
        "--ids": opt(
            st.sampled_from(["0", "0-3", "0,5,7", "49", " 1 , 2 "]),
            st.sampled_from(["3-1", "0,0", "50", "0-100001", "x"]),
        ),
        "--size-mm": opt(st.floats(1.0, 80.0).map(repr), st.sampled_from(["0", "-1", "nan", "1e300", "1e-300", "0.5"])),
        "--board": opt(st.sampled_from(["grid", "charuco"]), st.just("x")),
        "--cols": ints(1, 6),
        "--rows": ints(1, 6),
        "--gap-mm": floats(0.5, 20.0),
        "--square-mm": floats(1.0, 90.0),
        "--first-id": ints(0, 60),
        "--legacy": FLAG,
        "--name": opt(st.sampled_from(["a", "my-board"]), st.sampled_from(["a b", "../x", "", "é", SURROGATE])),
        "--format": opt(st.sampled_from(["pdf", "svg", "png"]), st.just("jpg")),
        "--dpi": opt(st.sampled_from(["50", "72", "150"]), st.sampled_from(["49", "0", "2401", "1000000"])),
        "--paper": opt(st.sampled_from(["a4", "letter"]), st.just("a3")),
        "--out": opt(st.sampled_from(["m", "m/sub"]), st.sampled_from(["a_file", "a_file/m", f"m{SURROGATE}"])),
        **COMMON,
    },
    "calibrate": {
        "--charuco": opt(st.sampled_from(["5x7", "5X7", "3x3"]), st.sampled_from(["0x7", "x", "5x7x2", "100x100"])),
        "--square-m": floats(0.01, 0.1),
        "--marker-m": floats(0.005, 0.08),
        "--dictionary": DICTIONARIES,
        "--legacy": FLAG,
        "--out": opt(st.just("c/cam.yml"), st.sampled_from(["c/", "c/cam.rrd", "imgs", "a_file/cam.yml"])),
        "--max-views": ints(3, 50),
        "--min-views": ints(3, 50),
        "--rrd": opt(st.just("c/cal.rrd"), st.sampled_from(["a_file/x.rrd", "c"])),
        "--spawn": FLAG,
        "--fps": floats(1.0, 60.0),
        "--width": ints(16, 640),
        "--height": ints(16, 480),
        "--duration-s": floats(0.1, 0.5),
        **COMMON,
    },
}
POSITIONALS = {
    "replay": opt(
        st.sampled_from(["imgs", "clip.avi", "imgs/*.png", "imgs/f0.png"]),
        st.sampled_from(
            [f"clip{SURROGATE}.avi", "empty.mp4", "text.mp4", "missing.mp4", "imgs/notes.txt", "'imgs/*.png'", ""]
        ),
    ),
    "bench": opt(st.sampled_from(["stability", "boards", "overlay", "speed"]), st.sampled_from(["stabilty", ""])),
    "calibrate": opt(
        st.sampled_from(["imgs", "imgs/*.png", "clip.avi"]),
        st.sampled_from(["missing", "/dev/video9", "9", "a_file", "", f"clip{SURROGATE}.avi"]),
    ),
}
REQUIRED = {  # options given 19 times in 20, so that most runs get past argparse and the file checks
    "calibrate": ["--charuco", "--square-m", "--marker-m", "--dictionary", "--out"],
    "live": ["--device"],  # else /dev/video0, absent here
    "replay": ["--camera"],  # else camera.yml beside the source (there only for imgs/)
}


def usually() -> st.SearchStrategy:
    """True 19 times in 20. (Not ``integers(...) > 0``: Hypothesis draws the simplest integer, 0, often.)"""
    return st.sampled_from([True] * 19 + [False])


def rarely() -> st.SearchStrategy:
    return st.sampled_from([False] * 29 + [True])


@st.composite
def command_line(draw, command: str, out: str) -> list[str]:
    options = OPTIONS[command]
    argv = draw(st.lists(st.sampled_from(["-v", "-q", "--quiet", "-vv"]), max_size=2))
    argv.append(command)
    if command in POSITIONALS and draw(usually()):
        argv.append(draw(POSITIONALS[command]))
    names = draw(st.lists(st.sampled_from(sorted(options)), max_size=5, unique=True))
    for name in REQUIRED.get(command, []):
        if name not in names and draw(usually()):
            names.append(name)
    if command == "markers" and draw(st.booleans()):
        single = ["--ids", "--size-mm"]
        names += [
            n
            for n in (single if draw(st.booleans()) else ["--board", "--cols", "--rows", *single[1:]])
            if n not in names
        ]
    for name in names:
        value = draw(options[name])
        argv += [name] if value is None else [name, value]
        if draw(rarely()):
            argv.append(draw(JUNK))
    if draw(rarely()):
        draw(st.randoms()).shuffle(argv)
    # the limits that keep every example cheap (given last: argparse keeps the last value)
    if command in ("demo", "replay", "live"):
        argv += ["--max-frames", "1", "--out", out]
    if command == "live":
        argv += ["--reconnect-s", "0", "--stall-s", "5"]
        if "--camera" not in names:  # the synthetic device renders 60 frames up front: keep them small
            argv += ["--width", "96", "--height", "54"]
    return argv


# ============================================================================ checks


def outputs_complete(out: Path) -> None:
    """A finished run's outputs: poses.csv with its header, every row the header's width; summary.json
    parses and says completed; recording.rrd is not empty."""
    lines = (out / "poses.csv").read_text(encoding="utf-8").splitlines()
    assert lines and lines[0] == POSES_HEADER
    rows = list(csv.reader(lines))
    assert all(len(row) == len(rows[0]) for row in rows)
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["status"] == "completed", summary["status"]
    assert (out / "recording.rrd").stat().st_size > 0


def check(result: CliResult, command: str, out: Path) -> None:
    assert_clean_exit(result)
    errors = error_lines(result.stderr)
    if result.system_exit:
        outcome(f"argparse exit {result.code}")
        assert result.code in (0, 2), result.describe()
        if result.code == 2:
            assert "usage: ar-anchor" in result.stderr, result.describe()
        return
    outcome(f"exit {result.code}")
    if result.code == 0:
        assert not errors, result.describe()
        if command in ("demo", "replay", "live"):
            outputs_complete(out)
    elif result.code == 2:
        assert len(errors) == 1, result.describe()  # one line saying what is wrong with the input
        if command in ("demo", "replay", "live"):
            assert not (out / "poses.csv").exists(), (
                f"outputs written for a run refused as bad input\n{result.describe()}"
            )
    else:
        assert errors, result.describe()  # a failure says why
        if command in ("demo", "replay", "live") and (out / "poses.csv").exists():
            lines = (out / "poses.csv").read_text(encoding="utf-8").splitlines()
            assert lines[0] == POSES_HEADER  # what was written stays readable


def fuzz_command(workspace: Path, command: str, data) -> None:
    out = f"out{next(_counter)}"
    argv = data.draw(command_line(command, out), label="argv")
    with working_directory(workspace):
        result = run_main(argv)
    check(result, command, workspace / out)


def _fuzz_test(command: str, budget: int):
    @fuzz_settings(budget)
    @given(data=st.data())
    def test(workspace, data):
        fuzz_command(workspace, command, data)

    test.__name__ = test.__qualname__ = f"test_fuzzed_{command}_command_lines_exit_cleanly"
    return test


test_fuzzed_demo_command_lines_exit_cleanly = _fuzz_test("demo", 30)
test_fuzzed_replay_command_lines_exit_cleanly = _fuzz_test("replay", 40)
test_fuzzed_live_command_lines_exit_cleanly = _fuzz_test("live", 25)
test_fuzzed_markers_command_lines_exit_cleanly = _fuzz_test("markers", 50)
test_fuzzed_calibrate_command_lines_exit_cleanly = _fuzz_test("calibrate", 40)


@fuzz_settings(40)
@given(data=st.data())
def test_fuzzed_bench_command_lines_exit_cleanly(workspace, stub_benchmarks, data):
    fuzz_command(workspace, "bench", data)


@fuzz_settings(60)
@given(
    argv=st.lists(
        st.one_of(
            JUNK,
            st.sampled_from(["demo", "replay", "live", "bench", "markers", "calibrate", "-h", "--help", "--version"]),
            st.sampled_from([name for options in OPTIONS.values() for name in options]),
        ),
        max_size=6,
    )
)
def test_random_token_soup_exits_cleanly(workspace, stub_benchmarks, argv):
    # no structure at all: every token list argparse can be handed (runs that start are kept to 1 frame)
    if any(token in ("demo", "replay", "live") for token in argv):
        argv = [*argv, "--max-frames", "1", "--out", f"out{next(_counter)}"]
    if "live" in argv:
        argv += ["--reconnect-s", "0", "--stall-s", "5"]
    if "demo" in argv:
        argv += ["--frames", "2"]
    with working_directory(workspace):
        result = run_main(argv)
    assert_clean_exit(result)
    outcome(f"exit {result.code}" + (" (argparse)" if result.system_exit else ""))


def test_letters_in_every_numeric_option_are_usage_errors(workspace):
    # each numeric option of each command, given a word: argparse refuses it, naming the option
    for command, options in OPTIONS.items():
        for name in options:
            if name in ("--max-frames", "--frames", "--seed", "--fps", "--near", "--far", "--dpi", "--queue", "--cols"):
                argv = [command, *(["x"] if command in POSITIONALS else []), name, "abc"]
                with working_directory(workspace):
                    result = run_main(argv)
                assert result.system_exit and result.code == 2, result.describe()
                assert name in result.stderr and "Traceback" not in result.stderr


# ==================================================================== found by fuzzing: cli.py, viz.py, video_out


@pytest.mark.parametrize(
    "extra",
    [
        pytest.param(["--near", "1e300", "--far", "1e300"], id="near-far-1e300"),
        pytest.param(["--near", "1e-300"], id="near-1e-300"),
    ],
)
def test_demo_extreme_distances_are_usage_errors(workspace, extra):
    with working_directory(workspace):
        result = run_main(["-q", "demo", "--frames", "2", *extra, "--out", f"out{next(_counter)}"])
    assert_clean_exit(result)
    assert result.code == 2, result.describe()


def test_demo_huge_blur_is_a_usage_error(workspace):
    with working_directory(workspace):
        result = run_main(["-q", "demo", "--frames", "2", "--blur", "1e300", "--out", f"out{next(_counter)}"])
    assert_clean_exit(result)
    assert result.code == 2, result.describe()


def test_demo_huge_noise_is_a_usage_error(workspace):
    with working_directory(workspace):
        result = run_main(["-q", "demo", "--frames", "2", "--noise", "1e300", "--out", f"out{next(_counter)}"])
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    assert "RuntimeWarning" not in result.stderr


def test_live_connect_to_a_malformed_url_is_a_usage_error(workspace):
    out = f"out{next(_counter)}"
    with working_directory(workspace):
        result = run_main(
            ["-q", "live", "--device", "synthetic", "--width", "96", "--height", "54"]
            + ["--connect", "garbage", "--max-frames", "1", "--out", out]
        )
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    assert not (workspace / out).exists(), "outputs created for a refused run"


def test_bench_out_that_is_a_file_is_a_clean_error(workspace, monkeypatch):
    # the real report writer, on an empty scenario list (the minutes-long grid is not what is tested)
    import ar_anchor.bench.stability.report as bench

    monkeypatch.setattr(bench, "stability_scenarios", lambda quick: [])
    with working_directory(workspace):
        result = run_main(["-q", "bench", "stability", "--out", "a_file"])
    assert_clean_exit(result)
    errors = error_lines(result.stderr)
    assert len(errors) == 1 and "a_file" in errors[0], result.describe()


def test_video_out_avi_with_a_non_utf8_name_does_not_crash(tmp_path):
    # OpenCV's bindings crash on file names that are not UTF-8 (see camera.opencv_path_problem, which the
    # readers now check); the .avi writer is not guarded. A child process, so that the crash fails one test.
    argv = [sys.executable, "-m", "ar_anchor", "-q", "demo", "--frames", "1", "--out", "run"]
    argv += ["--video-out", os.fsencode(f"v{SURROGATE}.avi")]
    result = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode in (0, 1, 2), f"exit {result.returncode}: {result.stderr[-500:]}"
    assert "Traceback" not in result.stderr


# ============================================================================ found by fuzzing (fixed)


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        pytest.param(
            ["markers", "--ids", "0", "--size-mm", "50", "--format", "png", "--dpi", "100000"],
            "--dpi",
            id="dpi-exhausting-memory",
        ),  # fmt: skip
        pytest.param(["markers", "--ids", "0", "--size-mm", "1e-300"], "--size-mm", id="invisible-marker"),
        pytest.param(["replay", "imgs", "--camera", "cam64.yml", "--fps", "1e-300"], "--fps", id="fps-overflow"),
        pytest.param(["replay", "imgs", "--camera", "cam64.yml", "--fps", "1e300"], "--fps", id="fps-zero-steps"),
    ],
)
def test_found_by_fuzzing_are_usage_errors(workspace, argv, named):
    out = f"out{next(_counter)}"
    with working_directory(workspace):
        result = run_main(["-q", *argv, "--out", out])
    assert_clean_exit(result)
    errors = error_lines(result.stderr)
    assert result.code == 2 and len(errors) == 1 and named in errors[0], result.describe()
    assert not (workspace / out / "poses.csv").exists()


def test_non_utf8_file_names_are_input_errors_not_crashes(tmp_path):
    # OpenCV's bindings segfault on a str that is not UTF-8 (how Python spells such a file name): a video, a
    # camera file and a board layout (through a config in a folder with such a name), in a child process
    name = os.fsencode(f"x{SURROGATE}")
    folder = tmp_path / f"conf{SURROGATE}"
    folder.mkdir()
    (folder / "map.yml").write_text(
        "%YAML:1.0\n---\naruco_bc_mInfoType: 1\naruco_bc_markers:\n"
        "   - { id:3, corners:[ [ 0., 0., 0. ], [ 0.05, 0., 0. ], [ 0.05, 0.05, 0. ], [ 0., 0.05, 0. ] ] }\n"
    )
    (folder / "tracker.toml").write_text('[[boards]]\nname = "m"\nkind = "custom"\nlayout = "map.yml"\n')
    writer = cv2.VideoWriter(str(tmp_path / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for _ in range(2):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    os.rename(tmp_path / "clip.avi", os.fsencode(tmp_path) + b"/" + name + b".avi")
    CameraModel.from_fov(64, 48, 60.0).to_yaml(tmp_path / "cam.yml")
    os.rename(tmp_path / "cam.yml", os.fsencode(tmp_path) + b"/" + name + b".yml")
    runs = {
        "video": ["replay", name + b".avi", "--camera", name + b".yml"],
        "camera": ["demo", "--frames", "1", "--camera", name + b".yml"],
        "layout": ["demo", "--frames", "1", "--config", os.fsencode(folder / "tracker.toml")],
    }
    for what, argv in runs.items():
        result = subprocess.run(
            [sys.executable, "-m", "ar_anchor", "-q", *argv, "--out", "run"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert result.returncode == 2, f"{what}: exit {result.returncode}: {result.stderr[-500:]}"
        assert "UTF-8" in result.stderr and "Traceback" not in result.stderr, result.stderr
