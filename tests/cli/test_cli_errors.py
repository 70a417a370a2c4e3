"""End-to-end ``ar-anchor`` error behaviour: exit codes and stderr.

Bad input is exit code 2 with a message and no traceback; a bad file is exactly one stderr line
naming that file; nothing is written for a run that never started.

Each case runs the command's ``main`` in-process (a real process costs ~0.2 s of start-up for a line of
argparse); :func:`test_a_real_process_says_what_main_says` runs a sample of them as real ``python -m ar_anchor``
processes and checks they give the same exit code and the same stderr, and the demo runs as a real process.
"""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import pytest

from tests.helpers import POSES_HEADER, cli, run_main, verify_rrd

pytestmark = pytest.mark.slow

TIMEOUT_S = 60

_K_OK = "500., 0., 319.5, 0., 500., 239.5, 0., 0., 1."
_CAMERA_WRONG_SHAPE = (
    "%YAML 1.2\n---\nimage_width: 640\nimage_height: 480\n"
    "camera_matrix: !!opencv-matrix\n   rows: 2\n   cols: 3\n   dt: d\n"
    "   data: [ 500., 0., 320., 0., 500., 240. ]\n"
)
_CAMERA_NEGATIVE_F = (
    "%YAML 1.2\n---\nimage_width: 640\nimage_height: 480\n"
    f"camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ -{_K_OK} ]\n"
)


def run_cli(args: list[str], cwd: Path, *, real_process: bool = False) -> subprocess.CompletedProcess[str]:
    """``ar-anchor ARGS`` in ``cwd``: its ``main`` in this process, or (``real_process``) a new Python process."""
    if real_process:
        return subprocess.run(
            cli(args),
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
            check=False,
        )
    result = run_main(args, cwd)
    return subprocess.CompletedProcess(args, result.code, result.stdout, result.stderr)


def assert_usage_error(result: subprocess.CompletedProcess[str]) -> None:
    assert result.returncode == 2, f"exit {result.returncode}, stderr: {result.stderr!r}"
    assert result.stderr.strip(), "no message on stderr"
    assert "Traceback" not in result.stderr and "Traceback" not in result.stdout


# ======================================================================== bad files: one line naming the file


# (option, file name, file content or None for a missing file, text the one stderr line must contain)
BAD_FILES = [
    pytest.param(
        "--config", "bad_value.toml", "[markers]\nlength_m = -0.05\n", "[markers] length_m", id="a-config-bad-value"
    ),
    pytest.param(
        "--config",
        "bad_type.toml",
        "[recording]\njpeg_quality = 'high'\n",
        "[recording] jpeg_quality",
        id="a-config-bad-type",
    ),
    pytest.param("--config", "bad_key.toml", "[pose]\nmax_reproj = 2.0\n", "max_reproj", id="a-config-unknown-key"),
    pytest.param(
        "--config", "bad_syntax.toml", "[pose\nmax_reproj_px = 2.0\n", "invalid TOML", id="a-config-invalid-toml"
    ),
    pytest.param(
        "--config",
        "bad_dict.toml",
        "[detector]\ndictionary = 'DICT_4X4_51'\n",
        "dictionary",
        id="b-config-unknown-dictionary",
    ),
    pytest.param("--config", "no_such.toml", None, "not found", id="a-config-missing"),
    pytest.param(
        "--config",
        "bad_id_key.toml",
        '[markers.lengths_m]\n"\u00b2" = 0.04\n',
        "lengths_m",
        id="a-config-unicode-digit-id",
    ),
    pytest.param("--camera", "no_such_camera.yml", None, "not found", id="c-camera-missing"),
    pytest.param("--camera", "bad_shape.yml", _CAMERA_WRONG_SHAPE, "camera_matrix", id="d-camera-wrong-shape"),
    pytest.param("--camera", "bad_focal.yml", _CAMERA_NEGATIVE_F, "focal", id="d-camera-negative-focal"),
    pytest.param("--camera", "empty_camera.yml", "", "empty", id="d-camera-empty"),
    pytest.param("--camera", "garbage_camera.yml", "not: a [camera\n{{{\n", "camera file", id="d-camera-garbage"),
    pytest.param(
        "--camera",
        "string_matrix.yml",
        "%YAML 1.2\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: identity\n",
        "camera_matrix",
        id="d-camera-matrix-not-a-matrix",
    ),
]


@pytest.mark.parametrize(("option", "name", "content", "expected"), BAD_FILES)
def test_bad_file_is_exit_2_with_one_stderr_line_naming_it(tmp_path, option, name, content, expected):
    # given a bad (or missing) config / camera file
    if content is not None:
        (tmp_path / name).write_text(content)
    # when the demo is started with it
    result = run_cli(["--quiet", "demo", "--frames", "2", option, name, "--out", "run"], tmp_path)
    # then: usage exit code, one line, naming the file and the problem, and no output written
    assert_usage_error(result)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got {lines!r}"
    assert lines[0].startswith("ar-anchor: error: ")
    assert name in lines[0]
    assert expected in lines[0]
    assert not (tmp_path / "run").exists()


