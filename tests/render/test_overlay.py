"""The AR overlay: geometry against ground truth, visibility, state styling, models and their errors."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import OverlayConfig, RecordingConfig, TrackerConfig, demo_config, load_config
from ar_anchor.errors import ConfigError
from ar_anchor.geometry import Pose, look_at
from ar_anchor.render.models import cube_model, load_mesh, pin_model
from ar_anchor.render.overlay import OverlayRenderer, target_from_anchor
from ar_anchor.run.options import RunOptions
from ar_anchor.run.run_outputs import RunOutputs
from ar_anchor.sources.base import Frame, SourceInfo
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
from ar_anchor.targets import TargetId, TrackState
from ar_anchor.track.corners import refine_corners_by_edges
from ar_anchor.track.detection import MarkerDetections
from ar_anchor.track.tracker import FrameResult, TargetResult, Tracker
from ar_anchor.viz.sinks import Recording
from tests.helpers import run_main

REPO = Path(__file__).resolve().parents[2]
DARK = (30, 30, 30)


def cube_only(target: str, **kwargs) -> TrackerConfig:
    return dataclasses.replace(demo_config(), overlays=(OverlayConfig(target=target, kind="cube", **kwargs),))


def distorted_camera() -> CameraModel:
    k = np.array([[700.0, 0.0, 639.5], [0.0, 700.0, 359.5], [0.0, 0.0, 1.0]])
    return CameraModel(k, np.array([-0.28, 0.09, 0.0004, -0.0003, 0.0]), 1280, 720)


def silhouette_vertices(grey: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The dark silhouette's polygon vertices, sub-pixel: lines fitted to its edges (undistorted) and intersected."""
    mask = (grey < 128).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)
    polygon = cv2.approxPolyDP(contour, 0.015 * cv2.arcLength(contour, True), True).reshape(-1, 2).astype(float)
    area = np.sum(polygon[:, 0] * np.roll(polygon[:, 1], -1) - np.roll(polygon[:, 0], -1) * polygon[:, 1])
    if area < 0:  # clockwise in the image (y down), like a marker's corners
        polygon = polygon[::-1]
    return refine_corners_by_edges(grey, polygon[None], 8, camera.camera_matrix, camera.dist_or_none)[0]


def tracked_cube_view(camera: CameraModel, camera_from_world: Pose, length: float = 0.08):
    """Track a marker over a few frames of a static view; (last result, true pose, last image)."""
    scene = SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(3, length, Pose.identity()),),
        trajectory=Trajectory(kind="static", near_m=0.4),
        frames=4,
        seed=2,
        noise_sigma=1.0,
        blur_sigma=0.5,
    )
    source = SyntheticSource(scene)
    config = cube_only("marker:3", colour=DARK)
    config = dataclasses.replace(config, markers=dataclasses.replace(config.markers, length_m=length, lengths_m={}))
    tracker = Tracker(config, camera)
    rng = np.random.default_rng(0)
    for index in range(4):
        image = source.render_view(camera_from_world, rng)
        result = tracker.process(Frame(image, index, index * 33_333_333))
    return tracker, result, source.truth(camera_from_world)["marker:3"]


