"""The process against a hostile environment: signals at start-up and while closing, a stdout that cannot
be written, an encoding without the characters of a file name, library noise, escape sequences in names."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from ar_anchor.cli import terminal
from ar_anchor.cli.report import finish
from ar_anchor.errors import EXIT_INTERRUPTED, EXIT_USAGE
from tests.helpers import cli, describe, run_main

DEMO = ["-q", "demo", "--frames", "2", "--out", "out"]
# long enough to be running still when the start-up signals arrive (a 2-frame demo can end within a second)
SIGNALLED = ["-q", "demo", "--frames", "60", "--out", "out"]


def _no_noise(result: subprocess.CompletedProcess[str]) -> None:
    for text in (result.stdout or "", result.stderr or ""):
        assert "Traceback" not in text, describe(result)
        assert "Exception ignored" not in text, describe(result)
        assert "internal error" not in text, describe(result)


# ---------------------------------------------------------------------------- start-up


def test_the_entry_point_imports_nothing_heavy_before_its_signal_handling():
    heavy = "('cv2', 'numpy', 'rerun', 'av')"
    code = f"import sys, ar_anchor.cli.main; print(sorted(m for m in {heavy} if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert result.stdout.strip() == "[]"


def test_a_run_command_preloads_the_tracker_but_not_trimesh_pyav_or_rerun():
    # the tracker loads while a signal still ends the process; trimesh (mesh files) and PyAV (video files)
    # where first used, whole (trimesh's optional imports catch BaseException and swallowed a Ctrl-C:
    # tests/test_lazy.py); rerun in the thread that opens the outputs (tests/cli/test_startup_imports.py)
    modules = "('ar_anchor.run.loop', 'ar_anchor.track.tracker', 'cv2', 'trimesh', 'scipy', 'av', 'rerun')"
    code = "import sys; from ar_anchor.cli import main; main._preload('demo')"
    code += f"; print([m in sys.modules for m in {modules}])"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert result.stdout.strip() == "[True, True, True, False, False, False, False]"


def test_signals_end_the_process_at_once_before_and_after_the_command_and_interrupt_it_during():
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    with terminal.Signals() as signals:
        assert signal.getsignal(signal.SIGINT) is terminal._exit_now
        assert signal.getsignal(signal.SIGTERM) is terminal._exit_now
        signals.running()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)  # SIGTERM exactly like Ctrl-C
            time.sleep(1.0)
        signals.finishing()
        assert signal.getsignal(signal.SIGINT) is terminal._exit_now
    assert {signum: signal.getsignal(signum) for signum in previous} == previous


def test_the_interrupted_line_says_where_the_outputs_are():
    interrupt = KeyboardInterrupt("signal 2")
    assert terminal.interrupted_outputs(interrupt) == "outputs written so far are complete"
    interrupt.out_dir = Path("recordings/live-1\n")  # set by the run loop; printed escaped
    assert terminal.interrupted_outputs(interrupt) == "outputs written so far in recordings/live-1\\n/ are complete"


_MAIN_THREAD_IMPORTS = """
import sys, threading
from ar_anchor.cli import terminal
running, seen = terminal.Signals.running, []
def traced(self):
    sys.meta_path.insert(0, Finder())
    return running(self)
class Finder:
    def find_spec(self, name, path, target=None):
        if name not in sys.modules and threading.current_thread() is threading.main_thread():
            seen.append(name)
terminal.Signals.running = traced
from ar_anchor.cli.main import main
main(sys.argv[1:])
print(sorted({name.split(".")[0] for name in seen}))
"""


@pytest.mark.parametrize(
    "command",
    [
        ["demo", "--frames", "2"],
        ["live", "--device", "synthetic", "--width", "320", "--height", "180", "--max-frames", "2"],
    ],
)
def test_a_run_imports_nothing_in_the_main_thread_once_a_signal_is_an_interrupt(command, tmp_path):
    # an import that a Ctrl-C cuts short can end in anything: numpy 2's own lazy submodules (numpy.random) or a
    # class body turned it into "internal error: RuntimeError: Error calling __set_name__" (seen on a busy machine)
    code = [sys.executable, "-c", _MAIN_THREAD_IMPORTS, "-q", *command, "--out", "out"]
    result = subprocess.run(code, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, describe(result)
    assert result.stdout.strip().splitlines()[-1] == "[]", describe(result)  # PyAV, trimesh: imported held


def test_an_interrupt_that_a_library_wrapped_is_still_an_interrupt():
    from ar_anchor.cli.main import _interrupted_within

    class Breaks:
        def __set_name__(self, owner, name):
            raise KeyboardInterrupt("signal 15")

    with pytest.raises(RuntimeError) as wrapped:
        type("Row", (), {"field": Breaks()})
    assert _interrupted_within(wrapped.value)
    assert not _interrupted_within(RuntimeError("a bug"))
    try:
        try:
            raise ValueError("first")
        except ValueError as first:
            raise RuntimeError("second") from first
    except RuntimeError as chained:
        assert not _interrupted_within(chained)


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("after_s", [0.15, 0.3, 0.45, 0.7, 1.0])
def test_a_signal_during_start_up_is_one_line_and_exit_130(signum, after_s, tmp_path):
    process = subprocess.Popen(cli(SIGNALLED), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(after_s)
    assert process.poll() is None, "the run ended before the signal: it tests nothing"
    process.send_signal(signum)
    stdout, stderr = process.communicate(timeout=60)
    result = subprocess.CompletedProcess(SIGNALLED, process.returncode, stdout, stderr)
    _no_noise(result)
    assert "requires numpy" not in stderr, describe(result)
    if process.returncode == -signum:  # before the interpreter ran a line of ours: killed, silently
        assert stderr == "", describe(result)
        return
    assert process.returncode == EXIT_INTERRUPTED, describe(result)  # never swallowed, never a completed run
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ar-anchor: interrupted"), describe(result)


# ---------------------------------------------------------------------------- a second Ctrl-C while closing


class _StalledViewer:
    """Listens like a viewer, accepts, and never reads a byte: rerun's flush and disconnect block on it."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.connections: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                connection, _ = self.server.accept()
            except OSError:
                return
            self.connections.append(connection)

    def close(self) -> None:
        self.server.close()
        for connection in self.connections:
            connection.close()


