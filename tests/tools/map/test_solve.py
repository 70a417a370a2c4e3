"""The map solver on observations projected from known poses (no rendering: fast): it recovers the layout,
does not trust a single frame (the planar flip), ignores misread ids and moved markers, and says why it
cannot build a map."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ar_anchor.errors import InputError
from ar_anchor.tools.map import aligned_errors, build_map, rms_m

from .scenes import WEBCAM, observe, sheet_cameras, sheet_markers, truth_corners

LENGTH_M = 0.05


def sheet_frames(count: int = 40, *, seed: int = 0, noise_px: float = 0.3, far: bool = False):
    rng = np.random.default_rng(seed)
    markers = sheet_markers(length_m=LENGTH_M)
    target = np.mean([p.tvec for p in markers.values()], axis=0)
    cameras = sheet_cameras(count, rng, target)
    if far:  # 1.3-1.9 m away: each 5 cm marker alone is ambiguous (its two IPPE poses reproject alike)
        cameras = [dataclasses.replace(c, tvec=c.tvec * (1.3 / 0.5) * rng.uniform(1.0, 1.45)) for c in cameras]
    return markers, observe(markers, cameras, WEBCAM, LENGTH_M, noise_px=noise_px, rng=rng)


def map_error_mm(solution, markers) -> float:
    _, residuals = aligned_errors(solution.map.all_corners(), truth_corners(markers, LENGTH_M))
    return 1000.0 * rms_m(residuals)


def test_sheet_is_recovered_with_its_uncertainty():
    # given 40 views of 8 markers, corners with 0.3 px noise
    markers, frames = sheet_frames()
    # when mapped
    solution = build_map(frames, [WEBCAM], LENGTH_M)
    # then every marker is mapped within 0.3 mm RMS, reprojection is at the noise level
    assert solution.map.ids == sorted(markers)
    assert map_error_mm(solution, markers) < 0.3
    assert solution.rms_px == pytest.approx(0.3 * np.sqrt(2), rel=0.2)
    assert not solution.dropped and not solution.unplaced
    # and each marker's uncertainty is small, finite, zero for the reference only
    sigmas = solution.map.sigma_mm
    assert sigmas[solution.map.reference_id] == 0.0
    others = [s for m, s in sigmas.items() if m != solution.map.reference_id]
    assert len(others) == 7 and all(0.005 < s < 1.0 for s in others)


def test_ambiguous_views_are_outvoted_not_trusted():
    # given far views: every marker alone has two plausible poses (ambiguity near 1)
    markers, frames = sheet_frames(60, seed=3, far=True)
    ratios = np.concatenate([f.ambiguity for f in frames])
    assert np.nanmedian(ratios) < 3.0
    # when mapped, then the layout is still right (no flipped marker: a flip would be centimetres off)
    solution = build_map(frames, [WEBCAM], LENGTH_M)
    assert solution.map.ids == sorted(markers)
    assert map_error_mm(solution, markers) < 2.0


def test_misread_ids_and_moved_markers_do_not_move_the_map():
    # given the clean views, and the same views where some detections lie
    markers, clean = sheet_frames(seed=5)
    reference = build_map(clean, [WEBCAM], LENGTH_M)
    frames = list(clean)
    rng = np.random.default_rng(9)
    lied = 0
    for index in rng.choice(len(frames), 10, replace=False):
        frame = frames[index]
        ids, corners = frame.ids.copy(), frame.corners.copy()
        k = int(rng.integers(len(ids)))
        if index % 2:
            others = [i for i in markers if i not in ids]
            if others:
                ids[k] = others[0]  # a misread id: another marker of the sheet, not in view
            else:
                j = (k + 1) % len(ids)
                ids[k], ids[j] = ids[j], ids[k]  # two ids read the wrong way round
        else:
            corners[k] += rng.normal(0.0, 8.0, 2)  # a marker's corners 8 px off (a smeared detection)
        frames[index] = dataclasses.replace(frame, ids=ids, corners=corners)
        lied += 1
    # and an id that is no marker of the sheet, seen twice
    spurious = dataclasses.replace(frames[0], ids=np.where(frames[0].ids == frames[0].ids[0], 99, frames[0].ids))
    frames[0] = spurious
    frames[1] = dataclasses.replace(frames[1], ids=np.where(frames[1].ids == frames[1].ids[0], 99, frames[1].ids))
    # when mapped
    solution = build_map(frames, [WEBCAM], LENGTH_M)
    # then the lies are dropped or never placed, and the map is where the clean one is
    assert solution.map.ids == sorted(markers)
    assert 99 in solution.unplaced
    assert lied == 10 and len(solution.dropped) >= lied - 2
    assert map_error_mm(solution, markers) < 0.4
    _, moved = aligned_errors(solution.map.all_corners(), reference.map.all_corners())
    assert 1000.0 * rms_m(moved) < 0.2
    assert solution.rms_px < 0.6


def test_origin_sets_the_map_frame():
    markers, frames = sheet_frames(20, seed=2)
    solution = build_map(frames, [WEBCAM], LENGTH_M, origin=6)
    assert solution.map.reference_id == 6
    pose = solution.map.world_from_marker[6]
    assert np.allclose(pose.tvec, 0.0) and np.allclose(pose.rvec, 0.0)
    with pytest.raises(InputError, match="--origin 77: marker 77 is never seen"):
        build_map(frames, [WEBCAM], LENGTH_M, origin=77)


def test_fewer_than_two_markers_together_is_a_clear_error():
    markers, frames = sheet_frames(5, seed=1)
    lonely = [dataclasses.replace(f, ids=np.full(len(f), 4)) for f in frames[:1]]
    with pytest.raises(InputError, match="fewer than two markers were ever seen together"):
        build_map(lonely, [WEBCAM], LENGTH_M)
    with pytest.raises(InputError, match="fewer than two markers"):
        build_map([], [WEBCAM], LENGTH_M)


def test_bundle_adjustment_jacobian_matches_finite_differences(monkeypatch):
    # given the bundle adjustment's residual function and analytic Jacobian, caught on their way to scipy
    from ar_anchor.tools.map import adjust, initialise, problem

    captured = {}
    real = adjust.least_squares

    def spy(fun, x0, jac="2-point", **options):
        captured.update(fun=fun, jac=jac, x0=x0)
        return real(fun, x0, jac=jac, **options)

    monkeypatch.setattr(adjust, "least_squares", spy)
    _, frames = sheet_frames(6, seed=4)
    prob = problem.Problem(frames, [WEBCAM], LENGTH_M)
    initial = initialise.initialise(prob)
    adjust.bundle_adjust(prob, initial.world_from_marker, initial.camera_from_world, initial.reference_id, max_nfev=1)
    fun, jac = captured["fun"], captured["jac"]
    # when evaluated away from the start (rotation increments of about 0.02 rad, translations moved 5 mm)
    rng = np.random.default_rng(0)
    x = captured["x0"] + rng.normal(0.0, 0.01, captured["x0"].shape)
    analytic = jac(x).toarray()
    numeric = np.empty_like(analytic)
    for i in range(len(x)):
        step = np.zeros_like(x)
        step[i] = 1e-6
        numeric[:, i] = (fun(x + step) - fun(x - step)) / 2e-6
    # then they agree to a part in 10^5 of the largest derivative
    assert np.abs(analytic - numeric).max() < 1e-5 * np.abs(numeric).max()