@pytest.mark.parametrize(
    "lens, eye, look",
    [
        ("pinhole", (0.22, 0.18, 0.42), (0.0, 0.0, 0.04)),
        ("distorted", (0.16, -0.12, 0.3), (0.2, -0.06, 0.0)),  # the cube lands near the image's left edge
    ],
)
@pytest.mark.slow
def test_cube_corners_land_on_the_true_projection(lens, eye, look):
    # given a marker tracked in synthetic frames with ground truth (and, once, a strong barrel lens)
    camera = CameraModel.default_synthetic() if lens == "pinhole" else distorted_camera()
    tracker, result, truth = tracked_cube_view(camera, look_at(eye, look))
    assert result.targets["marker:3"].state in ("tracked", "ambiguous")
    # when its cube is drawn (dark, opaque) on a white frame
    renderer = OverlayRenderer(tracker.config, camera)
    canvas = np.full((camera.height, camera.width, 3), 255, np.uint8)
    drawn = cv2.cvtColor(renderer.annotate(canvas, result), cv2.COLOR_BGR2GRAY)
    # then every corner of its silhouette is within 0.5 px of a true cube corner's projection
    h = 0.04
    cube = np.array([[x, y, z] for z in (0.0, 0.08) for x in (-h, h) for y in (-h, h)])
    expected = camera.project(truth.apply(cube))
    if lens == "distorted":
        assert expected[:, 0].min() < 60  # where the lens bends lines most (and the cube is fully in view)
        assert expected.min() > 0 and expected[:, 0].max() < camera.width and expected[:, 1].max() < camera.height
    measured = silhouette_vertices(drawn, camera)
    assert len(measured) == 6, measured  # a cube seen obliquely: a hexagonal silhouette
    distances = np.linalg.norm(measured[:, None, :] - expected[None, :, :], axis=2)
    nearest = distances.argmin(axis=1)
    assert len(set(nearest.tolist())) == 6
    assert distances.min(axis=1).max() < 0.5, distances.min(axis=1)


def synthetic_result(camera: CameraModel, targets: dict[str, tuple[Pose, str]], length: float = 0.05) -> FrameResult:
    results = {name: TargetResult(name, state, pose, pose, 0.1, 3.0, length) for name, (pose, state) in targets.items()}
    return FrameResult(0, 0, MarkerDetections.empty(), results, camera=camera)


def facing(distance: float, x: float = 0.0) -> Pose:
    """camera_from_marker: the marker straight ahead at ``distance``, shifted ``x`` sideways, turned a little."""
    rotation = cv2.Rodrigues(np.array([0.5, 0.4, 0.0]))[0]
    return Pose.from_matrix(rotation, np.array([x, 0.0, distance]))


def pixel(image: np.ndarray, camera: CameraModel, pose: Pose, point) -> np.ndarray:
    u, v = camera.project(pose.apply(np.asarray(point, float)[None]))[0]
    return image[int(round(v)), int(round(u))].astype(int)


def test_nearer_object_hides_the_farther_one(camera):
    # given a red cube near the camera and a green one farther away, overlapping in the image
    near, far = facing(0.45), facing(0.70, x=0.05)
    config = dataclasses.replace(
        demo_config(),
        overlays=(
            OverlayConfig(target="marker:1", kind="cube", colour=(230, 20, 20), colour_set=True),
            OverlayConfig(target="marker:2", kind="cube", colour=(20, 230, 20), colour_set=True),
        ),
    )
    renderer = OverlayRenderer(config, camera)
    black = np.zeros((camera.height, camera.width, 3), np.uint8)
    for order in (("marker:2", "marker:1"), ("marker:1", "marker:2")):  # the order the targets come in is irrelevant
        poses = {"marker:1": (near, "tracked"), "marker:2": (far, "tracked")}
        result = synthetic_result(camera, {name: poses[name] for name in order})
        image = renderer.annotate(black, result)
        # then where both project, the near (red) cube's colour is seen (BGR)
        blue, green, red = pixel(image, camera, near, (0.0, 0.0, 0.05))
        assert red > 60 and green < 30, (blue, green, red)
        # and the far cube still shows where the near one does not cover it
        assert (image[..., 1] > 60).sum() > 200


def one_triangle_obj(path: Path, counter_clockwise: bool) -> Path:
    # a triangle in the z = 0.02 plane; counter-clockwise seen from +z means its normal points at +z
    order = "1 2 3" if counter_clockwise else "1 3 2"
    path.write_text(f"v -0.03 -0.03 0.02\nv 0.03 -0.03 0.02\nv 0.0 0.03 0.02\nf {order}\n")
    return path