@pytest.mark.slow
def test_a_second_ctrl_c_while_flushing_to_a_stalled_viewer_ends_the_run_at_once(tmp_path):
    viewer = _StalledViewer()
    try:
        args = ["-q", "demo", "--frames", "300", "--connect", f"rerun+http://127.0.0.1:{viewer.port}/proxy"]
        args += ["--out", "out"]
        process = subprocess.Popen(cli(args), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while not (tmp_path / "out" / "poses.csv").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(3.0)  # frames logged into the viewer that never reads them
        process.send_signal(signal.SIGINT)
        time.sleep(1.0)
        process.send_signal(signal.SIGINT)
        sent = time.monotonic()
        stdout, stderr = process.communicate(timeout=60)
        waited = time.monotonic() - sent
    finally:
        viewer.close()
    result = subprocess.CompletedProcess(args, process.returncode, stdout, stderr)
    _no_noise(result)
    assert process.returncode == EXIT_INTERRUPTED, describe(result)
    assert waited < 5.0, describe(result)
    assert "recording.rrd may be incomplete" in stderr and "outputs in out/ are complete" in stderr, describe(result)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    assert summary["closing_cut_short"] == ["recording.rrd"]
    rows = (tmp_path / "out" / "poses.csv").read_text().splitlines()
    assert all(len(row.split(",")) == len(rows[0].split(",")) for row in rows)  # whole rows only


@pytest.mark.slow
def test_a_run_that_ends_while_its_viewer_stalls_ends_on_its_own(tmp_path):
    # given a viewer that accepts the connection and never reads (rerun's disconnect and its at-exit
    # flush used to wait for it forever: a 60-frame demo did not end in 150 s)
    # (its writes given 2 s, not the default 10: the same bound, sooner)
    (tmp_path / "flush.toml").write_text("[recording]\nflush_timeout_s = 2.0\n")
    viewer = _StalledViewer()
    try:
        args = ["-q", "demo", "--frames", "60", "--config", "flush.toml"]
        args += ["--connect", f"rerun+http://127.0.0.1:{viewer.port}/proxy", "--out", "out"]
        result = subprocess.run(cli(args), cwd=tmp_path, capture_output=True, text=True, timeout=120)
    finally:
        viewer.close()
    # then the run ends by itself: exit 1, one error line naming the viewer, the other outputs complete
    _no_noise(result)
    assert result.returncode == 1, describe(result)
    errors = [line for line in result.stderr.splitlines() if line.startswith("ar-anchor: error:")]
    assert len(errors) == 1 and "viewer" in errors[0] and "within 2 s" in errors[0], describe(result)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "failed" and 0 < summary["frames"] <= 60
    rows = (tmp_path / "out" / "poses.csv").read_text().splitlines()
    assert all(len(row.split(",")) == len(rows[0].split(",")) for row in rows)
    assert {int(row.split(",")[0]) for row in rows[1:]} <= set(range(summary["frames"]))


# ---------------------------------------------------------------------------- stdout


class _Broken:
    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self) -> None:
        raise BrokenPipeError(32, "Broken pipe")

    def fileno(self) -> int:
        raise OSError("no descriptor")


def test_a_stdout_that_cannot_be_written_is_given_up_quietly():
    quiet = terminal._QuietStdout(_Broken())
    assert quiet.write("outputs: out/\n") == len("outputs: out/\n")
    quiet.flush()
    assert quiet.broken


