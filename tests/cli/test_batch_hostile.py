"""``ar-anchor batch`` against hostile input (issue 34, the third ring): names from file stems stay inside
``--out``, the user's files are never replaced, one batch per ``--out``, file names escaped in every line,
manifests checked up front, FIFOs and empty globs named as such, ``--out`` never inside an image source, and
``--ray`` to a cluster that is not there ends within seconds in one line. Real 4-frame clips made here."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import cv2
import pytest

from ar_anchor.cli.recordings import RUNS_FILE, find_recordings, read_manifest
from ar_anchor.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE
from tests.helpers import assert_clean_exit, run_main

FRAMES = 4
NOT_UTF8 = b"\xff".decode("utf-8", "surrogateescape")


@pytest.fixture(scope="module")
def media(tmp_path_factory) -> Path:
    """A 4-frame 160x120 H.264 clip of the demo scene, its camera file, and its frames as a PNG folder."""
    from ar_anchor.bench.speed.scenes import encode_scene
    from ar_anchor.camera import CameraModel
    from ar_anchor.config import demo_config
    from ar_anchor.synthetic import Trajectory, demo_scene

    root = tmp_path_factory.mktemp("batch_hostile")
    camera = CameraModel.from_fov(160, 120, 125.0)
    trajectory = Trajectory(kind="handheld", near_m=0.35, far_m=1.0, look_at=(-0.01, 0, 0), seed=0, duration_s=1)
    scene = demo_scene(demo_config(), camera, frames=FRAMES, trajectory=trajectory, fps=25.0, seed=0)
    encode_scene(root / "clip.mp4", scene)
    camera.to_yaml(root / "camera.yml")
    (root / "shots").mkdir()
    capture = cv2.VideoCapture(str(root / "clip.mp4"))
    for index in range(FRAMES):
        ok, image = capture.read()
        assert ok
        cv2.imwrite(str(root / "shots" / f"{index:03d}.png"), image)
    capture.release()
    return root


def _clip(media: Path, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes((media / "clip.mp4").read_bytes())
    return path


def _batch(*args: str, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "ar_anchor", "batch", *args]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    return subprocess.run(command, capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout, check=False)


def _clean(result: subprocess.CompletedProcess[str], code: int) -> None:
    described = f"exit {result.returncode}\nstdout: {result.stdout!r}\nstderr: {result.stderr!r}"
    assert result.returncode == code, described
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr, described


def _one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ar-anchor: error: "), stderr
    return lines[0]


def _rows(out: Path) -> dict[str, dict]:
    import pyarrow.parquet as pq

    return {row["name"]: row for row in pq.read_table(out / RUNS_FILE).to_pylist()}


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ============================================================================ 1. names stay inside --out


def test_names_from_stems_are_made_safe_like_manifest_names(tmp_path):
    # given files whose stems are .., ., a control character, a byte that is not UTF-8, and runs.parquet
    names = ["...mp4", "..mp4", "a\nb\x1b[2J.mp4", f"c{NOT_UTF8}.mp4", "runs.parquet.mp4"]
    for name in names:
        (tmp_path / name).write_bytes(b"x")
    # when
    found = find_recordings([str(tmp_path / name) for name in names], None)
    # then: each is one folder name inside --out, none is a file the batch writes there
    assert [r.name for r in found] == ["recording", "recording_2", "a_b_[2J", "c_", "runs.parquet_2"]
    # and a manifest's rows without a name get the same names
    (tmp_path / "m.csv").write_text("source\n...mp4\n..mp4\n")
    assert [r.name for r in read_manifest(tmp_path / "m.csv")] == ["recording", "recording_2"]


def test_a_stem_of_dot_dot_writes_inside_out_and_the_earlier_run_beside_it_is_kept(media, tmp_path):
    # given an earlier run in runs/ (as `replay --out runs` left it) and clips named ...mp4 and ..mp4
    earlier = tmp_path / "runs"
    # (in-process: only the run's files are the given)
    replay = run_main(
        ["-q", "replay", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"), "--out", str(earlier)]
    )
    assert replay.code == 0, replay.describe()
    before = _tree(earlier)
    _clip(media, tmp_path / "src" / "...mp4")
    _clip(media, tmp_path / "src" / "..mp4")
    (tmp_path / "src" / "m.csv").write_text("source\n...mp4\n")
    out = earlier / "inner"
    # when: the two as SOURCEs, then through a manifest row
    result = _batch("-q", "src/...mp4", "src/..mp4", "--camera", str(media / "camera.yml"), "--out", str(out),
                    cwd=tmp_path)  # fmt: skip
    from_manifest = _batch("-q", "--manifest", "src/m.csv", "--camera", str(media / "camera.yml"), "--out",
                           str(tmp_path / "from_manifest"), cwd=tmp_path)  # fmt: skip
    # then: each recording has its own folder inside --out; the run beside --out is untouched
    _clean(result, EXIT_OK)
    _clean(from_manifest, EXIT_OK)
    assert sorted(p.name for p in out.iterdir()) == ["recording", "recording_2", RUNS_FILE]
    assert {row["status"] for row in _rows(out).values()} == {"ok"}
    assert (out / "recording" / "poses.csv").is_file() and (out / "recording_2" / "poses.csv").is_file()
    assert {k: v for k, v in _tree(earlier).items() if not k.startswith("inner")} == before
    assert (tmp_path / "from_manifest" / "recording" / "poses.csv").is_file()


# ============================================================================ 2. the user's files are kept


def test_the_users_own_runs_table_is_never_replaced(media, tmp_path):
    # given --out holding the user's own runs.parquet
    out = tmp_path / "out"
    out.mkdir()
    (out / RUNS_FILE).write_bytes(b"my own table")
    # when
    result = run_main(
        ["-q", "batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"), "--out", str(out)]
    )
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    line = _one_error_line(result.stderr)
    assert "holds runs.parquet, which no ar-anchor batch wrote" in line
    assert (out / RUNS_FILE).read_bytes() == b"my own table"
    assert sorted(p.name for p in out.iterdir()) == [RUNS_FILE]


def test_a_recording_folder_holding_the_users_files_is_never_written(media, tmp_path):
    # given --out/clip holding the user's own batch.json and poses.csv (no run's summary.json)
    folder = tmp_path / "out" / "clip"
    folder.mkdir(parents=True)
    (folder / "batch.json").write_text("mine")
    (folder / "poses.csv").write_text("mine")
    # when
    result = run_main(["-q", "batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
                       "--out", str(tmp_path / "out")])  # fmt: skip
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    assert "holds poses.csv, batch.json, which no ar-anchor run wrote" in _one_error_line(result.stderr)
    assert (folder / "batch.json").read_text() == "mine" and (folder / "poses.csv").read_text() == "mine"


def test_a_recording_folder_holding_another_commands_run_is_never_cleared(media, tmp_path):
    # given --out/clip holding a live session: its summary.json and its raw recording, the user's only copy
    folder = tmp_path / "out" / "clip"
    demo = run_main(["-q", "demo", "--frames", "2", "--out", str(folder)])  # (in-process: its files are the given)
    assert demo.code == 0, demo.describe()
    summary = json.loads((folder / "summary.json").read_text())
    (folder / "summary.json").write_text(json.dumps({**summary, "command": "live"}))
    (folder / "raw.mkv").write_bytes(b"the only copy")
    before = _tree(folder)
    # when a batch would replay clip.mp4 into it
    camera = str(media / "camera.yml")
    result = run_main(["-q", "batch", str(media / "clip.mp4"), "--camera", camera, "--out", str(tmp_path / "out")])
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    line = _one_error_line(result.stderr)
    assert f"--out {folder}: holds a run of `ar-anchor live` (its summary.json) that no batch wrote" in line, line
    assert _tree(folder) == before


# ============================================================================ 3. one batch per --out


def test_a_second_batch_on_a_busy_out_is_refused_and_the_lock_is_gone_after_a_batch(media, tmp_path):
    # given --out locked by a live process of this host
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / ".ar-anchor.lock").write_text(f"{holder.pid} {socket.gethostname()}\n")
        # when
        result = run_main(["-q", "batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
                           "--out", str(out)])  # fmt: skip
    finally:
        holder.kill()
        holder.wait()
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    assert f"another run (pid {holder.pid}" in _one_error_line(result.stderr)
    assert sorted(p.name for p in out.iterdir()) == [".ar-anchor.lock"]
    # and once that process is gone, a batch runs and leaves no lock behind
    done = _batch("-q", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"), "--out", str(out))
    _clean(done, EXIT_OK)
    assert not (out / ".ar-anchor.lock").exists() and _rows(out)["clip"]["status"] == "ok"


def test_two_batches_on_one_out_the_second_is_refused_and_the_first_completes(media, tmp_path):
    # given a batch of five clips under way
    clips = [str(_clip(media, tmp_path / f"c{k}.mp4")) for k in range(5)]
    out = tmp_path / "out"
    command = [sys.executable, "-m", "ar_anchor", "-q", "batch", *clips, "--camera", str(media / "camera.yml"),
               "--out", str(out), "--jobs", "1"]  # fmt: skip
    first = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (out / ".ar-anchor.lock").exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    # when a second batch is started on the same --out (the first held there meanwhile: no race)
    first.send_signal(signal.SIGSTOP)
    try:
        second = _batch("-q", clips[0], "--camera", str(media / "camera.yml"), "--out", str(out))
    finally:
        first.send_signal(signal.SIGCONT)
    _, stderr = first.communicate(timeout=120)
    # then: the second is refused; the first replays each recording once, all ok
    _clean(second, EXIT_USAGE)
    assert "another run (pid" in _one_error_line(second.stderr)
    assert first.returncode == 0, stderr
    assert [row["status"] for row in _rows(out).values()] == ["ok"] * 5
    assert not (out / ".ar-anchor.lock").exists()


# ============================================================================ 4. names escaped in every line


def test_worker_lines_escape_file_names_and_bidi_controls(media, tmp_path):
    # given an image folder holding a damaged image whose name forges an error line, and a broken video whose
    # name holds a right-to-left override
    shots = tmp_path / "shots"
    shots.mkdir()
    for image in (media / "shots").iterdir():
        (shots / image.name).write_bytes(image.read_bytes())
    (shots / "001x\nar-anchor: error: forged\x1b[2J.png").write_bytes(b"not a png")
    (tmp_path / "bad\u202egpj.mp4").write_bytes((media / "clip.mp4").read_bytes()[:600])
    # when
    out = tmp_path / "out\x1b[31m\nx"  # (and --out too: the summary and error lines name the table)
    result = _batch(str(shots), str(tmp_path / "bad\u202egpj.mp4"), "--camera", str(media / "camera.yml"),
                    "--out", str(out))  # fmt: skip
    # then: the broken video fails its row; every line is one line, escaped
    _clean(result, EXIT_FAILURE)
    assert "\x1b" not in result.stderr + result.stdout and "\u202e" not in result.stderr + result.stdout
    lines = result.stdout.strip().splitlines()
    # the table (header, rule, a line per recording, legend), the totals, the outputs
    assert len(lines) == 2 + 2 + 2 + 1 + 1
    assert all("out\\x1b[31m\\nx" in line for line in lines if "/" in line)  # (the folders, the table's path)
    assert not any("forged" in line for line in result.stderr.splitlines() if line.startswith("ar-anchor: error:"))
    assert "001x\\nar-anchor: error: forged\\x1b[2J.png" in result.stderr
    assert "bad\\u202egpj" in result.stderr


# ============================================================================ 5, 6. the table is always written


def test_a_manifest_row_named_runs_parquet_gets_its_own_folder_and_the_table_is_written(media, tmp_path):
    # given a manifest row named runs.parquet
    _clip(media, tmp_path / "clip.mp4")
    (tmp_path / "m.csv").write_text("source,name\nclip.mp4,runs.parquet\n")
    # when
    result = _batch("-q", "--manifest", str(tmp_path / "m.csv"), "--camera", str(media / "camera.yml"),
                    "--out", str(tmp_path / "out"))  # fmt: skip
    # then
    _clean(result, EXIT_OK)
    assert (tmp_path / "out" / RUNS_FILE).is_file()
    assert _rows(tmp_path / "out")["runs.parquet_2"]["status"] == "ok"
    assert (tmp_path / "out" / "runs.parquet_2" / "poses.csv").is_file()


def test_a_file_name_that_is_not_utf8_fails_its_row_and_the_table_is_written_every_time(media, tmp_path):
    # given a folder of a good clip and one whose name holds a byte that is not UTF-8
    _clip(media, tmp_path / "clips" / "good.mp4")
    _clip(media, Path(os.fsdecode(bytes(tmp_path / "clips") + b"/bad\xff.mp4")))
    for attempt in range(2):
        # when (twice: the failed one is tried again)
        result = _batch("-q", str(tmp_path / "clips"), "--camera", str(media / "camera.yml"), "--out",
                        str(tmp_path / "out"))  # fmt: skip
        # then
        _clean(result, EXIT_FAILURE)
        rows = _rows(tmp_path / "out")
        assert rows["good"]["status"] == ("ok" if attempt == 0 else "skipped"), rows
        assert rows["bad_"]["status"] == "failed" and rows["bad_"]["source"].endswith("bad\\udcff.mp4")
        assert "1 of 2 recording(s) failed: bad_" in result.stderr


# ============================================================================ 7-9. up-front checks


@pytest.mark.parametrize(
    "row, message",
    [
        ("clip.mp4,nocam.yml,", "line 2: camera {d}/nocam.yml: no such file"),
        ("clip.mp4,,none.toml", "line 2: config {d}/none.toml: no such file"),
        ("clip.mp4,pipe,", "line 2: camera {d}/pipe: is a named pipe (FIFO), not a regular file"),
    ],
)
def test_a_manifests_missing_camera_or_config_is_exit_2_before_anything_runs(media, tmp_path, row, message):
    # given a manifest whose row names a camera or config file that is not there (or a FIFO)
    _clip(media, tmp_path / "clip.mp4")
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "m.csv").write_text(f"source,camera,config\n{row}\n")
    # when (-q: the reason is still said)
    result = run_main(["-q", "batch", "--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path / "out")])
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    line = _one_error_line(result.stderr)
    assert f"--manifest {tmp_path / 'm.csv'}: {message.format(d=tmp_path)}" in line, line
    assert not (tmp_path / "out").exists()


def test_a_recording_without_any_camera_file_is_exit_2_before_anything_runs(media, tmp_path):
    _clip(media, tmp_path / "clip.mp4")
    result = run_main(["-q", "batch", str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "out")])
    assert_clean_exit(result, {EXIT_USAGE})
    assert "clip.mp4: no camera file: give --camera FILE" in _one_error_line(result.stderr)
    assert not (tmp_path / "out").exists()


def test_a_fifo_source_is_named_as_such(tmp_path):
    # given a FIFO as SOURCE, and as a manifest's source
    os.mkfifo(tmp_path / "pipe.mp4")
    (tmp_path / "m.csv").write_text("source\npipe.mp4\n")
    for argv in (["pipe.mp4"], ["--manifest", "m.csv"]):
        # when
        result = run_main(["batch", *[str(tmp_path / a) if "." in a else a for a in argv], "--out",
                           str(tmp_path / "out")])  # fmt: skip
        # then: never opened (it would block), said what it is
        assert_clean_exit(result, {EXIT_USAGE})
        line = _one_error_line(result.stderr)
        assert "pipe.mp4: is a named pipe (FIFO), not a video file, an image folder or a glob" in line, line
        assert not (tmp_path / "out").exists()


def test_a_glob_that_matches_nothing_says_so(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    nothing = run_main(["batch", str(tmp_path / "*.mp4"), "--out", str(tmp_path / "out")])
    assert_clean_exit(nothing, {EXIT_USAGE})
    assert _one_error_line(nothing.stderr).endswith("*.mp4: no file matches this pattern")
    no_media = run_main(["batch", str(tmp_path / "*.txt"), "--out", str(tmp_path / "out")])
    assert _one_error_line(no_media.stderr).endswith("*.txt: the pattern matches 1 file(s), none a video or an image")


@pytest.mark.parametrize(
    "pattern, message",
    [
        ("none/*.mp4", "none/*.mp4: no file matches this pattern"),
        ("clips/*.mp4", "clips/*.mp4: the pattern matches 1 file(s), none an image (a glob in a manifest row is one"),
    ],
)
def test_a_manifest_glob_that_matches_no_image_says_so_before_anything_runs(tmp_path, pattern, message):
    # given a manifest row whose glob matches nothing, or only a video (a row's glob is one image sequence)
    (tmp_path / "clips").mkdir()
    (tmp_path / "clips" / "a.mp4").write_bytes(b"x")
    (tmp_path / "camera.yml").write_text("x")
    (tmp_path / "m.csv").write_text(f"source,camera\n{pattern},camera.yml\n")
    # when
    result = run_main(["-q", "batch", "--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path / "out")])
    # then: no line about images that are not there; nothing written
    assert_clean_exit(result, {EXIT_USAGE})
    line = _one_error_line(result.stderr)
    assert f"--manifest {tmp_path / 'm.csv'}: line 2: {tmp_path}/{message}" in line, line
    assert not (tmp_path / "out").exists()


# ============================================================================ 10. --out inside an image source


@pytest.mark.parametrize(
    "source, out, message",
    [
        ("shots", ".", "recording shots would be written into {root}/shots, its own image folder"),
        ("shots", "shots", "is the image folder shots of recording shots"),
        ("shots", "shots/runs", "is inside the image folder shots of recording shots"),
        ("shots/*.png", ".", "recording shots would be written into {root}/shots, its own image folder"),
    ],
)
def test_an_out_in_its_own_image_folder_is_refused(media, tmp_path, monkeypatch, source, out, message):
    # given an image folder in the current folder
    (tmp_path / "shots").mkdir()
    for image in (media / "shots").iterdir():
        (tmp_path / "shots" / image.name).write_bytes(image.read_bytes())
    before = _tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    # when
    result = run_main(["-q", "batch", source, "--camera", str(media / "camera.yml"), "--out", out])
    # then: nothing written into the images' folder
    assert_clean_exit(result, {EXIT_USAGE})
    assert message.format(root=tmp_path) in _one_error_line(result.stderr), result.stderr
    assert _tree(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["shots"]


def test_an_image_folder_replayed_twice_is_skipped_the_second_time(media, tmp_path):
    # given an image folder with another file beside its images, replayed once
    (tmp_path / "shots").mkdir()
    for image in (media / "shots").iterdir():
        (tmp_path / "shots" / image.name).write_bytes(image.read_bytes())
    args = (str(tmp_path / "shots"), "--camera", str(media / "camera.yml"), "--out", str(tmp_path / "out"))
    _clean(_batch("-q", *args), EXIT_OK)
    # when a note is added beside the images (not a frame), and the batch runs again
    (tmp_path / "shots" / "notes.txt").write_text("x")
    again = _batch(*args)
    # then
    _clean(again, EXIT_OK)
    assert "0 replayed, 1 skipped" in again.stdout, again.stdout


# ============================================================================ 11. --ray to no cluster


def _closed_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as probe:
        return probe.getsockname()[1]


@pytest.mark.parametrize("scheme", ["", "ray://"])
def test_ray_at_an_address_where_nothing_listens_ends_at_once_in_one_line(media, tmp_path, scheme):
    pytest.importorskip("ray")
    address = f"{scheme}127.0.0.1:{_closed_port()}"
    started = time.monotonic()
    result = _batch(str(media / "clip.mp4"), "--camera", str(media / "camera.yml"), "--out", str(tmp_path / "out"),
                    "--ray", address, timeout=60)  # fmt: skip
    _clean(result, EXIT_USAGE)
    assert time.monotonic() - started < 30
    line = _one_error_line(result.stderr)  # (no Ray log line)
    assert f"--ray {address}: cannot reach 127.0.0.1:" in line and "nothing listens there" in line, line
    assert not (tmp_path / "out").exists()


def test_ray_auto_without_a_cluster_is_exit_2_in_one_line(media, tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    from ray._private.services import canonicalize_bootstrap_address

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    try:
        canonicalize_bootstrap_address("auto")
        pytest.skip("a Ray cluster runs on this machine")
    except ConnectionError:
        pass
    assert not ray.is_initialized()
    result = run_main(["batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
                       "--out", str(tmp_path / "out"), "--ray", "auto"])  # fmt: skip
    assert_clean_exit(result, {EXIT_USAGE})
    assert "--ray auto: no running Ray cluster found on this machine" in _one_error_line(result.stderr)
    assert not (tmp_path / "out").exists()


def _fake_ray(init) -> types.ModuleType:
    module = types.ModuleType("ray")
    module.is_initialized = lambda: False  # type: ignore[attr-defined]
    module.init = init  # type: ignore[attr-defined]
    module.shutdown = lambda *a, **k: None  # type: ignore[attr-defined]
    return module


def test_ray_that_answers_but_never_joins_is_bounded_and_its_lines_are_held(media, tmp_path, monkeypatch, capfd):
    # given an address where something listens (the probe passes) and a ray.init that prints and never returns
    from ar_anchor.cli import batch_task

    release = threading.Event()

    def init(**_kwargs):
        os.write(2, b"[ray C++] Failed to connect to GCS\n")
        release.wait(30)

    monkeypatch.setitem(sys.modules, "ray", _fake_ray(init))
    monkeypatch.setattr(batch_task, "RAY_CONNECT_TIMEOUT_S", 0.5)
    with socket.create_server(("127.0.0.1", 0)) as server:
        address = f"127.0.0.1:{server.getsockname()[1]}"
        started = time.monotonic()
        # when
        try:
            result = run_main(["batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
                               "--out", str(tmp_path / "out"), "--ray", address])  # fmt: skip
        finally:
            release.set()
    # then: one line within the bound; Ray's own line went to the debug log, not to the terminal
    assert_clean_exit(result, {EXIT_USAGE})
    assert time.monotonic() - started < 10
    assert f"--ray {address}: the address answers but no Ray cluster was joined within 0.5 s" in _one_error_line(
        result.stderr
    )
    assert "Failed to connect to GCS" not in capfd.readouterr().err
    assert not (tmp_path / "out").exists()


def test_ray_init_that_fails_is_one_line(media, tmp_path, monkeypatch):
    def init(**_kwargs):
        raise ConnectionError("Could not connect\nsecond line")

    monkeypatch.setitem(sys.modules, "ray", _fake_ray(init))
    with socket.create_server(("127.0.0.1", 0)) as server:
        address = f"ray://127.0.0.1:{server.getsockname()[1]}"
        result = run_main(["batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
                           "--out", str(tmp_path / "out"), "--ray", address])  # fmt: skip
    assert_clean_exit(result, {EXIT_USAGE})
    line = _one_error_line(result.stderr)
    assert line.endswith(f"--ray {address}: cannot join the Ray cluster (ConnectionError: Could not connect)"), line


def test_sigterm_while_joining_a_cluster_ends_the_batch_at_once(media, tmp_path):
    # given a batch whose ray.init never returns (a stand-in ray module, which says when it is entered), joining
    # a listening address
    fake = tmp_path / "fake"
    fake.mkdir()
    entered = tmp_path / "init-entered"
    (fake / "ray.py").write_text(
        "import pathlib, time\ndef is_initialized():\n    return False\n"
        f"def init(**kwargs):\n    pathlib.Path({str(entered)!r}).touch()\n    time.sleep(600)\n"
        "def shutdown(*a, **k):\n    pass\n"
    )
    with socket.create_server(("127.0.0.1", 0)) as server:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(Path(__file__).resolve().parents[2])])}
        process = subprocess.Popen(
            [sys.executable, "-m", "ar_anchor", "batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"),
             "--out", str(tmp_path / "out"), "--ray", f"127.0.0.1:{server.getsockname()[1]}"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while not entered.exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if not entered.exists():  # (the batch never reached the join: end it, and say what it printed)
            process.kill()
            pytest.fail(f"ray.init was never entered: {process.communicate(timeout=30)[1]}")
        time.sleep(0.2)  # (inside the never-ending join)
        # when
        sent = time.monotonic()
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=30)
    # then
    assert time.monotonic() - sent < 5, stderr
    assert process.returncode == 130 and "Traceback" not in stderr, stderr
    assert stderr.strip().startswith("ar-anchor: interrupted"), stderr


def test_the_users_own_runs_csv_is_never_replaced_without_pyarrow(media, tmp_path, monkeypatch):
    # given no pyarrow and a user's runs.csv that is not a table of ours
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs.csv").write_text("a,b\n1,2\n")
    # when
    result = run_main(
        ["-q", "batch", str(media / "clip.mp4"), "--camera", str(media / "camera.yml"), "--out", str(out)]
    )
    # then
    assert_clean_exit(result, {EXIT_USAGE})
    assert "holds runs.csv, which no ar-anchor batch wrote" in _one_error_line(result.stderr)
    assert list(csv.reader((out / "runs.csv").open())) == [["a", "b"], ["1", "2"]]
    assert sorted(p.name for p in out.iterdir()) == ["runs.csv"]


def test_a_joined_cluster_keeps_the_thread_that_joined_it_until_ray_shuts_down(monkeypatch):
    # given a stand-in Ray that joins at once (what ray.init starts is bound to the thread that called it)
    from ar_anchor.cli.batch_task import ray_session

    seen: dict[str, object] = {}

    def init(**kwargs):
        seen["thread"], seen["address"] = threading.current_thread(), kwargs["address"]

    fake = _fake_ray(init)
    fake.shutdown = lambda *a, **k: seen.setdefault("shutdown_while_alive", seen["thread"].is_alive())  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "ray", fake)
    with socket.create_server(("127.0.0.1", 0)) as server:
        address = f"127.0.0.1:{server.getsockname()[1]}"
        # when
        with ray_session(address, None) as ray:
            # then: joined, on a thread of its own that is still there
            assert ray is fake and seen["address"] == address
            thread = seen["thread"]
            assert thread is not threading.current_thread() and thread.is_alive()
    # and Ray is shut down while that thread lives, which then ends
    assert seen["shutdown_while_alive"] is True
    thread.join(5)
    assert not thread.is_alive()


def test_ray_alone_starts_a_local_ray_even_with_ray_address_set(monkeypatch, caplog):
    # given RAY_ADDRESS in the environment (ray.init would join it, and refuse num_cpus: was an internal error)
    from ar_anchor.cli.batch_task import ray_session

    seen: dict[str, object] = {}

    def init(**kwargs):
        seen["kwargs"], seen["env"] = kwargs, os.environ.get("RAY_ADDRESS")

    monkeypatch.setitem(sys.modules, "ray", _fake_ray(init))
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    # when
    with caplog.at_level("WARNING", logger="ar_anchor"), ray_session("", 2):
        pass
    # then: a local Ray of 2 CPUs, RAY_ADDRESS set aside meanwhile (and said so), then put back
    assert seen["kwargs"]["num_cpus"] == 2 and "address" not in seen["kwargs"] and seen["env"] is None
    assert os.environ["RAY_ADDRESS"] == "127.0.0.1:1"
    assert "RAY_ADDRESS=127.0.0.1:1 ignored: --ray alone starts a local Ray" in caplog.text
