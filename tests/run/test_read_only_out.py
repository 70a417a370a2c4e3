"""An existing output folder on a read-only file system (issue 34): every command that writes ends with one line
naming the folder, exit 1 (an output that cannot be written), never ``internal error: OSError [Errno 30]`` (the
lock's clean-up raised it over the real error).

Two ways: in-process, with the file functions made to fail with EROFS inside the folder (fast, everywhere); and
for real, in a user and mount namespace (``unshare -rm``) with the folder bind-mounted read-only (skipped where
the machine does not allow it)."""

from __future__ import annotations

import builtins
import errno
import io
import json
import os
import pathlib
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from tests.helpers import assert_clean_exit, error_lines, run_main
from tests.tools.map.test_outputs_hostile import _sheet_video

CAMERA = Path(__file__).resolve().parents[2] / "configs" / "camera_synthetic.yml"
ROOT = Path(__file__).resolve().parents[2]


def _inputs(tmp_path: Path) -> tuple[Path, Path, dict[str, list[str]]]:
    """The inputs (outside the read-only folder), the read-only folder (a run's output folder inside it) and the
    command lines, by name, that write into it."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    video = inputs / "in.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 90))
    for i in range(3):
        writer.write(np.full((90, 160, 3), 40 * i, np.uint8))
    writer.release()
    sheet = inputs / "sheet.mp4"
    _sheet_video(sheet)
    camera640 = inputs / "cam640.yml"
    CameraModel.from_fov(640, 480, 600.0).to_yaml(camera640)
    shots = inputs / "shots"
    shots.mkdir()
    ro = tmp_path / "ro"
    result = run_main(["-q", "demo", "--frames", "2", "--out", str(ro / "run")])
    assert result.code == 0, result.describe()
    out = str(ro)
    commands = {
        "demo": ["demo", "--frames", "2", "--out", out],
        "replay": ["replay", str(video), "--camera", str(CAMERA), "--out", out],
        "live": ["live", "--device", "synthetic", "--width", "320", "--height", "180", "--max-frames", "2",
                 "--out", out],
        "export --out": ["export", str(ro / "run"), "--out", out],
        "export RUN_DIR": ["export", str(ro / "run")],
        "map": ["map", str(sheet), "--camera", str(camera640), "--dictionary", "DICT_4X4_50", "--marker-length",
                "0.05", "--out", str(ro / "layout.yml")],
        "markers": ["markers", "--ids", "0-1", "--size-mm", "40", "--out", out],
        "calibrate": ["calibrate", str(shots), "--charuco", "5x7", "--square-m", "0.04", "--marker-m", "0.02",
                      "--dictionary", "DICT_4X4_50", "--out", str(ro / "camera.yml")],
    }  # fmt: skip
    return inputs, ro, commands


def _expected(name: str, ro: Path) -> tuple[str, ...]:
    """The line's possible starts: the lock that cannot be created, or (the commands whose --out is a file, on a
    real read-only mount, which access(2) sees) the folder found not writable before."""
    folder = ro / "run" if name == "export RUN_DIR" else ro
    option = "RUN_DIR" if name == "export RUN_DIR" else "--out"
    lock = f"ar-anchor: error: {option} {folder}: cannot create .ar-anchor.lock (Read-only file system)"
    out_file = {"map": "layout.yml", "calibrate": "camera.yml"}.get(name)
    if out_file is None:
        return (lock,)
    return lock, f"ar-anchor: error: --out {ro / out_file}: folder {ro} is not writable"


def _not_warnings(stderr: str) -> list[str]:
    """The lines of ``stderr`` but the warnings (the replay's camera scaled to the video's size)."""
    return [line for line in stderr.splitlines() if not line.startswith("ar-anchor: WARNING:")]


def _inside(path: object, folder: Path) -> bool:
    try:
        return Path(os.path.abspath(os.fspath(path))).is_relative_to(folder)
    except TypeError:
        return False  # a file descriptor


@pytest.fixture
def read_only(monkeypatch):
    """Make ``folder`` read-only for this process: creating, writing, linking, renaming or removing anything in it
    fails with EROFS (as on a read-only mount, where even removing a missing file does)."""

    def make(folder: Path) -> None:
        folder = Path(os.path.abspath(folder))

        def refuse(path: object) -> None:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))

        def guard(original, *positions):
            def guarded(*args, **kwargs):
                for position in positions:
                    if len(args) > position and _inside(args[position], folder):
                        refuse(args[position])
                return original(*args, **kwargs)

            return guarded

        def guard_open(original):
            def guarded(file, mode="r", *args, **kwargs):
                if any(ch in mode for ch in "wax+") and _inside(file, folder):
                    refuse(file)
                return original(file, mode, *args, **kwargs)

            return guarded

        def mkdir(path, *args, **kwargs):
            if _inside(path, folder):
                if os.path.lexists(path):
                    raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), os.fspath(path))
                refuse(path)
            return original_mkdir(path, *args, **kwargs)

        original_mkdir = os.mkdir
        monkeypatch.setattr(os, "mkdir", mkdir)
        for name in ("link", "replace", "rename", "symlink"):
            monkeypatch.setattr(os, name, guard(getattr(os, name), 0, 1))
        for name in ("unlink", "remove", "rmdir", "truncate"):
            monkeypatch.setattr(os, name, guard(getattr(os, name), 0))
        monkeypatch.setattr(pathlib.Path, "unlink", guard(pathlib.Path.unlink, 0))
        monkeypatch.setattr(pathlib.Path, "touch", guard(pathlib.Path.touch, 0))
        monkeypatch.setattr(builtins, "open", guard_open(builtins.open))
        monkeypatch.setattr(io, "open", guard_open(io.open))
        monkeypatch.setattr(os, "open", _guard_os_open(os.open, folder, refuse))

    return make


def _guard_os_open(original, folder: Path, refuse):
    def guarded(path, flags, *args, **kwargs):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC) and _inside(path, folder):
            refuse(path)
        return original(path, flags, *args, **kwargs)

    return guarded


@pytest.mark.parametrize(
    "name",
    [
        "demo",
        "replay",
        # (slow: the synthetic camera renders its clip when it opens, before the lock is tried)
        pytest.param("live", marks=pytest.mark.slow),
        "export --out",
        "export RUN_DIR",
        "map",
        "markers",
        "calibrate",
    ],
)
def test_every_command_on_a_read_only_out_is_one_line_naming_it(tmp_path, read_only, name):
    _, ro, commands = _inputs(tmp_path)
    before = sorted(p.relative_to(ro).as_posix() for p in ro.rglob("*"))
    read_only(ro)
    result = run_main(["-q", *commands[name]])
    assert_clean_exit(result)
    assert result.code == 1, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and _not_warnings(result.stderr) == lines, result.describe()
    assert lines[0].startswith(_expected(name, ro)), result.describe()
    assert sorted(p.relative_to(ro).as_posix() for p in ro.rglob("*")) == before


_IN_NAMESPACE = """
import json, subprocess, sys
from tests.helpers import run_main
ro, commands = sys.argv[1], json.loads(sys.argv[2])
subprocess.run(["mount", "--bind", "-o", "ro", ro, ro], check=True)
results = {}
for name, argv in commands.items():
    result = run_main(["-q", *argv])
    results[name] = [result.code, result.stdout, result.stderr]
print(json.dumps(results))
"""


def test_on_a_real_read_only_mount_every_command_is_one_line(tmp_path):
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode:
        pytest.skip("no user and mount namespaces here (unshare -rm)")
    _, ro, commands = _inputs(tmp_path)
    del commands["live"]  # (slow to open; the in-process test has it)
    done = subprocess.run(
        ["unshare", "-rm", sys.executable, "-c", _IN_NAMESPACE, str(ro), json.dumps(commands)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    if done.returncode and "mount" in done.stderr:
        pytest.skip(f"cannot bind-mount read-only here: {done.stderr.strip()[-200:]}")
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout.strip().splitlines()[-1])
    for name, (code, stdout, stderr) in results.items():
        assert code == 1, (name, stdout, stderr)
        assert "internal error" not in stderr and "Traceback" not in stderr, (name, stderr)
        lines = error_lines(stderr)
        assert len(lines) == 1 and _not_warnings(stderr) == lines, (name, stderr)
        assert lines[0].startswith(_expected(name, ro)), (name, lines[0])