@pytest.mark.parametrize("counter_clockwise, drawn", [(True, True), (False, False)])
def test_a_face_pointing_away_from_the_camera_is_never_drawn(tmp_path, camera, counter_clockwise, drawn):
    # given a one-triangle mesh whose normal faces the camera (+z of a marker facing it) or away from it
    mesh = one_triangle_obj(tmp_path / "tri.obj", counter_clockwise)
    config = dataclasses.replace(
        demo_config(),
        overlays=(OverlayConfig(target="marker:1", kind="mesh", path=str(mesh), colour=(250, 250, 250)),),
    )
    pose = Pose(np.array([np.pi, 0.0, 0.0]), np.array([0.0, 0.0, 0.5]))  # straight ahead, its +z toward the camera
    black = np.zeros((camera.height, camera.width, 3), np.uint8)
    image = OverlayRenderer(config, camera).annotate(black, synthetic_result(camera, {"marker:1": (pose, "tracked")}))
    # then it is drawn only when it faces the camera
    assert (image.max() > 0) == drawn


def test_ambiguous_and_predicted_targets_are_drawn_translucent(camera):
    config = cube_only("*", colour=(250, 250, 250), colour_set=True)
    renderer = OverlayRenderer(config, camera)
    pose = facing(0.5)
    black = np.zeros((camera.height, camera.width, 3), np.uint8)
    top = (0.0, 0.0, 0.05)
    levels = {}
    for state in ("tracked", "ambiguous", "predicted"):
        image = renderer.annotate(black, synthetic_result(camera, {"marker:4": (pose, state)}))
        levels[state] = pixel(image, camera, pose, top).mean()
    assert levels["tracked"] > 1.7 * levels["ambiguous"] > 0
    assert levels["ambiguous"] > levels["predicted"] > 0


