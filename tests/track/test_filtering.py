"""The temporal filter: its maths, and scenarios with ground truth."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from ar_anchor.bench.stability import Scenario, evaluate, run_scenario
from ar_anchor.camera import CameraModel
from ar_anchor.config import FilterConfig, demo_config
from ar_anchor.geometry import Pose, angle_between_deg, marker_corners_in_marker, matrix_from_rvec
from ar_anchor.track.filtering import (
    KalmanBatch,
    RotationFilter,
    TargetTrack,
    TranslationFilter,
    pose_covariance,
    unit_covariances_of,
)
from ar_anchor.track.filtering.linear import LinearKF, predict_linear, update_linear
from ar_anchor.track.pose import MarkerPose, PoseHypothesis
from tests.helpers import mirrored

DT = 1.0 / 30.0


# ---------------------------------------------------------------------------- maths


def test_rotation_filter_learns_a_turn_rate_and_predicts_through_a_gap():
    # given a target turning at 30 deg/s about z, measured for one second
    rate = math.radians(30.0)
    rf = RotationFilter(np.eye(3), np.eye(3) * 1e-6, 1e-4, 30.0)
    for k in range(1, 31):
        rf.predict(DT)
        rf.update(matrix_from_rvec(np.array([0.0, 0.0, rate * k * DT])), np.eye(3) * 1e-6)
    # then the filter knows the rate, and predicting 10 frames ahead keeps turning
    assert rf.omega[2] == pytest.approx(rate, rel=0.05)
    for _ in range(10):
        rf.predict(DT)
    expected = matrix_from_rvec(np.array([0.0, 0.0, rate * 40 * DT]))
    assert angle_between_deg(rf.rotation, expected) < 1.0


def test_two_mode_filter_matches_filterpys_imm_step_by_step():
    # given filterpy's IMMEstimator over two KalmanFilters, set up as TwoModeCV's still and moving models
    from filterpy.kalman import IMMEstimator, KalmanFilter

    from ar_anchor.track.filtering.smoothing import TwoModeCV, cv_process_noise, cv_transition

    rng = np.random.default_rng(1)
    x0 = rng.normal(size=6)
    a = rng.normal(size=(6, 6))
    p0 = a @ a.T * 0.01 + np.eye(6) * 1e-3
    still_sigma, accel = 1e-3, 30.0
    ours = TwoModeCV(x0, p0, still_sigma, accel)
    models = []
    for _ in range(2):
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        kf.x, kf.P = x0.reshape(6, 1).copy(), p0.copy()
        models.append(kf)
    reference = IMMEstimator(models, np.array([0.5, 0.5]), np.array([[0.98, 0.02], [0.02, 0.98]]))
    # when both run the same predicts (varying dt) and updates (some frames missed; motion starting halfway)
    moving_seen = []
    for k in range(60):
        dt = DT if k % 7 else 2 * DT
        models[0].F = np.block([[np.eye(3), np.zeros((3, 3))], [np.zeros((3, 3)), np.zeros((3, 3))]])
        models[0].Q = np.block(
            [[np.eye(3) * still_sigma**2 * dt, np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3) * 1e-12]]
        )
        models[1].F, models[1].Q = cv_transition(dt), cv_process_noise(dt, accel)
        reference.predict()
        ours.predict(dt)
        if k % 5 != 4:
            z = rng.normal(size=3) * 0.01 + (0.02 * (k - 30) if k > 30 else 0.0)
            r = np.diag(rng.uniform(0.5e-4, 2e-4, 3))
            for kf in models:
                kf.R = r
            reference.update(z.reshape(3, 1))
            ours.update(z, r)
        # then state, covariance and mode probability agree to rounding, every step
        np.testing.assert_allclose(ours.x, reference.x[:, 0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ours.P, reference.P, rtol=1e-9, atol=1e-14)
        assert ours.moving_probability == pytest.approx(reference.mu[1], abs=1e-9)
        moving_seen.append(ours.moving_probability)
    # and the comparison exercised both modes
    assert min(moving_seen) < 0.2 and max(moving_seen) > 0.8


def test_rotation_filter_update_moves_toward_the_measurement_by_the_gain():
    rf = RotationFilter(np.eye(3), np.eye(3) * 1e-4, 1e-4, 30.0)
    measured = matrix_from_rvec(np.array([0.01, 0.0, 0.0]))
    rf.predict(DT)
    rf.update(measured, np.eye(3) * 1e-4)  # equal prior and measurement variance: about halfway
    angle = angle_between_deg(np.eye(3), rf.rotation)
    assert 0.2 * math.degrees(0.01) < angle < 0.8 * math.degrees(0.01)
    assert angle_between_deg(rf.rotation, measured) < math.degrees(0.01)


def test_rotation_filter_is_smooth_across_the_180_degree_wrap():
    # given measurements of a slow rotation through 180 degrees about x (rvec norm wraps at pi)
    rf = RotationFilter(matrix_from_rvec(np.array([math.radians(170), 0, 0])), np.eye(3) * 1e-4, 1e-3, 30.0)
    rng = np.random.default_rng(0)
    previous = rf.rotation
    for k in range(1, 60):
        truth = matrix_from_rvec(np.array([math.radians(170 + 0.5 * k), 0, 0]))
        noisy = truth @ matrix_from_rvec(rng.normal(0, 1e-3, 3))
        rf.predict(DT)
        rf.update(noisy, np.eye(3) * 1e-6)
        # then every step is small (no jump where the rotation vector flips sign) and it follows the truth
        assert angle_between_deg(previous, rf.rotation) < 2.0
        previous = rf.rotation
    assert angle_between_deg(rf.rotation, truth) < 1.0
    assert np.linalg.norm(matrix_from_rvec(np.array([math.radians(199.5), 0, 0])) - truth) < 1e-9


def test_rotation_filter_reset_forgets_the_past():
    rf = RotationFilter(np.eye(3), np.eye(3) * 1e-4, 1e-4, 30.0, omega=np.array([0, 0, 1.0]))
    target = matrix_from_rvec(np.array([0.0, 2.0, 0.0]))
    rf.reset(target, np.eye(3) * 1e-4)
    assert angle_between_deg(rf.rotation, target) < 1e-9
    np.testing.assert_allclose(rf.omega, 0.0)


def test_translation_filter_averages_a_static_target_and_follows_motion():
    rng = np.random.default_rng(1)
    tf = TranslationFilter(np.array([0.0, 0.0, 1.0]), np.eye(3) * 1e-4, 1e-5, 5.0)
    for _ in range(90):  # static, 1 cm noise
        tf.predict(DT)
        tf.update(np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.01, 3), np.eye(3) * 1e-4)
    assert np.linalg.norm(tf.translation - [0, 0, 1.0]) < 0.004  # much better than one measurement
    for k in range(1, 31):  # then it moves at 0.5 m/s
        tf.predict(DT)
        tf.update(np.array([0.5 * k * DT, 0.0, 1.0]), np.eye(3) * 1e-6)
    assert abs(tf.translation[0] - 0.5) < 0.02


def test_pose_covariance_grows_with_distance_and_shrinks_with_size(camera):
    points = marker_corners_in_marker(0.05)
    facing = np.diag([1.0, -1.0, -1.0])
    near = pose_covariance(Pose.from_matrix(facing, [0, 0, 0.5]), points, camera, 0.2)
    far = pose_covariance(Pose.from_matrix(facing, [0, 0, 2.0]), points, camera, 0.2)
    big = pose_covariance(Pose.from_matrix(facing, [0, 0, 2.0]), marker_corners_in_marker(0.2), camera, 0.2)
    assert np.trace(far[0]) > 4 * np.trace(near[0]) and np.trace(far[1]) > 4 * np.trace(near[1])
    assert np.trace(big[0]) < np.trace(far[0]) / 4


def test_batched_covariances_are_each_poses_own(camera):
    # given the two solutions of two markers of different sizes, and a board-like target with more points
    rng = np.random.default_rng(3)
    measurements = []
    for length, count in ((0.05, 1), (0.12, 1), (0.2, 4)):
        points = np.concatenate([marker_corners_in_marker(length) + [0.3 * k, 0, 0] for k in range(count)])
        hypotheses = tuple(
            PoseHypothesis(Pose(rng.normal(0, 0.3, 3), [rng.normal(0, 0.1), rng.normal(0, 0.1), 1.0 + k]), 0.1 + k)
            for k in range(2)
        )
        measurements.append(SimpleNamespace(points_in_target=points, hypotheses=hypotheses))  # (what is read)
    # when their covariances are computed all at once
    unit = unit_covariances_of(measurements, camera)
    # then each is the pose's own (at one pixel of noise), found by the pose object itself
    assert len(unit) == 6
    for measurement in measurements:
        for hypothesis in measurement.hypotheses:
            pose, covariance = unit[id(hypothesis.pose)]
            assert pose is hypothesis.pose
            own = pose_covariance(pose, measurement.points_in_target, camera, 0.3)
            np.testing.assert_allclose(0.09 * covariance[:3, :3], own[0], rtol=1e-9)
            np.testing.assert_allclose(0.09 * covariance[3:, 3:], own[1], rtol=1e-9)


def test_linear_filter_steps_match_filterpys_kalman_filter_for_many_filters_at_once():
    # given three of filterpy's 4-state constant-velocity filters and the same three as LinearKF
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(5)
    reference, ours = [], []
    for _ in range(3):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
        kf.x = rng.normal(size=(4, 1))
        kf.P = np.diag(rng.uniform(0.1, 1.0, 4))
        reference.append(kf)
        ours.append(LinearKF(kf.x.ravel(), kf.P, measured=2))
    for _ in range(30):
        # when each takes its own transition, process noise, measurement and measurement noise
        dts = rng.uniform(0.01, 0.2, 3)
        transitions = [np.eye(4) + np.diag([dt, dt], 2) for dt in dts]
        noises = [np.kron([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], np.eye(2)) for dt in dts]
        zs = [rng.normal(size=2) for _ in range(3)]
        rs = [np.eye(2) * rng.uniform(0.01, 0.5) for _ in range(3)]
        for kf, f, q, z, r in zip(reference, transitions, noises, zs, rs):
            kf.predict(F=f, Q=q)
            kf.update(z.reshape(2, 1), R=r)
        predict_linear(ours, transitions, noises)
        update_linear(ours, zs, rs)
        # then the states and covariances are filterpy's
        for kf, mine in zip(reference, ours):
            np.testing.assert_allclose(mine.x, kf.x.ravel(), rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(mine.P, kf.P, rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------------- the track, step by step


def hypotheses_for(truth: Pose, wrong: Pose, camera, err_true: float, err_wrong: float) -> MarkerPose:
    corners = camera.project(truth.apply(marker_corners_in_marker(0.05)))
    ordered = sorted([PoseHypothesis(truth, err_true), PoseHypothesis(wrong, err_wrong)], key=lambda h: h.reproj_px)
    ratio = (ordered[1].reproj_px + 1e-3) / (ordered[0].reproj_px + 1e-3)
    return MarkerPose(0, 0.05, corners, tuple(ordered), ratio, "ippe_square")


def flipped(pose: Pose, degrees: float = 40.0) -> Pose:
    return Pose.from_matrix(pose.rotation @ matrix_from_rvec(np.array([math.radians(degrees), 0, 0])), pose.tvec)


def test_track_commits_on_evidence_and_holds_its_branch_against_single_frame_flips(camera):
    truth = Pose.from_matrix(matrix_from_rvec(np.array([0.3, 0.2, 0.0])) @ np.diag([1.0, -1.0, -1.0]), [0, 0, 1.0])
    track = TargetTrack(FilterConfig(), marker_corners_in_marker(0.05))
    states = []
    for k in range(30):
        # the wrong solution reprojects 0.3 px worse, except in frame 20 where noise makes it look a little
        # better (not decisively: a decisive frame is shown, see test_pose_truth)
        better_wrong = k == 20
        measurement = hypotheses_for(
            truth, mirrored(truth), camera, 0.25 if better_wrong else 0.1, 0.12 if better_wrong else 0.4
        )
        update = track.update(measurement, int(k * DT * 1e9), camera)
        states.append(update.state)
        assert angle_between_deg(update.pose.rotation, truth.rotation) < 1.0  # never shows the flip
    assert states[0] == "ambiguous" and states[-1] == "tracked"
    assert "tracked" in states[:5]  # 0.3 px per frame decides within a few frames


def test_track_never_commits_below_the_bias_margin(camera):
    truth = Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), [0, 0, 3.0])
    track = TargetTrack(FilterConfig(), marker_corners_in_marker(0.05))
    for k in range(200):  # 0.03 px systematic difference: below what the corner detector's bias can fake
        update = track.update(
            hypotheses_for(truth, flipped(truth, 25.0), camera, 0.10, 0.13), int(k * DT * 1e9), camera
        )
        assert update.state == "ambiguous"


def test_track_predicts_through_a_gap_then_resets(camera):
    # a tracked (committed, vouched for) still marker: only such a target is predicted
    truth = Pose.from_matrix(matrix_from_rvec(np.array([0.3, 0.2, 0.0])) @ np.diag([1.0, -1.0, -1.0]), [0, 0, 0.5])
    config = FilterConfig(predict_s=0.1, memory_s=0.2)
    track = TargetTrack(config, marker_corners_in_marker(0.05))
    for k in range(15):
        update = track.update(hypotheses_for(truth, mirrored(truth), camera, 0.02, 1.0), int(k * DT * 1e9), camera)
    assert update.state == "tracked"
    states, alive = [], []
    for k in range(7):
        states.append(track.update(None, int((15 + k) * DT * 1e9), camera))
        alive.append(track.alive)
    # a still target is predicted for predict_s (3 frames at 30 fps) ...
    assert [s.state for s in states[:3]] == ["predicted"] * 3
    assert angle_between_deg(states[2].pose.rotation, truth.rotation) < 0.5
    # ... then nothing is published, but the track keeps its memory until memory_s (6 frames) ...
    assert states[3] is None and alive[3] and alive[5]
    # ... and is then reset
    assert states[6] is None and not alive[6]


# ---------------------------------------------------------------------------- scenarios with ground truth

CAMERA = CameraModel.from_fov(960, 540, 750.0)


def scenario_metrics(scenario: Scenario) -> dict:
    config = demo_config()
    # the raw pipeline's and the live tracker's metrics (the offline replay's, checked in test_offline, not run)
    return evaluate(run_scenario(scenario, config, CAMERA, offline=False), config)


def assert_honest_and_steady(result: dict) -> None:
    tracker = result["tracker"]
    assert tracker["wrong_tracked_pct"] == 0.0, result  # never vouches for a flipped pose
    assert tracker["twitches"] == 0, result  # never snaps by more than 10 deg in place


@pytest.mark.slow
def test_far_static_marker_says_ambiguous_and_holds_steady():
    result = scenario_metrics(Scenario("far static", 0.04, 2.6, "static", tilt_deg=15, frames=70))
    assert_honest_and_steady(result)
    assert result["tracker"]["ambiguous_pct"] > 90  # undecidable here: it says so
    assert result["tracker"]["jitter_deg"] < result["raw"]["jitter_deg"] / 3


@pytest.mark.slow
def test_nearly_fronto_parallel_wobbling_marker():
    result = scenario_metrics(Scenario("wobble", 0.05, 0.5, "wobble", frames=70))
    assert_honest_and_steady(result)
    assert result["tracker"]["flipped_pct"] <= result["raw"]["flipped_pct"]
    assert result["tracker"]["rot_median_deg"] < 2.0


@pytest.mark.slow
def test_orbiting_camera_commits_fast_and_follows_without_lag():
    result = scenario_metrics(Scenario("orbit", 0.06, 0.8, "orbit", frames=70))
    assert_honest_and_steady(result)
    tracker, raw = result["tracker"], result["raw"]
    assert tracker["frames_to_commit"] is not None and tracker["frames_to_commit"] <= 5
    assert tracker["flipped_pct"] <= 2.0 and tracker["ambiguous_pct"] <= 10.0
    assert tracker["lag_frames"] <= 2
    assert tracker["rot_median_deg"] <= raw["rot_median_deg"] + 0.1


@pytest.mark.slow
def test_dropout_is_reacquired_without_a_flip_and_never_published_blind():
    from ar_anchor.sources.synthetic import SyntheticSource
    from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory
    from ar_anchor.track.tracker import Tracker

    # given an orbiting camera (about 45 deg/s at the peak) that loses the marker for 6 frames (0.2 s)
    scene = SyntheticScene(
        camera=CAMERA,
        markers=(PlacedMarker(0, 0.06, Pose.identity()),),
        trajectory=Trajectory(kind="orbit", near_m=0.8, azimuth_deg=35, elevation_deg=15, roll_deg=10, cycles=0.4),
        frames=70,
        noise_sigma=2.0,
        blur_sigma=0.6,
        hidden=((30, 36),),
    )
    source = SyntheticSource(scene)
    config = dataclasses.replace(demo_config(), boards=())
    config = config.with_overrides(marker_length_m=0.06)
    tracker = Tracker(dataclasses.replace(config, markers=dataclasses.replace(config.markers, lengths_m={})), CAMERA)
    errors: dict[str, list[float]] = {"tracked": [], "ambiguous": [], "predicted": []}
    seen_after = 0
    for frame in source:
        target = tracker.process(frame).targets.get("marker:0")
        if target is None:
            continue
        truth = source.camera_from_world(frame.index)  # the marker is the world frame, hidden or not
        errors[target.state].append(angle_between_deg(target.pose.rotation, truth.rotation))
        seen_after += frame.index >= 36
    # then a prediction is published only while it can be trusted: none is more than 3 deg off
    assert all(error <= 3.0 for error in errors["predicted"]), errors["predicted"]
    # and the marker is picked up again on its own branch: no flip after the gap, never a wrong tracked frame
    assert seen_after == 70 - 36
    assert max(errors["tracked"] + errors["ambiguous"]) < 10.0


@pytest.mark.slow
def test_short_dropout_of_a_still_marker_is_predicted():
    # given a static camera that loses the marker for 3 frames (0.1 s, within predict_s)
    result = scenario_metrics(
        Scenario("still dropout", 0.06, 0.8, "static", tilt_deg=20, frames=70, hidden=((40, 43),))
    )
    assert_honest_and_steady(result)
    # then the gap is bridged by predictions, not dropped
    assert result["tracker"]["predicted_pct"] == pytest.approx(100 * 3 / 70, abs=0.1)


@pytest.mark.slow
def test_static_near_marker_jitter_is_far_below_raw():
    result = scenario_metrics(Scenario("static near", 0.08, 0.6, "static", tilt_deg=25, frames=70))
    assert_honest_and_steady(result)
    assert result["tracker"]["jitter_deg"] < result["raw"]["jitter_deg"] / 5


def test_no_filter_is_the_raw_pipeline(camera):
    from ar_anchor.sources.synthetic import SyntheticSource
    from ar_anchor.synthetic import demo_scene
    from ar_anchor.track.tracker import Tracker

    config = demo_config()
    raw_config = dataclasses.replace(config, filter=dataclasses.replace(config.filter, enabled=False))
    source = SyntheticSource(demo_scene(config, camera, frames=3))
    tracker = Tracker(raw_config, camera)
    states = set()
    for frame in source:
        for target in tracker.process(frame).targets.values():
            # the lower-error solution as it is, called tracked only where the frame alone decides
            assert target.pose is target.raw and target.state in ("tracked", "ambiguous")
            hyps = target.hypotheses
            if len(hyps) == 2 and hyps[1].reproj_px < 1.5 * hyps[0].reproj_px:
                assert target.state == "ambiguous"
            states.add(target.state)
    assert "tracked" in states


@pytest.mark.parametrize("key", ["evidence_window_s", "decide_margin_px", "predict_s", "memory_s"])
def test_filter_config_values_are_validated(tmp_path, key):
    from ar_anchor.config import load_config
    from ar_anchor.errors import ConfigError

    path = tmp_path / "bad.toml"
    path.write_text(f"[filter]\n{key} = -1\n")
    with pytest.raises(ConfigError, match=rf"\[filter\] {key}"):
        load_config(path)


def test_tracks_updated_in_steps_with_one_kalman_batch_give_the_same_results_as_alone(camera):
    # given three moving targets, one missing now and then (coasting) and one seen again after a gap (restart)
    rng = np.random.default_rng(7)
    config = FilterConfig()
    alone = [TargetTrack(config, marker_corners_in_marker(0.05)) for _ in range(3)]
    batched = [TargetTrack(config, marker_corners_in_marker(0.05)) for _ in range(3)]
    for k in range(60):
        measurements = []
        for index in range(3):
            truth = Pose.from_matrix(
                matrix_from_rvec(np.array([0.3 + 0.01 * k * index, 0.2, 0.05 * index])) @ np.diag([1.0, -1.0, -1.0]),
                [0.1 * index, 0.002 * k, 1.0 + 0.5 * index],
            )
            seen = not (index == 1 and k % 7 == 3) and not (index == 2 and 20 <= k < 40)
            noisy = rng.uniform(0.08, 0.12), rng.uniform(0.15, 0.5)
            measurements.append(hypotheses_for(truth, mirrored(truth), camera, *noisy) if seen else None)
        ns = int(k * DT * 1e9)
        # when one set of tracks is updated one by one, and the other in steps sharing one Kalman batch
        expected = [track.update(m, ns, camera) for track, m in zip(alone, measurements)]
        batch = KalmanBatch()
        steps = [track.update_steps(m, ns, camera, batch=batch) for track, m in zip(batched, measurements)]
        got: dict[int, object] = {}
        while len(got) < len(steps):
            for index, step in enumerate(steps):
                if index in got:
                    continue
                try:
                    next(step)
                except StopIteration as done:
                    got[index] = done.value
            batch.run()
        # then every update is the same: state, pose and events
        for index, update in enumerate(expected):
            other = got[index]
            assert (update is None) == (other is None), (k, index)
            if update is not None:
                assert update.state == other.state and update.events == other.events, (k, index)
                np.testing.assert_allclose(other.pose.rvec, update.pose.rvec, rtol=0, atol=1e-12)
                np.testing.assert_allclose(other.pose.tvec, update.pose.tvec, rtol=0, atol=1e-12)


def test_a_batch_given_to_update_is_refused_its_steps_would_never_be_taken(camera):
    track = TargetTrack(FilterConfig(), marker_corners_in_marker(0.05))
    truth = Pose.from_matrix(np.diag([1.0, -1.0, -1.0]), [0, 0, 1.0])
    with pytest.raises(ValueError, match="update_steps"):
        track.update(hypotheses_for(truth, flipped(truth), camera, 0.1, 0.4), 0, camera, batch=KalmanBatch())
