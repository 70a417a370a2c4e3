"""The 3D scene's values (:mod:`ar_anchor.viz.parts`' batched arithmetic, rotation matrices throughout) are
those :class:`~ar_anchor.geometry.Pose` composition gives, target by target: in float64 to 1e-9, and read
back from a recording (rerun keeps float32) to float32's rounding, at the same frames; and the arrow arrays
:meth:`Recording.cells <ar_anchor.viz.sinks.Recording.cells>` builds are those rerun's own archetypes build."""

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
from ar_anchor.geometry import Pose
from ar_anchor.targets import TargetId
from ar_anchor.viz.parts import Shapes, Trail, branch_strips, camera_in_world, causal_axes, closed_squares, placed
from ar_anchor.viz.recorder import RerunRecorder
from ar_anchor.viz.sinks import Recording


@pytest.fixture(scope="module")
def tracked() -> tuple[CameraModel, list]:
    """A demo scene seen from near, orbiting (a board and lone markers, coming and going); every other frame
    with the live filter's targets beside (an offline replay's ``causal_targets``), one of them dropped."""
    from tests.helpers import orbit_pairs

    camera, pairs = orbit_pairs(24)
    pairs = [
        (frame, dataclasses.replace(r, causal_targets=dict(list(r.targets.items())[1:]) if frame.index % 2 else None))
        for frame, r in pairs
    ]
    assert max(len(r.targets) for _, r in pairs) >= 4
    assert any(pose is not None for _, r in pairs for t in r.targets.values() for pose in t.branch_poses[1:])
    return camera, pairs


def _expected(pairs: list) -> dict[tuple[str, str], dict[int, np.ndarray]]:
    """What the recorder's scene holds, computed target by target with ``Pose`` (``compose``, ``inverse``,
    ``apply``): entity and component -> frame -> value (float64)."""
    expected: dict[tuple[str, str], dict[int, np.ndarray]] = defaultdict(dict)
    anchor: TargetId | None = None
    world_from_camera: Pose | None = None
    for frame, result in pairs:
        if anchor is None and result.targets:
            anchor = TargetId.ordered(result.targets)[0]
        if anchor in result.targets:
            world_from_camera = result.targets[anchor].pose.inverse()
            expected[("/world/camera", "translation")][frame.index] = world_from_camera.tvec
            expected[("/world/camera", "mat3x3")][frame.index] = world_from_camera.rotation
        if world_from_camera is None:
            continue
        strips = []
        for name, target in result.targets.items():
            if name != anchor:
                world_from_target = world_from_camera.compose(target.pose)
                entity = f"/world/targets/{name.path_part}"
                expected[(entity, "translation")][frame.index] = world_from_target.tvec
                expected[(entity, "mat3x3")][frame.index] = world_from_target.rotation
            normal = np.array([[0.0, 0.0, 0.0]] + [[0.0, 0.0, target.length_m]] * 4)
            shape = np.concatenate([closed_squares(target), normal[None]])
            for pose in target.branch_poses:
                if pose is not None:
                    points = world_from_camera.compose(pose).apply(shape.reshape(-1, 3))
                    strips.append(points.reshape(shape.shape))
        if strips:
            expected[("/world/hypotheses", "strips")][frame.index] = np.concatenate(strips)
        if result.causal_targets:
            placed_ = [(world_from_camera.compose(t.pose), t.length_m) for t in result.causal_targets.values()]
            origins = [pose.tvec for pose, _ in placed_ for _ in range(3)]
            vectors = [axis for pose, length in placed_ for axis in pose.rotation.T * (length * 0.75)]
            expected[("/world/causal", "origins")][frame.index] = np.array(origins)
            expected[("/world/causal", "vectors")][frame.index] = np.array(vectors)
    return expected


def _read(path: Path, wanted: set[tuple[str, str]]) -> dict[tuple[str, str], dict[int, np.ndarray]]:
    """The recording's values of ``wanted`` (entity, component) at each ``frame`` (float64 of rerun's float32)."""
    found: dict[tuple[str, str], dict[int, np.ndarray]] = defaultdict(dict)
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "frame" not in batch.schema.names:
            continue
        frames = batch.column("frame").cast("int64").to_pylist()
        for field in batch.schema:
            component = field.name.rpartition(":")[2]
            if (chunk.entity_path, component) not in wanted:
                continue
            for frame, value in zip(frames, batch.column(field.name).to_pylist()):
                if value is not None:
                    found[(chunk.entity_path, component)][frame] = np.array(value, np.float64)
    return found


def test_the_recorded_scene_is_what_pose_composition_gives(tmp_path, tracked):
    camera, pairs = tracked
    recorder = RerunRecorder(tmp_path / "r.rrd", camera=camera, settings=RecordingConfig(image_every=0))
    for frame, result in pairs:
        recorder.log_frame(frame, result)
    recorder.close()
    expected = _expected(pairs)
    assert {entity for entity, _ in expected} >= {"/world/camera", "/world/hypotheses", "/world/causal"}
    found = _read(recorder.parts[0], set(expected))
    for key, by_frame in expected.items():
        assert sorted(found[key]) == sorted(by_frame), key  # the same frames
        for index, want in by_frame.items():
            got = found[key][index].ravel()
            if key[1] == "mat3x3":
                want = want.T  # (stored column by column)
            want = np.asarray(want, np.float64).ravel()
            assert got.shape == want.shape, key
            # rerun keeps float32: the value rounded to it (a float64 a rounding away may round to the next one)
            np.testing.assert_allclose(got, want.astype(np.float32), rtol=2**-23, atol=1e-12, err_msg=str(key))