# ======================================================================== bad options: argparse rejects them

BAD_OPTIONS = [
    pytest.param(["demo", "--frame", "3"], "--frame", id="e-misspelt-frame"),
    pytest.param(["demo", "--framez", "3"], "--framez", id="e-misspelt-framez"),
    pytest.param(["demo", "--fram", "3"], "--fram", id="e-abbreviation"),
    pytest.param(["demo", "--max", "3"], "--max", id="e-abbreviation-max-frames"),
    pytest.param(["--verb", "demo"], "--verb", id="e-abbreviation-top-level"),
    pytest.param(["demo", "--frames", "0"], "--frames", id="f-frames-zero"),
    pytest.param(["demo", "--frames", "-3"], "--frames", id="f-frames-negative"),
    pytest.param(["demo", "--frames", "abc"], "--frames", id="g-frames-not-int"),
    pytest.param(["demo", "--frames", "2.5"], "--frames", id="g-frames-fraction"),
    pytest.param(["demo", "--near", "0"], "--near", id="near-zero"),
    pytest.param(["demo", "--noise", "nan"], "--noise", id="noise-nan"),
    pytest.param(["demo", "--trajectory", "spiral"], "--trajectory", id="unknown-trajectory"),
    pytest.param(["demo", "stray-positional"], "stray-positional", id="stray-positional"),
    pytest.param(["demoo"], "demoo", id="unknown-command"),
    pytest.param([], "COMMAND", id="no-command"),
]


@pytest.mark.parametrize(("argv", "named"), BAD_OPTIONS)
def test_bad_option_is_rejected_by_argparse_with_exit_2(tmp_path, argv, named):
    # when the CLI is given a bad option (plus a valid --out so a silent run would be visible)
    result = run_cli([*argv, "--out", "run"] if argv[:1] == ["demo"] else argv, tmp_path)
    # then argparse refuses it: exit 2, a usage message naming the culprit, nothing run
    assert_usage_error(result)
    assert "usage: ar-anchor" in result.stderr
    assert named in result.stderr
    assert not (tmp_path / "run").exists()
    assert not (tmp_path / "recordings").exists()


def test_far_below_near_is_exit_2_one_line(tmp_path):
    argv = ["--quiet", "demo", "--frames", "2", "--near", "2", "--far", "1", "--out", "run"]
    result = run_cli(argv, tmp_path)
    assert_usage_error(result)
    assert result.stderr.splitlines() == [result.stderr.strip()]
    assert "--far" in result.stderr and "--near" in result.stderr


# a bad file, a bad option, a bad pair of values, an unknown command
REAL_PROCESS_SAMPLE = [
    ["--quiet", "demo", "--frames", "2", "--camera", "no_such_camera.yml", "--out", "run"],
    ["demo", "--framez", "3", "--out", "run"],
    ["--quiet", "demo", "--frames", "2", "--near", "2", "--far", "1", "--out", "run"],
    ["demoo"],
]


def test_a_real_process_says_what_main_says(tmp_path, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")  # argparse wraps its usage lines to the terminal's width: one width for both
    for argv in REAL_PROCESS_SAMPLE:
        # when the same bad command line is given to a real process and to main in-process
        real = run_cli(argv, tmp_path, real_process=True)
        in_process = run_cli(argv, tmp_path)
        # then both end with exit 2 and the same stderr, and neither ran
        assert real.returncode == in_process.returncode == 2, (argv, real, in_process)
        assert real.stderr == in_process.stderr and real.stdout == in_process.stdout, (argv, real, in_process)
        assert "Traceback" not in real.stderr and not (tmp_path / "run").exists()


# ============================================================================ happy path


@pytest.mark.parametrize(
    "argv",
    [
        pytest.param(["--quiet", "demo", "--frames", "5"], id="quiet-before-command"),
        pytest.param(["demo", "--frames", "5", "--quiet"], id="quiet-after-command"),
    ],
)
def test_demo_writes_csv_summary_and_valid_recording(tmp_path, argv):
    # given an output directory that does not exist yet
    out = tmp_path / "run"
    # when a short demo runs
    result = run_cli([*argv, "--out", str(out)], tmp_path, real_process=True)
    # then it succeeds quietly and writes the three outputs
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert "frames in" not in result.stdout  # --quiet: no summary table
    assert str(out) in result.stdout

    lines = (out / "poses.csv").read_text().splitlines()
    assert lines[0] == POSES_HEADER
    rows = list(csv.DictReader(lines))
    assert rows, "poses.csv has no data rows"
    assert {int(r["frame"]) for r in rows} <= set(range(5))
    assert all(len(r) == len(POSES_HEADER.split(",")) for r in rows)

    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 5

    verify_rrd(out / "recording.rrd")
