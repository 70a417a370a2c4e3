"""The 3D scene and the detections sent in batches (the poses of ``world/camera`` and ``world/targets/<target>``,
the image's points and outlines, labels, hypotheses..., :mod:`ar_anchor.viz.series`) make the same recording
as one ``rr.log`` per entity and frame, and the metrics' columns built with pyarrow the same as rerun's own
(``rr.Scalars.columns``): read back, the files hold the same values at the same times, in the same order
where two share a time."""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from ar_anchor.camera import CameraModel
from ar_anchor.config import RecordingConfig
from ar_anchor.viz import recorder as recorder_module
from ar_anchor.viz.recorder import RerunRecorder
from ar_anchor.viz.sinks import Recording

TIMELINES = ("frame", "time")


@pytest.fixture(scope="module")
def tracked() -> tuple[CameraModel, list]:
    """A demo scene seen from near, orbiting: a board and lone markers, targets coming and going."""
    from tests.helpers import orbit_pairs

    camera, pairs = orbit_pairs(30)
    seen = [set(result.targets) for _, result in pairs]
    # (what the comparison needs of the scene: several targets at once, a board, targets gone and back)
    assert max(map(len, seen)) >= 4 and any(name.is_board for names in seen for name in names)
    assert sum(bool(before - after) for before, after in zip(seen, seen[1:])) >= 3
    return camera, pairs


def _record(
    path: Path, camera: CameraModel, pairs: list, settings: RecordingConfig, *, batched: bool, at_once: bool = False
) -> list[Path]:
    recorder = RerunRecorder(path, camera=camera, settings=settings)
    assert not recorder.series.at_once  # (a file alone: the scene is kept for the batches)
    recorder.series.at_once = at_once
    if not batched:  # the recorder as it was: the scene logged on its own frame, one rr.log per entity;
        recording = recorder.recording  # the metrics in batches built by rerun's own columns
        recorder.series.at_once = True

        def log_now(entity: str, translation: np.ndarray, rotation: np.ndarray) -> None:
            recording.log(entity, rr.Transform3D(translation=translation, mat3x3=rotation))

        def time_columns(*, frames, seconds, log_ns=None) -> list[rr.TimeColumn]:
            return [rr.TimeColumn("frame", sequence=frames), rr.TimeColumn("time", duration=seconds)]

        def scalar_columns(entity: str, values, times) -> None:
            columns = rr.Scalars.columns(scalars=np.asarray(values))
            recording.stream.send_columns(recording._at(entity), indexes=times, columns=columns)

        recorder.series.transform = log_now  # type: ignore[method-assign]
        recording.time_columns, recording.scalar_columns = time_columns, scalar_columns  # type: ignore[method-assign]
    for frame, result in pairs:
        recorder.log_frame(frame, result, stages={"output_ms": 1.0})
    recorder.close()
    return recorder.parts


def _content(path: Path) -> tuple[dict, dict]:
    """What a file holds: for each entity and each time on a timeline (``frame``, ``time``; None: static),
    the component values logged there, and the recursive clears of the entities above it at that time, in
    the order rerun keeps them (by row id: it decides between two at the same time), and which timelines
    each entity's components are on."""
    values: dict[tuple, list] = defaultdict(list)
    clears: dict[tuple, list] = defaultdict(list)  # (timeline, time) -> [(entity, row id)] of recursive clears
    timelines: dict[tuple[str, str], set[str]] = defaultdict(set)
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        names = [
            field.name
            for field in batch.schema
            if field.metadata.get(b"rerun:kind") == b"data" and field.name != "RecordingInfo:start_time"
        ]  # (when the recording started: a wall clock, as ``log_time``, whose values are not compared)
        indexes = [field.name for field in batch.schema if field.metadata.get(b"rerun:kind") == b"index"]
        rows = {name: batch.column(name).to_pylist() for name in [*names, "rerun.controls.RowId"]}
        for name in names:
            timelines[(chunk.entity_path, name)].update(indexes)
        for row in range(batch.num_rows):
            row_id = rows["rerun.controls.RowId"][row]
            cells = [(name, rows[name][row]) for name in names if rows[name][row] is not None]
            places = [(timeline, _time(batch, timeline, row)) for timeline in TIMELINES if timeline in indexes]
            for place in places or [("static", None)]:
                values[(chunk.entity_path, *place)].append((row_id, cells))
                if ("Clear:is_recursive", [True]) in cells:
                    clears[place].append((chunk.entity_path, row_id))
    for (entity, *place), rows in values.items():
        above = [(row_id, [("cleared above", path)]) for path, row_id in clears[tuple(place)] if _under(entity, path)]
        rows += above
    ordered = {key: [cells for _, cells in sorted(rows)] for key, rows in values.items()}
    return ordered, dict(timelines)


def _under(entity: str, above: str) -> bool:
    return entity.startswith(above.rstrip("/") + "/")