@pytest.mark.slow
@pytest.mark.parametrize("where", ["closed pipe", "/dev/full"])
def test_an_unwritable_stdout_ends_quietly_with_the_runs_exit_code(where, tmp_path):
    if where == "/dev/full" and not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    if where == "closed pipe":
        process = subprocess.Popen(cli(DEMO[1:]), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        process.stdout.close()  # the reader is gone before a line was written (| head after its line)
        stderr = process.stderr.read().decode()
        process.wait(timeout=120)
        result = subprocess.CompletedProcess(DEMO, process.returncode, "", stderr)
    else:
        with open("/dev/full", "w") as full:
            result = subprocess.run(cli(DEMO[1:]), cwd=tmp_path, stdout=full, stderr=subprocess.PIPE, text=True)
    _no_noise(result)
    assert result.returncode == 0 and result.stderr == "", describe(result)
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["status"] == "completed"


@pytest.mark.slow
def test_an_ascii_terminal_shows_a_non_ascii_file_name_escaped(tmp_path):
    env = {**os.environ, "PYTHONIOENCODING": "ascii"}
    args = ["demo", "--frames", "2", "--out", "caf\u00e9"]
    result = subprocess.run(cli(args), cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    _no_noise(result)
    assert result.returncode == 0, describe(result)
    assert "outputs: caf\\xe9/" in result.stdout, describe(result)
    assert (tmp_path / "caf\u00e9" / "summary.json").is_file()


def test_version_to_a_full_device_is_quiet():
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    with open("/dev/full", "w") as full:
        result = subprocess.run(cli(["--version"]), stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)
    assert result.returncode == 0 and result.stderr == "", result.stderr


# ---------------------------------------------------------------------------- library noise


def test_numpy_warnings_go_to_the_debug_log_not_stderr(capsys, caplog, monkeypatch):
    logger = logging.getLogger("ar_anchor")
    monkeypatch.setattr(logger, "handlers", [])  # whatever an earlier test left there
    monkeypatch.setattr(logger, "propagate", True)  # to caplog
    with caplog.at_level("DEBUG", logger="ar_anchor"), terminal.warnings_to_log():
        warnings.simplefilter("always")
        np.float64(1e300) * np.float64(1e300)  # noqa: B018 - overflow: a RuntimeWarning
    assert capsys.readouterr().err == ""
    assert any("RuntimeWarning" in record.getMessage() for record in caplog.records)


def test_opencv_is_silent_below_vv_and_speaks_at_vv():
    code = (
        "import sys; from ar_anchor.cli import terminal; terminal.quiet_libraries_early(); import cv2; "
        "terminal.quiet_libraries(int(sys.argv[1])); cv2.imread('/nonexistent/x.png')"
    )
    env = {key: value for key, value in os.environ.items() if key not in ("OPENCV_LOG_LEVEL", "RUST_LOG")}
    quiet = subprocess.run([sys.executable, "-c", code, "0"], capture_output=True, text=True, env=env, timeout=60)
    loud = subprocess.run([sys.executable, "-c", code, "2"], capture_output=True, text=True, env=env, timeout=60)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    assert "imread" in loud.stderr


# ---------------------------------------------------------------------------- file names on the terminal


def test_the_summary_lines_escape_file_names(capsys):
    hostile = "out\n\x1b[31mred\rx"
    outputs = SimpleNamespace(
        out_dir=Path(hostile),
        raw_video=None,
        summary={"status": "completed", "video_out": {"path": hostile + ".mp4", "frames": 3}},
    )
    assert finish(SimpleNamespace(quiet=True), outputs) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\r" not in out
    assert out.count("\n") == 1  # one line: the outputs and the annotated video
    assert "out\\n\\x1b[31mred\\rx/" in out


def test_error_lines_escape_file_names(tmp_path):
    result = run_main(["replay", str(tmp_path / "a\nb\x1b[2J.mp4"), "--camera", str(tmp_path / "c.yml")])
    assert result.code == EXIT_USAGE, result.describe()
    assert "\x1b" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.describe()
    assert "a\\nb\\x1b[2J.mp4" in result.stderr


# ---------------------------------------------------------------------------- --connect


def test_connect_to_a_viewer_that_is_not_there_is_refused_before_the_run(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as probe:
        port = probe.getsockname()[1]  # free again once closed
    out = tmp_path / "out"
    result = run_main(["demo", "--frames", "2", "--connect", f"rerun+http://127.0.0.1:{port}/proxy", "--out", str(out)])
    assert result.code == EXIT_USAGE, result.describe()
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and f"127.0.0.1:{port}" in lines[0] and "--connect" in lines[0], result.describe()
    assert not out.exists()


def test_a_signal_ignored_by_the_parent_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job of a script, nohup
    try:
        with terminal.Signals() as signals:
            signals.running()
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is terminal._raise_interrupt
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
