"""The tracker's tracks, one flip-filter track (:class:`~ar_anchor.track.filtering.TargetTrack`) per target, and
their bookkeeping: every track updated for a frame, the numeric steps of all of them taken at once
(:func:`update_tracks`, also the offline replay's backward pass), each output checked against its own frame and
its track restarted where the output is replaced (:func:`fit_to_frame`), the tracks a cut ends
(:func:`end_at_a_cut`), and a learned group's track warmed from the frames before it formed, or ended when the
group is gone (:func:`warm_group_track`, :func:`end_group_tracks`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Generator
from typing import Any

from ..camera import CameraModel
from ..config import FilterConfig, TrackerConfig
from ..sources.base import Frame
from ..targets import TargetId
from .filtering import SEGMENT_STARTS, KalmanBatch, TargetTrack, TrackUpdate, unit_covariances_of
from .fit import refit
from .groups import GroupLearner
from .pose import BoardPose, MarkerPose
from .results import TargetResult

__all__ = ["end_at_a_cut", "end_group_tracks", "fit_to_frame", "run_filter_steps", "update_tracks", "warm_group_track"]

log = logging.getLogger(__name__)


def update_tracks(
    tracks: dict[TargetId, TargetTrack],
    measured: dict[TargetId, MarkerPose | BoardPose],
    timestamp_ns: int,
    camera: CameraModel,
    blurred: bool,
    config: FilterConfig,
) -> dict[TargetId, TrackUpdate | None]:
    """Every track's update for one frame (a track started for a target measured for the first time; one
    lost for good removed), in :class:`TargetId` order, the numeric steps taken for all targets at once:
    the pose covariances (:func:`~.filtering.unit_covariances_of`) and the smoothers' Kalman steps (each
    track's update runs as steps, :meth:`~.filtering.TargetTrack.update_steps`, paused while a
    :class:`KalmanBatch` takes the steps they queued). The live tracker's, and the offline replay's
    backward pass's (:mod:`ar_anchor.track.offline`)."""
    unit = unit_covariances_of(list(measured.values()), camera)
    batch = KalmanBatch()
    steps = {}
    for name in TargetId.ordered(set(measured) | set(tracks)):
        solved = measured.get(name)
        track = tracks.get(name)
        if track is None:
            assert solved is not None
            track = tracks[name] = TargetTrack(config, solved.points_in_target)
        steps[name] = track.update_steps(
            solved, timestamp_ns, camera, blurred=blurred, unit_covariances=unit, batch=batch
        )
    updates = run_filter_steps(steps, batch)
    for name, update in updates.items():
        if update is None and not tracks[name].alive:
            del tracks[name]
    return {name: updates[name] for name in steps}


def run_filter_steps(steps: dict[TargetId, Generator[None, None, Any]], batch: KalmanBatch) -> dict[TargetId, Any]:
    """Advance every generator a step at a time, taking ``batch``'s queued steps after each round; their
    return values, by name."""
    results: dict[TargetId, Any] = {}
    pending = dict(steps)
    while pending:
        for name, generator in list(pending.items()):
            try:
                next(generator)
            except StopIteration as done:
                results[name] = done.value
                del pending[name]
        batch.run()
    return results


def fit_to_frame(
    tracks: dict[TargetId, TargetTrack],
    targets: dict[TargetId, TargetResult],
    measured: dict[TargetId, MarkerPose | BoardPose],
    frame: Frame,
    camera: CameraModel,
    blurred: bool,
    config: TrackerConfig,
) -> dict[TargetId, TargetResult]:
    """Every measured output checked against its own frame (:func:`~.fit.refit`): one that misses the
    frame's corners is moved just enough to fit (a spike held back, a lag) or, held over a cut or on the
    other solution, replaced by the frame's own best solution, and the target's track restarts from it."""
    for name, target in targets.items():
        solved = measured.get(name)
        fitted = None if solved is None else refit(target, solved, camera, config.filter, config.pose.fit_margin_px)
        if fitted is None:
            continue
        assert solved is not None
        replaced, restart = fitted
        log.info("frame %d: %s: %s", frame.index, name, replaced.events[-1].message)
        track = tracks.get(name)
        if restart and track is not None:
            started = track.restart_from(solved, frame.timestamp_ns, camera, blurred=blurred)
            replaced = dataclasses.replace(replaced, events=(*replaced.events, *started))
        targets[name] = replaced
    return targets


def end_at_a_cut(
    tracks: dict[TargetId, TargetTrack], targets: dict[TargetId, TargetResult], index: int
) -> dict[TargetId, TargetResult]:
    """A cut (every target measured this frame whose track went on from earlier frames jumped: see
    :meth:`~.filtering.TargetTrack.update_steps`, event ``jump``; at least one): the tracks of the targets
    not seen in it end too, and none is predicted: their poses belong to the scene before the cut."""
    measured = [target for target in targets.values() if target.measured]
    jumped = [t for t in measured if any(event.kind == "jump" for event in t.events)]
    went_on = [t for t in measured if not any(event.kind in SEGMENT_STARTS for event in t.events)]
    if not jumped or went_on:
        return targets
    ended = sorted(name for name in tracks if name not in targets or not targets[name].measured)
    for name in ended:
        del tracks[name]
    if ended:
        log.info("frame %d: a cut (every target seen jumped): the tracks of %s end", index, ", ".join(map(str, ended)))
    return {name: target for name, target in targets.items() if target.measured}


def warm_group_track(
    tracks: dict[TargetId, TargetTrack], groups: GroupLearner, name: TargetId, config: FilterConfig
) -> str:
    """A group formed or grown this frame starts from the frames the learner kept (the last
    ``[filter] evidence_window_s``), not from nothing: a planar group's layout is first refined from
    them (:meth:`~.groups.GroupLearner.refine_from_past`), then its flip filter is replayed over its
    joint pose in each (:meth:`~.groups.GroupLearner.past_solves`). Far away, a layout straight from
    pair evidence tips the flip evidence the wrong way, and a filter started now shows its first
    frames' coin-toss pick, where the frames before already hold the evidence. Returns the event's text."""
    refined = groups.refine_from_past(name)
    track: TargetTrack | None = None
    frames = 0
    for past, solved in groups.past_solves(name):
        if track is None and solved is None:
            continue
        if track is None:
            assert solved is not None
            track = TargetTrack(config, solved.points_in_target)
        track.update(solved, past.timestamp_ns, past.camera, blurred=past.blurred)
        frames += solved is not None
    tracks.pop(name, None)
    layout = f"its layout refined from {refined} earlier frames; " if refined else ""
    if track is None:
        return f"{layout}its flip filter starts now (no earlier frame of its markers kept)"
    tracks[name] = track
    decided = "decided" if track.committed is not None else "undecided"
    return f"{layout}its flip filter replayed over the {frames} earlier frames that solve it (flip {decided})"


def end_group_tracks(tracks: dict[TargetId, TargetTrack], groups: GroupLearner, configured: set[TargetId]) -> None:
    """Forget the tracks of learned groups that are gone (merged into another, or dissolved)."""
    for name in [n for n in tracks if n.is_board and n not in configured and n not in groups.groups]:
        del tracks[name]