def _time(batch, timeline: str, row: int) -> int:
    return batch.column(timeline).cast("int64")[row].as_py()


def _compare(tmp_path: Path, camera, pairs, settings: RecordingConfig, *, at_once: bool = False) -> set[str]:
    old = _record(tmp_path / "old" / "r.rrd", camera, pairs, settings, batched=False)
    new = _record(tmp_path / "new" / "r.rrd", camera, pairs, settings, batched=True, at_once=at_once)
    assert [part.name for part in old] == [part.name for part in new]
    entities: set[str] = set()
    for old_part, new_part in zip(old, new):
        (old_values, old_timelines), (new_values, new_timelines) = _content(old_part), _content(new_part)
        assert new_timelines == old_timelines  # log_time included: rr.log stamps it, the batches too
        assert sorted(new_values) == sorted(old_values)
        for key, cells in old_values.items():
            assert new_values[key] == cells, key
        entities.update(entity for entity, *_ in old_values)
    assert any(entity.startswith("/world/targets/") and entity.count("/") == 3 for entity in entities)
    return entities  # (the entities compared)


@pytest.mark.parametrize("causal", [False, True])
def test_the_batched_scene_makes_the_same_recording_as_one_call_each(tmp_path, tracked, causal):
    camera, pairs = tracked
    if causal:  # an offline replay's live filter beside it: its axes on some frames, none (cleared) on others
        pairs = [
            (frame, dataclasses.replace(r, causal_targets=[dict(r.targets), {}, None][frame.index % 3]))
            for frame, r in pairs
        ]
    entities = _compare(tmp_path, camera, pairs, RecordingConfig(image_every=0, metrics_every=4))
    kept = ["/world/camera", "/world/camera/image/boards/board_desk/inliers", "/world/labels", "/world/hypotheses"]
    kept += ["/world/camera/image/markers", "/world/camera_trajectory", "/world/truth_camera"]
    assert set(kept + ["/world/causal"] * causal) <= entities


@pytest.mark.parametrize("first", [0, 1])
def test_the_same_with_frames_that_share_a_time_and_a_target_gone_at_it(tmp_path, tracked, first):
    # given frames two by two at the same time (from frame ``first``): a target gone on the second is cleared
    # at the time its last pose has (rerun breaks the tie by arrival: the clear must come after it, as it did)
    camera, pairs = tracked
    shared = [(frame.index + first) // 2 for frame, _ in pairs]
    paired = [(dataclasses.replace(frame, timestamp_ns=at * 66_666_667), r) for (frame, r), at in zip(pairs, shared)]
    gone_at_a_tie = [
        index
        for index in range(1, len(pairs))
        if shared[index] == shared[index - 1] and set(pairs[index - 1][1].targets) - set(pairs[index][1].targets)
    ]
    assert gone_at_a_tie
    _compare(tmp_path, camera, paired, RecordingConfig(image_every=0, metrics_every=5))


def test_the_same_in_a_new_part_every_frame(tmp_path, tracked):
    camera, pairs = tracked
    _compare(tmp_path, camera, pairs[:8], RecordingConfig(image_every=0, metrics_every=10, part_minutes=1e-9))


def test_the_same_with_each_frames_scene_sent_at_once(tmp_path, tracked):
    camera, pairs = tracked
    _compare(tmp_path, camera, pairs, RecordingConfig(image_every=0, metrics_every=4), at_once=True)


class _Watched(Recording):
    """A recording a viewer watches (its URL; no sink: nothing listens there)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.viewer_url = "rerun+http://127.0.0.1:9/proxy"


def test_a_viewer_watching_gets_each_frames_scene_on_that_frame(tmp_path, tracked, monkeypatch):
    # given a recording a viewer watches, and the metrics sent every 10 frames
    camera, pairs = tracked
    monkeypatch.setattr(recorder_module, "Recording", _Watched)
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, settings=RecordingConfig(image_every=0))
    recording = recorder.recording
    logged: list[tuple[int, str]] = []
    batched: list[str] = []
    transform = recording.transform

    def spy(entity, translation, rotation) -> None:
        logged.append((index, entity))
        transform(entity, translation, rotation)

    recording.transform = spy
    recording.transform_columns = lambda entity, *_: batched.append(entity)
    recording.rows_columns = lambda entity, *_: batched.append(entity)
    for index, (frame, result) in enumerate(pairs):
        recorder.log_frame(frame, result)
        # then the camera (placed by the anchor in view) and every target but the anchor (placed from the
        # camera, from the first frame placing it on) were logged on the frame, one call each
        now = [entity for at, entity in logged if at == index]
        targets = [name for name in result.targets if name != recorder.anchor]
        assert now.count("world/camera") == (recorder.anchor in result.targets)
        assert len(now) == (len(targets) if recorder.anchor is not None else 0) + (recorder.anchor in result.targets)
    recorder.close()
    assert logged and not batched  # (nothing of the scene kept for the batches)
