"""``ar-anchor map`` end to end on rendered clips of known layouts: a hand-held webcam clip of a sheet of
markers (motion blur, noise, H.264) and a room of 20 markers on four walls with the camera walking a loop
through it. The learned maps are scored against the truth after a similarity alignment."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.cli.main import main
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, Renderer, SyntheticScene, Trajectory, marker_sheet, webcam_camera
from ar_anchor.tools.map import aligned_errors, rms_m

from .scenes import ROOM_MARKER_M, room_markers, room_path, truth_corners

pytestmark = pytest.mark.slow


def run_map(tmp_path, folder, camera, dictionary: str, length_m: float) -> dict[int, np.ndarray]:
    camera_file = tmp_path / "camera.yml"
    camera.to_yaml(camera_file)
    out = tmp_path / "map" / "layout.yml"
    args = [str(folder), "--camera", str(camera_file), "--dictionary", dictionary, "--marker-length", f"{length_m}"]
    assert main(["-q", "map", *args, "--out", str(out)]) == 0
    for name in ("layout.yml", "layout.toml", "layout_report.md", "layout.rrd"):
        assert (out.parent / name).is_file(), name
    return {marker_id: np.array(corners) for marker_id, corners in read_layout(out)}


def handheld_scene() -> SyntheticScene:
    markers, sheet = marker_sheet(range(6), length_m=0.05, cols=3, gap_m=0.025)
    return SyntheticScene(
        camera=webcam_camera(640, 480, k1=-0.12, k2=0.03),
        dictionary="DICT_4X4_50",
        markers=markers,
        sheets=(sheet,),
        trajectory=Trajectory(kind="handheld", near_m=0.3, far_m=0.55, azimuth_deg=30.0, elevation_deg=20.0, seed=4),
        frames=75,
        fps=25.0,
        seed=4,
        noise_sigma=2.0,
        blur_sigma=0.5,
        exposure_s=0.008,
        max_subframes=4,
        compression="h264",
        h264_kbps=1500.0,
    )


def test_handheld_clip_recovers_the_sheet_within_a_millimetre(tmp_path):
    # given a hand-held clip (motion blur, noise, H.264) of a sheet of 6 markers, as an image folder
    scene = handheld_scene()
    folder = tmp_path / "clip"
    folder.mkdir()
    with SyntheticSource(scene) as source:
        for frame in source:
            cv2.imwrite(str(folder / f"{frame.index:04d}.png"), frame.image)
    # when mapped
    learned = run_map(tmp_path, folder, scene.camera, scene.dictionary, 0.05)
    # then every marker's corners are within 1 mm RMS of the truth after a similarity alignment
    truth = {m.marker_id: m.world_from_target for m in scene.markers}
    assert sorted(learned) == sorted(truth)
    _, residuals = aligned_errors(learned, truth_corners(truth, 0.05))
    assert 1000.0 * rms_m(residuals) < 1.0


def room_scene(frames: int) -> SyntheticScene:
    markers = tuple(PlacedMarker(i, ROOM_MARKER_M, pose) for i, pose in room_markers().items())
    return SyntheticScene(
        camera=webcam_camera(960, 540, hfov_deg=75.0),
        dictionary="DICT_4X4_50",
        markers=markers,
        frames=frames,
        clutter=False,
        noise_sigma=1.5,
        blur_sigma=0.5,
        supersample=2,
    )


def test_room_map_is_within_one_percent_of_the_room(tmp_path):
    # given a walk around a 4 m x 3 m room with 20 markers on its walls, frames as JPEG files
    poses = room_path(120)
    scene = room_scene(len(poses))
    renderer = Renderer(scene)
    rng = np.random.default_rng(0)
    folder = tmp_path / "walk"
    folder.mkdir()
    for index, camera_from_world in enumerate(poses):
        image = renderer.render_view(camera_from_world, rng)
        cv2.imwrite(str(folder / f"{index:04d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    # when mapped
    learned = run_map(tmp_path, folder, scene.camera, scene.dictionary, ROOM_MARKER_M)
    # then every marker is mapped and its centre is within 1 % of the room's size of the truth
    truth = truth_corners(room_markers(), ROOM_MARKER_M)
    assert sorted(learned) == sorted(truth)
    _, residuals = aligned_errors(learned, truth)
    points = np.concatenate(list(truth.values()))
    size_m = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    centre_errors = [float(np.linalg.norm(r.mean(axis=0))) for r in residuals.values()]
    assert max(centre_errors) < 0.01 * size_m
