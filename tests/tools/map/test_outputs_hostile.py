"""``ar-anchor map``'s outputs under the rule every writing command follows (issue 34): one run per output folder
(the lock replay takes), a file map did not write never replaced, each refusal one line naming the option that
gave the path."""

from __future__ import annotations

import os
import subprocess

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.run.paths import LOCK_NAME
from tests.helpers import assert_clean_exit, error_lines, run_main


def _sheet_video(path, count: int = 4) -> None:
    """``count`` frontal views of three DICT_4X4_50 markers (ids 0, 1, 2), each moved a little, as an MP4."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 5, (640, 480))
    try:
        for index in range(count):
            image = np.full((480, 640), 255, np.uint8)
            dy, dx = 150 + 9 * index, 6 * index
            for k, x in enumerate((100, 250, 400)):
                image[dy : dy + 120, x + dx : x + dx + 120] = cv2.aruco.generateImageMarker(dictionary, k, 120)
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    finally:
        writer.release()


@pytest.fixture
def scene(tmp_path):
    camera = tmp_path / "camera.yml"
    CameraModel.from_fov(640, 480, 600.0).to_yaml(camera)
    video = tmp_path / "sheet.mp4"
    _sheet_video(video)
    return video, ["--camera", str(camera), "--dictionary", "DICT_4X4_50", "--marker-length", "0.05"]


def _one_error(result) -> str:
    assert_clean_exit(result)
    assert result.code == 2, result.describe()
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and result.stderr.strip() == lines[0], result.describe()
    return lines[0]


def test_rrd_naming_the_input_video_is_refused_naming_rrd(tmp_path, scene):
    # given --rrd on the video being mapped
    video, options = scene
    before = video.read_bytes()
    result = run_main(
        ["-q", "map", str(video), *options, "--out", str(tmp_path / "m" / "layout.yml"), "--rrd", str(video)]
    )
    # then the line blames --rrd (was: --out), the video is untouched and nothing is created
    assert _one_error(result) == (
        f"ar-anchor: error: --rrd {video}: is the input VIDEO {video}; refusing to overwrite it (write somewhere else)"
    )
    assert video.read_bytes() == before and not (tmp_path / "m").exists()


def test_rrd_naming_a_file_map_did_not_write_is_refused_naming_rrd(tmp_path, scene):
    video, options = scene
    mine = tmp_path / "notes.rrd"
    mine.write_bytes(b"the user's")
    result = run_main(
        ["-q", "map", str(video), *options, "--out", str(tmp_path / "m" / "layout.yml"), "--rrd", str(mine)]
    )
    assert _one_error(result) == (
        f"ar-anchor: error: --rrd {mine}: would overwrite {mine} (its recording), which ar-anchor map did not write: "
        "move that file or give another --rrd"
    )
    assert mine.read_bytes() == b"the user's"


def test_a_second_map_on_a_busy_out_folder_is_refused_and_the_lock_is_held_for_the_whole_run(
    tmp_path, scene, monkeypatch
):
    video, options = scene
    out = tmp_path / "m"
    out.mkdir()
    # given another live process holding the folder's lock: refused, nothing written, its lock kept
    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        (out / LOCK_NAME).write_text(f"{sleeper.pid} {os.uname().nodename}\n")
        line = _one_error(run_main(["-q", "map", str(video), *options, "--out", str(out / "layout.yml")]))
        assert line == (
            f"ar-anchor: error: --out {out}: another run (pid {sleeper.pid} on {os.uname().nodename}) is writing into "
            f"it; give another --out (or remove {LOCK_NAME} if that run is gone)"
        )
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    finally:
        sleeper.kill()
        sleeper.wait()
    (out / LOCK_NAME).unlink()
    # and a map run holds the lock from before it reads its first frame until it is done (also in --rrd's folder)
    import ar_anchor.tools.map.command as command

    seen = []
    observe = command.observe_sources

    def observing(*args, **kwargs):
        seen.append(((out / LOCK_NAME).exists(), (tmp_path / "r" / LOCK_NAME).exists()))
        return observe(*args, **kwargs)

    monkeypatch.setattr(command, "observe_sources", observing)
    rrd = tmp_path / "r" / "map.rrd"
    result = run_main(["-q", "map", str(video), *options, "--out", str(out / "layout.yml"), "--rrd", str(rrd)])
    assert result.code == 0, result.describe()
    assert seen == [(True, True)]
    assert not (out / LOCK_NAME).exists() and not (rrd.parent / LOCK_NAME).exists() and rrd.is_file()


def test_a_failed_map_leaves_no_folder_and_no_lock(tmp_path, scene):
    # given an input that holds no marker pair, into folders that do not exist yet
    _video, options = scene
    blank = tmp_path / "blank"
    blank.mkdir()
    cv2.imwrite(str(blank / "0.png"), np.full((480, 640), 255, np.uint8))
    out = tmp_path / "new" / "deeper" / "layout.yml"
    rrd = tmp_path / "other" / "map.rrd"
    result = run_main(["-q", "map", str(blank), *options, "--out", str(out), "--rrd", str(rrd)])
    assert result.code == 2, result.describe()
    assert not (tmp_path / "new").exists() and not (tmp_path / "other").exists()


def test_a_layout_that_cannot_be_written_is_one_line_naming_it(tmp_path, scene, monkeypatch):
    # given a disk that fills as the TOML layout is put in place
    video, options = scene
    out = tmp_path / "m" / "layout.yml"
    replace = os.replace

    def full(source, target, *args, **kwargs):
        if str(target).endswith("layout.toml"):
            raise OSError(28, "No space left on device", str(target))
        return replace(source, target, *args, **kwargs)

    monkeypatch.setattr(os, "replace", full)
    result = run_main(["-q", "map", str(video), *options, "--out", str(out)])
    # then one line naming that file, exit 1, no temporary file, no lock and no recording left
    assert_clean_exit(result)
    assert result.code == 1, result.describe()
    assert error_lines(result.stderr) == [
        f"ar-anchor: error: --out {out.with_suffix('.toml')}: cannot write (No space left on device)"
    ]
    assert sorted(p.name for p in out.parent.iterdir()) == ["layout.yml"]
