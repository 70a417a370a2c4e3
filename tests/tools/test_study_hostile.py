"""``ar-anchor study`` against hostile input: numbers out of range, odd cameras, bad ``--out`` paths, write
failures and interruption (Ctrl-C, SIGTERM) at any moment; nothing that looks final is left behind."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.errors import InputError, OutputError
from ar_anchor.tools.study import command, run_study
from ar_anchor.tools.study import interrupt as study_interrupt
from ar_anchor.tools.study.figures import plot_jitter, plot_outliers
from ar_anchor.tools.study.files import StudyFiles
from tests.helpers import study_args

TINY_PNP = ["--seeds", "1", "--points", "20", "--contamination", "10", "--iterations", "20"]


parse = study_args


def camera_file(tmp_path: Path, width: int, height: int, fx: float, *, cx=None, skew=0.0, dist=()) -> Path:
    k = np.array([[fx, skew, width / 2 if cx is None else cx], [0.0, fx, height / 2], [0.0, 0.0, 1.0]])
    path = tmp_path / "camera.yml"
    CameraModel(k, np.array(dist, float), width, height).to_yaml(path)
    return path


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["jitter", "--distances", "1e9"], r"--distances: 1e\+09 m outside 0\.192-6\.25 m, where the 5 cm marker"),
        (["jitter", "--distances", "0.05,1"], "--distances: 0.05 m outside 0.192-6.25 m"),
        (["jitter", "--distances", "1", "--marker-m", "0.001"], "--distances: 1 m outside 0.00383-0.125 m"),
        (["jitter", "--distances", ",".join(str(0.3 + i / 100) for i in range(101))], "at most 100 values, got 101"),
        (["jitter", "--marker-m", "34"], r"--marker-m: must be in \[0\.001, 1\] m, got 34"),
        (["jitter", "--frames", "1000000000"], r"--frames: must be in \[32, 100000\] \(the first 30 are"),
        (["jitter", "--blur", "1e9"], r"--blur: must be in \[0, 10\] px, got 1e\+09"),
        (["jitter", "--sensor-noise", "1e3"], r"--sensor-noise: must be in \[0, 100\] grey levels"),
        (["jitter", "--sensor-noise", "nan"], "--sensor-noise: must be in .* got nan"),
        (["jitter", "--tilt-deg", "inf"], r"--tilt-deg: must be in \[0, 80\), got inf"),
        (["jitter", "--seed", "3000000"], r"--seed: must be in \[0, 1e\+06\], got 3e\+06"),
        (["outliers", "--points", "100000"], r"--points: must be in \[6, 1000\], got 100000"),
        (["outliers", "--iterations", "100000"], r"--iterations: must be in \[1, 5000\]"),
        (["outliers", "--seeds", "1000000000"], r"--seeds: must be in \[1, 100000\]"),
        (["outliers", "--pixel-noise", "1e6"], r"--pixel-noise: must be in \[0, 100\] px"),
        (["outliers", "--threshold", "1e9"], r"--threshold: must be in \[0\.001, 1000\] px"),
        (["ransac", "--thresholds", "1,2,1e9"], r"--thresholds: must all be in \[0\.001, 1000\] px, got 1e\+09"),
    ],
)
def test_number_out_of_range_is_an_input_error_naming_option_and_range(tmp_path, argv, message):
    # given
    out = tmp_path / "study"
    # when / then: refused before anything runs or is written
    start = time.perf_counter()
    with pytest.raises(InputError, match=message):
        run_study(parse([*argv, "--out", str(out)]))
    assert time.perf_counter() - start < 5.0
    assert not out.exists()


@pytest.mark.parametrize(
    ("study", "camera", "message"),
    [
        ("jitter", dict(width=16, height=16, fx=16.0), "image 16x16; the jitter study needs sides of 64-4096 px"),
        ("outliers", dict(width=32, height=32, fx=32.0), "image 32x32; the pnp study needs sides of 64-16384 px"),
        ("jitter", dict(width=20000, height=20000, fx=15000.0), "the jitter study needs sides of 64-4096 px"),
        ("outliers", dict(width=1280, height=720, fx=1000.0, cx=-10.0), r"principal point \(-10, 360\) lies outside"),
        ("jitter", dict(width=1280, height=720, fx=20.0), "horizontal field of view 176 deg"),
        ("outliers", dict(width=1280, height=720, fx=1e5), "horizontal field of view 0.733 deg"),
        # refused by the camera file's own checks or by the study's: either way, naming the file
        ("outliers", dict(width=1280, height=720, fx=1000.0, cx=-50000.0), "principal point"),
        ("jitter", dict(width=1280, height=720, fx=1000.0, skew=1e9), "skew"),
        ("jitter", dict(width=1280, height=720, fx=1.0), "(field of view|focal length)"),
        ("jitter", dict(width=1280, height=720, fx=1000.0, dist=(-1e6, 0, 0, 0, 0)), "fold"),
        ("outliers", dict(width=1280, height=720, fx=1000.0, dist=(-1e6, 0, 0, 0, 0)), "fold"),
    ],
)
def test_odd_camera_is_an_input_error_naming_the_camera_file(tmp_path, study, camera, message):
    # given
    path = camera_file(tmp_path, **camera)
    out = tmp_path / "study"
    # when / then
    with pytest.raises(InputError, match=f"^--camera: camera file {path}: .*{message}"):
        run_study(parse([study, "--camera", str(path), "--out", str(out)]))
    assert not out.exists()


def test_jitter_camera_whose_view_never_fits_the_scene_says_so(tmp_path):
    # given: the principal point on the image's left edge: the camera aims there, half the scene is cut off
    path = camera_file(tmp_path, 1280, 720, 1000.0, cx=0.0)
    # when / then
    with pytest.raises(InputError, match="--distances: no distance shows the 5 cm marker and its board"):
        run_study(parse(["jitter", "--camera", str(path), "--out", str(tmp_path / "study")]))


def _undetected_row(distance: float) -> dict:
    empty = {"frames": 0, "detected_pct": 0.0}
    return {
        "distance_m": distance,
        "marker_px": 10.0,
        **{f"{t}_{p}": dict(empty) for t in ("marker", "board") for p in ("raw", "tracker")},
        "marker_gap_median_px": None,
        "marker_noise_free_margin_px": None,
        "marker_tracker_states_pct": {"tracked": 0.0, "ambiguous": 0.0, "predicted": 0.0},
    }


def test_jitter_figure_of_a_study_that_detected_nothing_or_no_noise_is_drawn(tmp_path, recwarn):
    # given: no detection at any distance (the log axes have nothing positive); one distance, zero spreads
    settings = {"flip_deg": 10.0, "marker_m": 0.05, "camera": "c", "tilt_deg": 10.0, "frames": 40}
    settings |= {"settle_frames": 30, "sensor_noise_grey": 0.0}
    nothing = {"distances": [_undetected_row(1.0), _undetected_row(2.0)], "summary": {}, "settings": settings}
    still = _undetected_row(1.0)
    still["marker_raw"] |= {"frames": 10, "rotation_std_deg": 0.0, "distance_std_mm": 0.0, "flipped_pct": 0.0}
    quiet = {"distances": [still], "summary": {}, "settings": settings}
    # when
    plot_jitter(nothing, tmp_path / "nothing.png")
    plot_jitter(quiet, tmp_path / "quiet.png")
    # then
    for name in ("nothing.png", "quiet.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    assert not [w for w in recwarn if "log" in str(w.message)], [str(w.message) for w in recwarn]


def test_outliers_figure_with_every_solve_failed_is_drawn(tmp_path):
    # given
    rows = [{"plain_error_m": None, "ransac_error_m": None, "inliers": 0, "honest_inliers": 0}]
    result = {"seeds": rows, "settings": {"contamination": 0.5, "threshold_px": 2.0, "iterations": 1}}
    result["summary"] = {"honest_points": 6}
    # when
    plot_outliers(result, tmp_path / "failed.png")
    # then
    assert (tmp_path / "failed.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("", "--out: empty path"),
        (os.fsdecode(b"study-\xff"), r"--out study-\\udcff: the path is not valid UTF-8"),
        ("taken/inner", r"--out: .*taken/inner is inside .*taken, which is a file, not a directory"),
        ("line\nbreak\x1b[31m/" + os.fsdecode(b"\xfe"), r"line\\nbreak\\x1b\[31m/\\udcfe: the path is not valid"),
    ],
)
def test_bad_out_is_an_input_error_naming_it_printably(tmp_path, monkeypatch, out, message):
    # given
    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken").write_text("mine")
    # when / then
    with pytest.raises(InputError, match=message) as caught:
        run_study(parse(["outliers", *TINY_PNP, "--out", out]))
    assert "\n" not in str(caught.value) and "\x1b" not in str(caught.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]
    assert (tmp_path / "taken").read_text() == "mine"


@pytest.mark.parametrize("out", ["/sys", "/sys/ar-anchor-study"])
def test_out_that_cannot_be_written_is_an_input_error(out):
    # given: /sys refuses new files even to root
    if not Path("/sys").is_dir():
        pytest.skip("no /sys here")
    # when / then
    with pytest.raises(InputError, match=f"--out {out}: cannot write there"):
        run_study(parse(["outliers", *TINY_PNP, "--out", out]))


def test_write_failure_mid_study_names_the_file_and_leaves_nothing_final(tmp_path, monkeypatch):
    # given: the disk fills as the Markdown is written
    out = tmp_path / "study"

    def full(self, suffix, text):
        raise self.error(suffix, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))

    monkeypatch.setattr(StudyFiles, "write_text", full)
    # when / then
    with pytest.raises(OutputError, match=r"study/outliers\.md: cannot write \(No space left on device\)"):
        run_study(parse(["outliers", *TINY_PNP, "--out", str(out)]))
    assert list(out.iterdir()) == []


def _plotter_interrupted(swallowed: bool):
    """A figure writer that is interrupted by a real SIGINT while drawing (its exception swallowed, as in
    a library's cleanup, when ``swallowed``)."""

    def plot(result, path):
        Path(path).write_bytes(b"\x89PNG half")
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs here
        except KeyboardInterrupt:
            if not swallowed:
                raise

    return plot


@pytest.mark.parametrize("swallowed", [False, True])
def test_interrupted_study_leaves_nothing_that_looks_final(tmp_path, monkeypatch, swallowed):
    # given: a study that completes, and a second interrupted while its figure is drawn
    out = tmp_path / "study"
    handler = signal.getsignal(signal.SIGINT)
    writers = dict(command._WRITERS)
    writers["ransac"] = (_plotter_interrupted(swallowed), writers["ransac"][1])
    monkeypatch.setattr(command, "_WRITERS", writers)
    monkeypatch.setattr(command, "STUDIES", ("outliers", "ransac"))
    # when / then
    with pytest.raises(KeyboardInterrupt):
        run_study(parse(["all", *TINY_PNP, "--contaminations", "0", "--thresholds", "2", "--out", str(out)]))
    assert sorted(p.name for p in out.iterdir()) == ["outliers.json", "outliers.md", "outliers.png", "outliers.rrd"]
    assert signal.getsignal(signal.SIGINT) is handler


def test_all_studies_end_with_one_line_listing_every_file(tmp_path, monkeypatch, capsys):
    # given two studies run as `all`
    out = tmp_path / "study"
    monkeypatch.setattr(command, "STUDIES", ("outliers", "ransac"))
    args = parse(["all", *TINY_PNP, "--contaminations", "0", "--thresholds", "2", "--out", str(out)])
    args.quiet = False
    # when they complete
    assert run_study(args) == 0
    # then the last line names each file written, and they are the folder's files
    last = capsys.readouterr().out.strip().splitlines()[-1]
    listed = last.removeprefix(f"outputs: {out}/ (").removesuffix(")").split(", ")
    assert sorted(listed) == sorted(p.name for p in out.iterdir()) and len(listed) == 8, last


def test_signal_within_held_waits_for_its_end_then_interrupts():
    # given
    done = []
    with study_interrupt.interruptible():
        # when
        with pytest.raises(KeyboardInterrupt):
            with study_interrupt.held():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.2)
                done.append("renamed")
    # then
    assert done == ["renamed"]


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_study_interrupted_in_its_loop_exits_130_within_seconds_leaving_no_final_file(tmp_path, sig):
    # given: a jitter study that would run for minutes
    out = tmp_path / "study"
    argv = [sys.executable, "-m", "ar_anchor.cli.main", "study", "jitter", "--frames", "100000", "--distances", "1"]
    process = subprocess.Popen([*argv, "--out", str(out)], stderr=subprocess.PIPE, text=True)
    try:
        lines = [process.stderr.readline() for _ in range(1)]
        while not lines[-1].startswith("jitter: 1 m") and lines[-1] and len(lines) < 20:
            lines.append(process.stderr.readline())
        assert lines[-1].startswith("jitter: 1 m"), lines
        # well into the frame loop: after the line, one noise-free view is rendered and tracked twice (~0.1 s
        # of CPU), then the loop runs for minutes; the child spins a core for as long as this sleep lasts
        time.sleep(1.5)
        # when
        sent = time.perf_counter()
        process.send_signal(sig)
        code = process.wait(timeout=30)
    finally:
        process.kill()
    # then
    assert code == 130
    assert time.perf_counter() - sent < 5.0
    assert "interrupted" in process.stderr.read()
    assert list(out.iterdir()) == [], "an interrupted study left files"


@pytest.mark.slow
def test_odd_but_allowed_jitter_values_run(tmp_path, recwarn):
    # given: one distance given twice, no sensor noise, no blur, no tilt, the fewest frames
    out = tmp_path / "study"
    argv = ["jitter", "--distances", "1,1", "--sensor-noise", "0", "--blur", "0", "--tilt-deg", "0"]
    # when
    code = run_study(parse([*argv, "--frames", "32", "--out", str(out)]))
    # then
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["jitter.json", "jitter.md", "jitter.png", "jitter.rrd"]
    assert not [w for w in recwarn if "log" in str(w.message)]
    assert (out / "jitter.rrd").stat().st_size > 0