def test_board_anchor_frame_is_centred_with_z_out_of_the_board(camera):
    # given a 2x2 grid board (OpenCV frame: origin top-left, y down, z into the board)
    config = demo_config()
    tracker = Tracker(config, camera)
    outline = tracker.outline("board:desk")
    target = TargetResult("board:desk", "tracked", Pose.identity(), None, 0.0, 1.0, 0.04, outline_in_target=outline)
    matrix = target_from_anchor(target)
    # then the anchor is at the board's centre, z = -z_board (out of it), y = -y_board (up), x = x_board
    np.testing.assert_allclose(matrix[:3, 3], [0.05, 0.05, 0.0], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


# ------------------------------------------------------------------------- models and their errors


def test_cube_model_is_closed_with_outward_normals():
    import trimesh

    for subdivisions in (1, 4):
        model = cube_model(0.1, subdivisions)
        mesh = trimesh.Trimesh(model.vertices, model.faces, process=True)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume == pytest.approx(0.001)  # positive: normals point out
        assert model.vertices[:, 2].min() == 0.0  # stands on the marker plane


def _pin_built_by_trimesh(height_m: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pin as ar_anchor built it with trimesh before it was stored (ar_anchor/data/pin_*.npy)."""
    import trimesh

    ball_r = 0.28 * height_m
    cone = trimesh.creation.cone(radius=0.14 * height_m, height=0.72 * height_m, sections=24)
    cone.apply_transform(trimesh.transformations.rotation_matrix(math.pi, (1, 0, 0)))  # tip down
    cone.apply_translation((0, 0, 0.72 * height_m))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=ball_r)
    ball.apply_translation((0, 0, height_m - ball_r))
    parts = [(cone, (235, 235, 225)), (ball, (220, 40, 50))]
    vertices, faces, colours = [], [], []
    offset = 0
    for mesh, rgb in parts:
        vertices.append(np.asarray(mesh.vertices))
        faces.append(np.asarray(mesh.faces) + offset)
        colours.append(np.tile(np.asarray(rgb, np.float32), (len(mesh.faces), 1)))
        offset += len(mesh.vertices)
    return np.concatenate(vertices), np.concatenate(faces).astype(np.int32), np.concatenate(colours)


def test_the_stored_builtin_pin_is_the_model_trimesh_builds():
    # stored so that the default config (the pin on every board) does not import trimesh at start-up
    vertices, faces, colours = _pin_built_by_trimesh()
    pin = pin_model()
    np.testing.assert_array_equal(pin.vertices, vertices)
    np.testing.assert_array_equal(pin.faces, faces)
    np.testing.assert_array_equal(pin.face_colours, colours)
    np.testing.assert_array_equal(pin.facets, np.arange(368))
    assert (pin.vertices.dtype, pin.faces.dtype, pin.face_colours.dtype) == (np.float64, np.int32, np.float32)
    np.testing.assert_allclose(pin_model(0.5).vertices, _pin_built_by_trimesh(0.5)[0], atol=1e-15)


def test_builtin_pin_and_the_shipped_file_are_the_same_model():
    builtin = load_mesh("builtin:pin")
    shipped = load_mesh(REPO / "configs" / "models" / "pin.ply")
    assert len(builtin.faces) == len(shipped.faces) == len(pin_model().faces)
    np.testing.assert_allclose(shipped.vertices, builtin.vertices, atol=1e-6)
    np.testing.assert_allclose(shipped.face_colours, builtin.face_colours, atol=1.0)


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("missing.obj", None, "not found"),
        ("garbage.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01", "cannot read"),
        ("text.stl", b"this is not an STL file at all", "cannot read|no faces|holds no triangle"),
        ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces|holds no triangle"),
        ("nan.obj", b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "non-finite"),
        ("model.xyz", b"0 0 0\n", "unsupported format"),
    ],
)
def test_bad_mesh_files_are_clear_errors_naming_the_file(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=message) as caught:
        load_mesh(path)
    assert str(path) in str(caught.value)


def write_config(tmp_path: Path, overlay: str) -> Path:
    path = tmp_path / "tracker.toml"
    path.write_text("[[overlays]]\n" + overlay)
    return path


@pytest.mark.parametrize(
    "overlay, message",
    [
        ('kind = "sphere"\n', "kind: must be one of"),
        ('target = "marker:x"\n', "target: must be"),
        ('kind = "mesh"\n', "path: a mesh overlay needs a model file"),
        ('kind = "cube"\npath = "a.obj"\n', "path: only mesh overlays"),
        ('kind = "mesh"\npath = "builtin:teapot"\n', "unknown built-in model"),
        ("colour = [300, 0, 0]\n", "colour: values must be"),
        ("offset_m = [0, 0]\n", "offset_m: must be a list of 3 numbers"),
        ("opacity = 1.5\n", "opacity: must be in"),
        ("sized_m = 1\n", "unknown key"),
    ],
)
def test_bad_overlay_config_names_file_table_and_key(tmp_path, overlay, message):
    path = write_config(tmp_path, overlay)
    with pytest.raises(ConfigError, match=message) as caught:
        load_config(path)
    assert str(path) in str(caught.value) and "[[overlays]] #1" in str(caught.value)


def test_mesh_path_is_relative_to_the_config_file(tmp_path):
    (tmp_path / "models").mkdir()
    one_triangle_obj(tmp_path / "models" / "tri.obj", True)
    config = load_config(write_config(tmp_path, 'target = "board:*"\nkind = "mesh"\npath = "models/tri.obj"\n'))
    assert config.overlays[0].path == str(tmp_path / "models" / "tri.obj")
    assert config.overlays_for("board:desk") == config.overlays
    assert config.overlays_for("marker:3") == ()
    OverlayRenderer(config)  # reads the file


def test_default_overlays_skip_board_members():
    config = demo_config()
    assert [o.kind for o in config.overlays_for("marker:0")] == ["cube"]
    assert config.overlays_for("marker:10") == ()  # a desk marker: the board carries the model
    assert [o.kind for o in config.overlays_for("board:desk")] == ["mesh"]


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ar_anchor", *args], capture_output=True, text=True, cwd=cwd, timeout=300, check=False
    )


def run_in_process(args: list[str], cwd: Path) -> None:
    """``ar-anchor ARGS`` in ``cwd`` through ``main()`` (in-process: the runs whose files are checked), exit 0."""
    result = run_main(args, cwd)
    assert result.code == 0, result.describe()


@pytest.mark.slow
def test_demo_video_out_has_one_frame_per_processed_frame(tmp_path):
    run_in_process(["-q", "demo", "--frames", "12", "--out", "run", "--video-out", "demo.mp4"], tmp_path)
    capture = cv2.VideoCapture(str(tmp_path / "demo.mp4"))
    frames = 0
    while capture.read()[0]:
        frames += 1
    assert frames == 12
    assert '"frames": 12' in (tmp_path / "run" / "summary.json").read_text()


@pytest.mark.slow
def test_a_missing_mesh_file_stops_the_run_before_any_output(tmp_path):
    config = write_config(tmp_path, 'kind = "mesh"\npath = "nowhere.glb"\n')
    result = run_cli(["demo", "--frames", "3", "--config", str(config), "--out", "run"], tmp_path)
    assert result.returncode == 2
    assert "nowhere.glb" in result.stderr and "not found" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "run").exists()


def test_an_opaque_model_hides_the_background_completely(camera):
    # given the built-in pin (a ball overlapping a cone) seen from above its tip, on white and on black
    config = dataclasses.replace(
        demo_config(), overlays=(OverlayConfig(target="board:*", kind="mesh", path="builtin:pin", size_m=0.1),)
    )
    renderer = OverlayRenderer(config, camera)
    pose = Pose(np.array([np.pi + 0.2, 0.1, 0.0]), np.array([0.0, 0.0, 0.5]))
    result = synthetic_result(camera, {"board:b": (pose, "tracked")})
    white = renderer.annotate(np.full((camera.height, camera.width, 3), 255, np.uint8), result)
    black = renderer.annotate(np.zeros((camera.height, camera.width, 3), np.uint8), result)
    # then inside the model's silhouette (away from its anti-aliased rim) the background never shows
    inside = cv2.erode((np.abs(white.astype(int) - 255).max(axis=2) > 0).astype(np.uint8), np.ones((5, 5), np.uint8))
    assert inside.sum() > 2000
    assert np.array_equal(white[inside > 0], black[inside > 0])


@pytest.mark.slow
def test_an_unsupported_video_extension_is_a_usage_error_before_any_output(tmp_path):
    result = run_cli(["demo", "--frames", "3", "--out", "run", "--video-out", "clip.gif"], tmp_path)
    assert result.returncode == 2
    assert "--video-out clip.gif: unsupported extension" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_recording_holds_the_overlay_meshes_under_the_projected_world_and_no_overlay_image(tmp_path):
    rerun = Path(sys.executable).with_name("rerun")
    if not rerun.exists():
        pytest.skip(f"{rerun} not found")
    run_in_process(["-q", "demo", "--frames", "8", "--out", "run"], tmp_path)
    recording = tmp_path / "run" / "recording.rrd"
    printed = subprocess.run(
        [str(rerun), "rrd", "print", str(recording)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    # the image under the camera's pinhole, the meshes in the world the camera view projects onto it
    for entity in ("/world/camera/image ", "/world/camera_trajectory ", "/world/targets/marker_0/overlay/0 "):
        assert entity in printed, entity
    assert "Mesh3D" in printed and "Pinhole" in printed
    assert "/camera/overlay" not in printed  # no rasterised overlay without [recording] overlay_images
    verify = subprocess.run([str(rerun), "rrd", "verify", str(recording)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stdout + verify.stderr


@pytest.mark.parametrize(
    ("video_out", "overlay_images", "overlays", "drawn", "meshes", "overlay_image"),
    [
        (False, False, True, 0, True, False),  # the default: the viewer draws the overlay from the meshes
        (False, True, True, 3, True, True),  # [recording] overlay_images
        (True, False, True, 3, True, False),  # --video-out
        (True, True, False, 3, False, False),  # --no-overlay --video-out: the video's overlay only
    ],
)
def test_the_overlay_is_rasterised_only_for_video_out_or_overlay_images(
    tmp_path, camera, monkeypatch, video_out, overlay_images, overlays, drawn, meshes, overlay_image
):
    # given a run's outputs with a renderer whose annotate() is watched, and the entities the recording gets
    renderer = OverlayRenderer(demo_config(), camera)
    annotated: list[int] = []
    annotate = renderer.annotate

    def spy_annotate(image, result):
        annotated.append(result.index)
        return annotate(image, result)

    monkeypatch.setattr(renderer, "annotate", spy_annotate)
    logged: set[str] = set()
    log, jpeg = Recording.log, Recording.jpeg

    def spy_log(self, entity, data, *, static=False):
        logged.add(entity)
        log(self, entity, data, static=static)

    def spy_jpeg(self, entity, image, **kwargs):
        logged.add(entity)
        jpeg(self, entity, image, **kwargs)

    monkeypatch.setattr(Recording, "log", spy_log)
    monkeypatch.setattr(Recording, "jpeg", spy_jpeg)
    options = RunOptions(
        video_out=tmp_path / "annotated.mp4" if video_out else None, overlays=overlays, output_process=False
    )  # (the worker in this process, where the spies are)
    (tmp_path / "out").mkdir()
    outputs = RunOutputs(tmp_path / "out", options)
    outputs.open(camera, RecordingConfig(overlay_images=overlay_images), SourceInfo(), renderer)
    # when three tracked frames are written
    image = np.full((camera.height, camera.width, 3), 90, np.uint8)
    name = TargetId.parse("marker:1")
    targets = {name: TargetResult(name, TrackState.TRACKED, facing(0.5), facing(0.5), 0.1, 3.0, 0.05)}
    for index in range(3):
        result = FrameResult(index, index * 33_000_000, MarkerDetections.empty(), targets, camera=camera)
        outputs.write(Frame(image, index, index * 33_000_000), result, None, {})
    outputs.close()
    summary = outputs.write_summary("completed", 1.0, {})
    # then the renderer ran only where its image is used, and the recording has what the options ask for
    assert annotated == list(range(drawn))
    assert ("world/overlay/0" in logged) is meshes
    assert ("camera/overlay" in logged) is overlay_image
    assert "world/camera/image" in logged
    if not drawn:
        assert summary["latency_ms"]["render_ms"]["median"] < 1.0


def test_axes_are_drawn_in_their_colours_along_the_target_axes(camera):
    config = dataclasses.replace(demo_config(), overlays=(OverlayConfig(target="*", kind="axes", size_m=0.05),))
    pose = facing(0.5)
    image = OverlayRenderer(config, camera).annotate(
        np.zeros((camera.height, camera.width, 3), np.uint8), synthetic_result(camera, {"marker:2": (pose, "tracked")})
    )
    # x red, y green, z blue (BGR), each a little way along its own axis
    for axis, channel in ((0, 2), (1, 1), (2, 0)):
        point = np.zeros(3)
        point[axis] = 0.03
        colour = pixel(image, camera, pose, point)
        assert colour[channel] > 150 and colour[channel] == colour.max(), (axis, colour)


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".glb", ".off"])
def test_mesh_formats_load_the_same_triangles(tmp_path, suffix):
    import trimesh

    model = pin_model()
    path = tmp_path / f"pin{suffix}"
    trimesh.Trimesh(model.vertices, model.faces, process=False).export(path)
    loaded = load_mesh(path, rgb=(10, 20, 30))
    assert len(loaded.faces) == len(model.faces)

    def centroids(m):
        c = m.vertices[m.faces].mean(axis=1)
        return c[np.lexsort(np.round(c, 5).T)]

    np.testing.assert_allclose(centroids(loaded), centroids(model), atol=1e-5)  # the same triangles, any order
    assert np.all(loaded.face_colours == (10, 20, 30))


def test_a_closed_non_planar_board_gets_a_finite_anchor_frame():
    # two markers back to back (a sign printed on both sides): their outward normals cancel
    front = np.array([[-0.02, 0.02, 0.0], [0.02, 0.02, 0.0], [0.02, -0.02, 0.0], [-0.02, -0.02, 0.0]])
    back = front[[1, 0, 3, 2]] - [0.0, 0.0, 0.001]
    outline = np.stack([front, back])
    target = TargetResult("board:sign", "tracked", Pose.identity(), None, 0.0, 1.0, 0.04, outline_in_target=outline)
    matrix = target_from_anchor(target)
    # then the anchor is the board's own axes at its centre, not NaN
    assert np.all(np.isfinite(matrix))
    np.testing.assert_allclose(matrix[:3, :3], np.eye(3))
    np.testing.assert_allclose(matrix[:3, 3], [0.0, 0.0, -0.0005])