def test_the_batched_arithmetic_is_pose_composition_to_1e_9(tracked):
    _, pairs = tracked
    shapes = Shapes()
    checked = 0
    for _, result in pairs:
        targets = list(result.targets.values())
        if not targets:
            continue
        camera_from_world = targets[0].pose
        world = camera_in_world(camera_from_world)
        inverse = camera_from_world.inverse()
        np.testing.assert_allclose(world[0], inverse.rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(world[1], inverse.tvec, rtol=1e-12, atol=1e-15)
        rotations, translations = placed(world, [target.pose for target in targets])
        strips = branch_strips(targets, world, shapes)
        origins, vectors, _ = causal_axes(targets, world)
        expected_strips = []
        for index, target in enumerate(targets):
            composed = inverse.compose(target.pose)
            scale = max(1.0, float(np.abs(composed.tvec).max()))
            np.testing.assert_allclose(rotations[index], composed.rotation, rtol=0, atol=1e-9)
            np.testing.assert_allclose(translations[index], composed.tvec, rtol=0, atol=1e-9 * scale)
            np.testing.assert_allclose(origins[3 * index : 3 * index + 3], [composed.tvec] * 3, atol=1e-9 * scale)
            axes = composed.rotation.T * (target.length_m * 0.75)
            np.testing.assert_allclose(vectors[3 * index : 3 * index + 3], axes, rtol=0, atol=1e-9 * target.length_m)
            normal = np.array([[0.0, 0.0, 0.0]] + [[0.0, 0.0, target.length_m]] * 4)
            shape = np.concatenate([closed_squares(target), normal[None]])
            for pose in target.branch_poses:
                if pose is not None:
                    points = inverse.compose(pose).apply(shape.reshape(-1, 3)).reshape(shape.shape)
                    expected_strips.append(points)
            checked += 1
        if expected_strips:
            assert strips is not None
            want = np.concatenate(expected_strips)
            scale = max(1.0, float(np.abs(want).max()))
            np.testing.assert_allclose(strips[0], want, rtol=0, atol=1e-9 * scale)
            assert len(strips[1]) == len(strips[2]) == len(want)
        else:
            assert strips is None
    assert checked >= 20


def test_the_trail_keeps_the_last_points_in_order():
    trail = Trail(4)
    kept: list[np.ndarray] = []
    for step in range(19):
        point = np.array([step, -step, 0.5 * step], np.float64)
        trail.append(point)
        kept.append(point)
        assert len(trail) == min(len(kept), 4)
        np.testing.assert_array_equal(trail.points(), np.array(kept[-4:]))


def _arrays(data) -> list[tuple[str, object]]:
    return [(descriptor, array) for descriptor, array in Recording.component_arrays(data)]


@pytest.mark.parametrize("count", [0, 1, 3, 17])
def test_cells_built_directly_are_what_rerun_builds(count):
    rng = np.random.default_rng(count)
    labels = [str(i) if i % 2 else "" for i in range(count)]
    rgb = [tuple(int(c) for c in rng.integers(0, 256, 3)) for _ in range(count)]
    rgba = rng.integers(0, 256, (count, 4)).astype(np.uint8)
    radii = list(rng.random(count))
    strips2, strips3 = rng.random((count, 5, 2)) * 500, rng.random((count, 5, 3))
    points2, points3 = rng.random((count, 2)) * 500, rng.random((count, 3))
    cases = [
        (
            rr.LineStrips2D(strips2, colors=rgb, labels=labels, radii=radii),
            Recording.cells("LineStrips2D", strips=strips2, colors=rgb, labels=labels, radii=radii),
        ),
        (
            rr.LineStrips3D(strips3, colors=rgba, radii=np.float32(radii)),
            Recording.cells("LineStrips3D", strips=strips3, colors=rgba, radii=np.float32(radii)),
        ),
        (
            rr.Points2D(points2, radii=1.5, colors=[(255, 0, 255)]),
            Recording.cells("Points2D", positions=points2, radii=1.5, colors=[(255, 0, 255)]),
        ),
        (
            rr.Points3D(points3, labels=labels, radii=np.array(radii)),
            Recording.cells("Points3D", positions=points3, labels=labels, radii=np.array(radii)),
        ),
    ]
    if count:  # one strip of many points (the camera's trajectory)
        cases.append(
            (
                rr.LineStrips3D([points3], colors=[(255, 210, 60)], radii=[0.25]),
                Recording.cells("LineStrips3D", strips=points3[None], colors=[(255, 210, 60)], radii=[0.25]),
            )
        )
    for data, built in cases:
        want, got = _arrays(data), _arrays(built)
        assert [d for d, _ in got] == [d for d, _ in want]
        for (descriptor, array), (_, expected) in zip(got, want):
            assert array.type == expected.type, descriptor
            assert array.equals(expected), (descriptor, array, expected)
