"""One scenario rendered and tracked once: per-frame records of the raw measurement and of the
tracker's output, side by side, for every target with truth."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from ...camera import CameraModel
from ...config import PoseConfig, TrackerConfig
from ...geometry import Pose
from ...sources.synthetic import SyntheticSource
from ...targets import TargetId
from ...track.detection import Detector
from ...track.fit import fit_bound_px
from ...track.offline import smooth
from ...track.tracker import Tracker
from .metrics import is_decisive
from .scenarios import Scenario

__all__ = ["ScenarioRun", "TargetSeries", "run_scenario"]


@dataclass
class TargetSeries:
    """Per-frame records of one target (None / NaN / "" where there is nothing)."""

    truth: list[Pose | None] = field(default_factory=list)
    raw: list[Pose | None] = field(default_factory=list)
    output: list[Pose | None] = field(default_factory=list)
    state: list[str] = field(default_factory=list)  # "" when no output
    delta_px: list[float] = field(default_factory=list)  # worse - better IPPE reprojection error
    decisive: list[bool] = field(default_factory=list)  # the raw measurement is decisive (see is_decisive)
    # issue 32: does a measured output fit its own frame? (NaN where the row is not measured with hypotheses)
    reproj_px: list[float] = field(default_factory=list)  # the output's RMS error on this frame's corners
    fit_bound_px: list[float] = field(default_factory=list)  # track.fit.fit_bound_px(best solution's, margin)

    def append(self, target: Any, truth: Pose | None, fit_margin_px: float | None = None) -> None:
        """Record one frame's ``TargetResult`` (or None) and truth. ``fit_margin_px``: ``[pose]
        fit_margin_px`` of the tracker's config (default: the config default), for the fit bound."""
        self.truth.append(truth)
        self.raw.append(target.raw if target is not None else None)
        self.output.append(target.pose if target is not None else None)
        self.state.append(target.state if target is not None else "")
        hyps = tuple(target.hypotheses) if target is not None else ()
        self.delta_px.append(hyps[1].reproj_px - hyps[0].reproj_px if len(hyps) == 2 else math.nan)
        self.decisive.append(target is not None and target.raw is not None and is_decisive(hyps))
        if target is not None and target.measured and hyps:
            margin = PoseConfig().fit_margin_px if fit_margin_px is None else fit_margin_px
            self.reproj_px.append(float(target.reproj_px))
            self.fit_bound_px.append(fit_bound_px(float(hyps[0].reproj_px), margin))
        else:
            self.reproj_px.append(math.nan)
            self.fit_bound_px.append(math.nan)


@dataclass
class ScenarioRun:
    """Per-frame records of one scenario: one :class:`TargetSeries` per target with truth.

    ``truth``, ``raw``, ``output``, ``state`` and ``delta_px`` are the first target's (a lone-marker
    scenario's only target)."""

    scenario: Scenario
    targets: dict[str, TargetSeries] = field(default_factory=dict)
    track_ms: list[float] = field(default_factory=list)
    render_s: float = 0.0
    track_s: float = 0.0
    offline: dict[str, TargetSeries] = field(default_factory=dict)  # the offline replay's (track.offline)
    full_frame_found: int = 0  # marker-frames of tracked ids a full-frame search finds on the same frames ...
    roi_missed: int = 0  # ... and how many of those the tracker (ROI tracking on) did not find

    def _first(self) -> TargetSeries:
        return next(iter(self.targets.values())) if self.targets else TargetSeries()

    @property
    def truth(self) -> list[Pose | None]:
        return self._first().truth

    @property
    def raw(self) -> list[Pose | None]:
        return self._first().raw

    @property
    def output(self) -> list[Pose | None]:
        return self._first().output

    @property
    def state(self) -> list[str]:
        return self._first().state

    @property
    def delta_px(self) -> list[float]:
        return self._first().delta_px


def run_scenario(scenario: Scenario, config: TrackerConfig, camera: CameraModel, offline: bool = True) -> ScenarioRun:
    """Render and track a scenario with ``config`` (its filter on, tracking exactly the scene's markers).

    ``camera`` is the default camera (a scenario may ask for its own); the tracker gets the same
    camera model as the renderer (with its distortion). ``offline``: also the offline replay's answer
    (:func:`~ar_anchor.track.offline.smooth`) over the same frames, in :attr:`ScenarioRun.offline`."""
    camera = scenario.camera_model(camera)
    source = SyntheticSource(scenario.scene(camera, config.detector.dictionary))
    tracker = Tracker(scenario.tracker_config(config), camera)
    full_frame = Detector(tracker.config.detector)  # what full-frame detection finds, for the ROI count
    margin = tracker.config.pose.fit_margin_px
    names = [TargetId.marker(i) for i in scenario.marker_ids]
    run = ScenarioRun(scenario, {name: TargetSeries() for name in names})
    frames = iter(source)
    results, truths = [], []
    while True:
        start = time.perf_counter()
        frame = next(frames, None)
        run.render_s += time.perf_counter() - start
        if frame is None:
            break
        start = time.perf_counter()
        result = tracker.process(frame)
        elapsed = time.perf_counter() - start
        run.track_s += elapsed
        run.track_ms.append(elapsed * 1e3)
        truth = frame.truth or {}
        for name, series in run.targets.items():
            series.append(result.targets.get(name), truth.get(name), margin)
        results.append(result)
        truths.append(truth)
        everywhere = {i for i in full_frame.detect(frame.image, camera).ids.tolist() if tracker.config.tracks_marker(i)}
        run.full_frame_found += len(everywhere)
        run.roi_missed += len(everywhere - set(result.detections.ids.tolist()))
    if offline:
        run.offline = {name: TargetSeries() for name in names}
        for result, truth in zip(smooth(results, tracker.config), truths):
            for name, series in run.offline.items():
                series.append(result.targets.get(name), truth.get(name), margin)
    # targets never in view have nothing to score
    run.targets = {name: s for name, s in run.targets.items() if any(t is not None for t in s.truth)} or run.targets
    run.offline = {name: s for name, s in run.offline.items() if name in run.targets}
    return run
