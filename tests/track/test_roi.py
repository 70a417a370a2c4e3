"""ROI tracking: regions planned from the last frame, searched at reduced scale, exact corners."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ar_anchor.camera import CameraModel
from ar_anchor.config import BoardConfig, DetectorConfig, MarkersConfig, TrackerConfig, demo_config
from ar_anchor.geometry import Pose, angle_between_deg
from ar_anchor.sources.base import Frame
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedBoard, PlacedMarker, SyntheticScene, Trajectory
from ar_anchor.track.detection import Detector, MarkerDetections, Region, plan_regions
from ar_anchor.track.tracker import Tracker
from tests.track.scenes import PAIR_CAMERA, pair_frame


def orbit_frames(frames: int = 40, markers=((0, 0.05, (0.0, 0.0)),), size=(1280, 720, 1000.0)):
    camera = CameraModel.from_fov(*size)
    placed = tuple(PlacedMarker(i, length, Pose(np.zeros(3), np.array([x, y, 0.0]))) for i, length, (x, y) in markers)
    scene = SyntheticScene(
        camera=camera,
        markers=placed,
        trajectory=Trajectory(kind="orbit", near_m=0.6),
        frames=frames,
        seed=4,
        noise_sigma=2.0,
        blur_sigma=0.6,
    )
    return camera, list(SyntheticSource(scene))


def tracker_config(roi: bool, ids=(0,), **detector) -> TrackerConfig:
    config = demo_config()
    return dataclasses.replace(
        config,
        boards=(),
        markers=MarkersConfig(length_m=0.05, lengths_m={}, ids=tuple(ids)),
        detector=dataclasses.replace(config.detector, roi=roi, **detector),
    )


def test_region_corners_match_full_frame_corners():
    # given a frame and the regions planned from its own detections (one of them shrunk to half scale)
    camera, frames = orbit_frames(frames=1)
    detector = Detector(DetectorConfig())
    image = frames[0].image
    full = detector.detect(image, camera)
    assert full.ids.tolist() == [0]
    regions = plan_regions({0: full.corners[0]}, {}, camera.size, margin=0.6)
    assert len(regions) == 1 and regions[0].scale == 1.0  # an 80 px marker is searched at full scale
    for scale in (1.0, 0.5):
        region = dataclasses.replace(regions[0], scale=scale)
        # when only the region is searched
        found = detector.detect_regions(image, [region], camera)
        # then the corners are the full-frame ones (edge-refined on the full image either way)
        assert found.ids.tolist() == [0]
        np.testing.assert_allclose(found.corners, full.corners, atol=0.02)


def test_plan_regions_follows_motion_merges_overlaps_and_clips():
    square = np.array([[100.0, 100.0], [200.0, 100.0], [200.0, 200.0], [100.0, 200.0]])
    # a marker moving right by 30 px per frame: the region leads it
    (region,) = plan_regions({1: square + [30, 0]}, {1: square}, (1280, 720), margin=0.5)
    assert region.x0 < 130 + 60 - 50 and region.x1 > 230 + 30 + 50  # grown by the motion and half a side
    # two nearby markers: one region; a far one: its own
    near = square + [90, 0]
    far = square + [900, 400]
    regions = plan_regions({1: square, 2: near, 3: far}, {}, (1280, 720), margin=0.5)
    assert len(regions) == 2
    # at the image edge: clipped
    edge = square + [1150, 550]
    (clipped,) = plan_regions({4: edge}, {}, (1280, 720), margin=0.5)
    assert clipped.x1 == 1280 and clipped.y1 == 720
    # a 400 px marker is searched at about 80 px
    big = square * 4
    (shrunk,) = plan_regions({5: big}, {}, (1920, 1080), margin=0.5)
    assert 0.15 < shrunk.scale < 0.25


@pytest.mark.slow
def test_roi_tracking_is_as_accurate_as_full_frame_and_searches_less():
    camera, frames = orbit_frames(frames=40, markers=((0, 0.05, (0.0, 0.0)), (1, 0.05, (0.12, 0.05))))
    errors, full_searches = {}, {}
    for roi in (False, True):
        from ar_anchor.track.tracker import Tracker

        tracker = Tracker(tracker_config(roi, ids=(0, 1)), camera)
        calls = {"full": 0}
        original = tracker.detector.detect

        def counting(image, camera=None, fast=False, original=original, calls=calls):
            calls["full"] += 1
            return original(image, camera, fast)

        tracker.detector.detect = counting
        found = []
        for frame in frames:
            result = tracker.process(frame)
            found.append(sorted(result.detections.ids.tolist()))
            for name, target in result.targets.items():
                errors.setdefault(roi, []).append(angle_between_deg(target.pose.rotation, frame.truth[name].rotation))
        full_searches[roi] = calls["full"]
        if roi:
            assert found == reference_found  # noqa: F821 - the same markers in every frame
        else:
            reference_found = found  # noqa: F841
    assert full_searches[False] == 40
    assert full_searches[True] <= 40 // 15 + 2
    assert np.median(errors[True]) <= 1.1 * np.median(errors[False]) + 1e-6


def test_a_marker_missed_by_the_regions_is_searched_for_in_the_whole_frame_at_once(camera):
    from ar_anchor.track.tracker import Tracker

    _, frames = orbit_frames(frames=3)
    tracker = Tracker(tracker_config(True), frames[0].image.shape[1::-1] and CameraModel.from_fov(1280, 720, 1000.0))
    tracker.process(frames[0])
    # when the marker jumps far away from where the regions will look (another part of the image)
    image = frames[1].image
    shifted = np.roll(image, (300, -500), axis=(0, 1))
    result = tracker.process(Frame(shifted, 1, 33_333_333))
    # then the same frame's full-frame search still finds it
    assert result.detections.ids.tolist() == [0]


def test_region_dataclass_defaults_to_full_scale():
    assert Region(0, 0, 10, 10).scale == 1.0


def test_region_corners_match_full_frame_corners_through_lens_distortion():
    from tests.helpers import corner_view, distorted_camera

    camera = distorted_camera()
    source, camera_from_world = corner_view(camera)
    image = source.render_view(camera_from_world)
    detector = Detector(DetectorConfig())
    full = detector.detect(image, camera)
    assert full.ids.tolist() == [5]
    for region in plan_regions({5: full.corners[0]}, {}, camera.size, margin=0.6):
        found = detector.detect_regions(image, [region], camera)
        np.testing.assert_allclose(found.corners, full.corners, atol=0.02)


def test_region_corners_of_far_small_markers_match_full_frame_corners():
    # given a lone 5 cm marker beside a 2x2 board of them, 10 deg off-axis, at 1.5-3 m (markers 17-33 px
    # wide, cells of 3-6 px), rendered without noise
    camera = CameraModel.from_fov(1280, 720, 1000.0)
    board = BoardConfig(name="b", cols=2, rows=2, marker_length_m=0.05, separation_m=0.01, first_id=10)
    width, height = board.size_m
    scene = SyntheticScene(
        camera=camera,
        markers=(PlacedMarker(0, 0.05, Pose(np.zeros(3), np.array([-0.0583, 0.0, 0.0]))),),
        boards=(PlacedBoard(board, Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), np.array([0.0, height / 2, 0.0]))),),
        frames=1,
        blur_sigma=0.6,
    )
    source = SyntheticSource(scene)
    detector = Detector(DetectorConfig())
    for distance in (1.5, 2.0, 2.5, 3.0):
        view = Trajectory(kind="static", near_m=distance, azimuth_deg=10.0, look_at=(-0.0017, 0.0, 0.0))
        image = source.render_view(view.camera_from_world(0))
        full = detector.detect(image, camera)
        assert len(full) == 5, distance
        regions = plan_regions(dict(zip(full.ids.tolist(), full.corners)), {}, camera.size, margin=0.6)
        # when only the regions planned from them are searched
        found = detector.detect_regions(image, regions, camera)
        # then every marker has the full-frame corners (a region search with one threshold window once
        # outlined some of these 1.5-2 px off)
        assert found.ids.tolist() == full.ids.tolist(), distance
        np.testing.assert_allclose(found.corners, full.corners, atol=0.02, err_msg=f"at {distance} m")


@pytest.mark.slow
@pytest.mark.parametrize("full_every", [5, 15])
def test_a_newly_appearing_marker_is_found_within_the_full_frame_period(full_every):
    # given a tracker following marker 0 with ROI tracking (searching around it only), and then marker 1
    # appearing elsewhere in the image (frame `switch` on)
    # (a still camera 0.6 m away, new sensor noise every frame: the view test_pose_truth and the tests below
    # play too, rendered once: tests/track/scenes.py)
    camera = PAIR_CAMERA
    switch = 7
    tracker = Tracker(tracker_config(True, ids=(0, 1), roi_full_every=full_every), camera)
    found_at = None
    for index in range(switch + 3 * full_every):
        image = pair_frame(index, both=index >= switch).image
        result = tracker.process(Frame(image, index, index * 33_333_333))
        assert "marker:0" in result.targets
        if index < switch:
            assert "marker:1" not in result.targets
        elif "marker:1" in result.targets and found_at is None:
            found_at = index
    # then it is found by the next full-frame search: within the full-frame period
    assert found_at is not None
    assert found_at - switch < full_every, (found_at, switch)


def _vanishing_marker_frames(length_m: float, frames: int = 14, vanish: int = 4):
    """Two markers, static camera 0.6 m away; marker 1 is gone from frame ``vanish`` on (remembered, so every
    frame after that is a full-frame search). The renders are shared (tests/track/scenes.py): read-only."""
    return PAIR_CAMERA, [
        Frame(pair_frame(index, both=index < vanish, length_m=length_m).image, index, index * 33_333_333)
        for index in range(frames)
    ]


def _counting_searches(tracker: Tracker) -> dict[str, int]:
    calls = {"fast": 0, "thorough": 0}
    original = tracker.detector.detect

    def counting(image, camera=None, fast=False):
        calls["fast" if fast else "thorough"] += 1
        return original(image, camera, fast)

    tracker.detector.detect = counting
    return calls


def test_full_frame_searches_for_big_markers_are_fast_and_find_what_a_thorough_search_finds():
    # given 83 px markers, one of which vanishes (so every later frame searches the whole frame)
    camera, frames = _vanishing_marker_frames(0.05)
    found = {}
    for roi in (False, True):
        tracker = Tracker(tracker_config(roi, ids=(0, 1), roi_full_every=6, fast_search=True), camera)
        calls = _counting_searches(tracker)
        found[roi] = [sorted(tracker.process(frame).detections.ids.tolist()) for frame in frames]
        if roi:
            # then the whole-frame searches are mostly fast, with a thorough one at least every roi_full_every
            assert calls["fast"] >= 6 and 2 <= calls["thorough"] <= 4, calls
        else:
            assert calls == {"fast": 0, "thorough": len(frames)}  # (no ROI tracking: always thorough)
    # and they find the same markers in every frame
    assert found[True] == found[False]
    assert found[True][0] == [0, 1] and found[True][-1] == [0]


def test_small_markers_are_always_searched_thoroughly():
    # given 33 px markers (Aruco3's one-threshold search finds none below 32-40 px)
    camera, frames = _vanishing_marker_frames(0.02)
    tracker = Tracker(tracker_config(True, ids=(0, 1), roi_full_every=6, fast_search=True), camera)
    calls = _counting_searches(tracker)
    found = [sorted(tracker.process(frame).detections.ids.tolist()) for frame in frames]
    # then no whole-frame search is the fast one, and both markers are found while there
    assert calls["fast"] == 0 and calls["thorough"] >= len(frames) - 4, calls
    assert found[0] == [0, 1] and found[-1] == [0]


def test_a_marker_the_fast_search_misses_is_looked_for_in_its_region():
    camera, frames = _vanishing_marker_frames(0.05)
    tracker = Tracker(tracker_config(True, ids=(0, 1), roi_full_every=6, fast_search=True), camera)
    original = tracker.detector.detect
    blind = {"on": False}

    def fast_search_blind_to_marker_0(image, camera=None, fast=False):
        found = original(image, camera, fast)
        if fast and blind["on"]:  # the fast search loses marker 0 (as one threshold may, on a blurred frame)
            keep = found.ids != 0
            return MarkerDetections(found.ids[keep], found.corners[keep])
        return found

    tracker.detector.detect = fast_search_blind_to_marker_0
    for frame in frames[:6]:
        tracker.process(frame)
    blind["on"] = True
    # when the fast search misses marker 0, which the previous frame had
    result = tracker.process(frames[6])
    # then its region is searched thoroughly in the same frame, and it is found where it is
    assert result.detections.ids.tolist() == [0]
    assert "marker:0" in result.targets and result.targets["marker:0"].state.measured


def test_regions_covering_most_of_the_frame_give_way_to_the_fast_whole_frame_search():
    # given three big markers (77-114 px) spread over a VGA frame: their regions cover about half of it
    camera = CameraModel.from_fov(640, 480, 600.0)
    markers = tuple(
        PlacedMarker(i, 0.08, Pose(np.zeros(3), np.array([x, y, 0.0])))
        for i, (x, y) in enumerate([(-0.12, 0.07), (0.12, 0.07), (0.0, -0.08)])
    )
    scene = SyntheticScene(
        camera=camera, markers=markers, trajectory=Trajectory(kind="static", near_m=0.5), frames=8, noise_sigma=1.0
    )
    frames = list(SyntheticSource(scene))
    tracker = Tracker(tracker_config(True, ids=(0, 1, 2), roi_full_every=15, fast_search=True), camera)
    calls = _counting_searches(tracker)
    regions = {"calls": 0}
    original = tracker.detector.detect_regions

    def counting_regions(*args, **kwargs):
        regions["calls"] += 1
        return original(*args, **kwargs)

    tracker.detector.detect_regions = counting_regions
    found = [sorted(tracker.process(frame).detections.ids.tolist()) for frame in frames]
    # then after the first (thorough) search every frame is searched whole, fast, and no region is searched
    assert found == [[0, 1, 2]] * len(frames)
    assert calls == {"fast": len(frames) - 1, "thorough": 1} and regions["calls"] == 0, (calls, regions)


def test_the_fast_search_is_off_by_default():
    # given big markers, one of which vanishes (every later frame searches the whole frame), default settings
    camera, frames = _vanishing_marker_frames(0.05)
    tracker = Tracker(tracker_config(True, ids=(0, 1)), camera)
    calls = _counting_searches(tracker)
    for frame in frames:
        tracker.process(frame)
    # then every whole-frame search is the thorough one
    assert calls["fast"] == 0 and calls["thorough"] >= len(frames) - 4, calls
