"""Benchmarks on synthetic ground truth: ``ar-anchor bench stability``.

Every scenario is rendered once and tracked once; each frame's result carries both the raw
per-frame solution (``raw``, the lower-error IPPE solution) and the tracker's output (``pose``),
so the two pipelines are compared on the very same frames. The offline replay
(:func:`ar_anchor.track.offline.smooth`, issue 20) then decides the same frames with the whole
recording: a third pipeline, ``offline``.

Scenarios
---------
The 14 calm scenarios (a lone 3-12 cm marker, static or moving on smooth synthetic paths, 720p)
are the grid the temporal filter was tuned on; a 15th, ``approach`` (a 4 cm marker the camera
approaches from 4 m to 0.5 m), is ambiguous far away and decisive near (issue 20). Issue 32 ("tracked
means right on every sequence", :func:`~.scenarios.discontinuity_scenarios`) adds scenes whose frames are not
one smooth video: ``stills`` (45 unrelated photos of a lone 8 cm marker, turned -70..+70 deg in 10-deg
steps about a vertical axis, at 0.5 m centred and at 0.3-1.5 m anywhere in the image, shuffled with a fixed
seed, played at 30 fps: camera path ``Trajectory(kind="stills")``), ``cut`` (a lone 6 cm marker, a hand-held
path cut at the middle frame to an unrelated one: ``Trajectory(kind="cut")``) and, in the full grid, the
far fronto-parallel static scene rendered sharper (noise 1, blur 0.3 px, tilt 2 deg). The hand-held
scenarios (``motion="handheld"``) look like a hand-held webcam: sway, tremor, quick turns, approach
and retreat, motion blur integrated over the exposure, rolling shutter, lighting drift and steps, a
hand crossing the markers, JPEG or H.264 compression, 5-60 fps, duplicated frames, lens distortion,
and a rigid sheet of six markers (each scored against its own truth). See
:mod:`ar_anchor.sources.synthetic` for how each effect is rendered.

The tracker is configured to track exactly the scenario's markers: lone markers of the scenario's
size (``lengths_m`` emptied), ``ids`` = the scene's ids, no boards, filter on.

Metrics (per pipeline: ``raw`` = ``TargetResult.raw``, ``tracker`` = ``TargetResult.pose``)
-----------------------------------------------------------------------------------------------
Computed per target with truth, then pooled over the scenario's targets (frames concatenated,
counts summed, longest stretch the maximum) and reported for the worst target:

- *wrong-frame rate* (``flipped_pct``): frames whose rotation error against truth exceeds
  ``FLIP_DEG`` (10 deg), among frames with an output and truth.
- *wrong tracked* (tracker only): frames the tracker calls ``tracked`` that are wrong.
- *twitches*: consecutive outputs more than 10 deg apart with less than 1 cm of motion.
- *longest stretch*: the longest run of consecutive frames in which the output is more than 10 deg
  from a *decisive* raw measurement: the raw pick is the only valid IPPE solution, or the other
  solution reprojects at least ``DECISIVE_RATIO`` times worse and ``DECISIVE_MARGIN_PX`` px worse.
  A frame without a decisive measurement ends the run. ``ignored_run`` is the gap-tolerant variant:
  frames without a decisive measurement neither extend nor end it (it counts decisive
  measurements the output disagreed with in a row). ``decisive_wrong``: decisive raw
  measurements that are themselves more than 10 deg from truth (blur, compression: a decisive
  measurement is not always right, so a stretch is a symptom to look at, not proof of a fault).
- *predicted error*: median and p95 rotation error of ``predicted`` rows (the tracker's output
  while the target is not measured).
- *sheet disagreement* (scenarios with a sheet of markers): frames where two markers of the rigid
  sheet disagree in rotation by more than 10 deg (every marker of a flat sheet has the same true
  rotation), per pipeline.
- *misfit rows* (issue 32, :func:`~.metrics.misfit_rows`; tracker and offline): measured rows (``tracked``
  or ``ambiguous``, with this frame's solutions) whose output reprojects on that frame's own corners
  (``TargetResult.reproj_px``) worse than :func:`ar_anchor.track.fit.fit_bound_px` of the frame's best
  solution's error (``hypotheses[0].reproj_px``) and ``[pose] fit_margin_px`` (recorded per frame in
  :class:`TargetSeries`: ``reproj_px``, ``fit_bound_px``); ``misfit_worst_px``: the largest excess.
- jitter (static scenes), lag (moving), the tracker's states, as before.

Acceptance (the ``pass`` column; ``ACCEPTANCE``): for every target the tracker's wrong-frame rate is
at most the raw pipeline's + 0.2 points, no wrong tracked frame, no twitch, longest stretch <= 3,
predicted median <= 3 deg and p95 <= 10 deg, no misfit row (issue 32).

Offline replay (``offline``: the same metrics as the tracker's, with ``interpolated_pct`` and a signed
lag, negative when the output leads the truth): its acceptance (:func:`offline_acceptance`,
``OFFLINE_ACCEPTANCE``, issue 20) against the causal tracker: wrong-frame rate at most the causal's, no
wrong tracked frame, no misfit row (issue 32), static jitter at most the causal's, |lag| <= 0.5 frame on
moving scenarios, fewer
ambiguous frames wherever the scenario decides at some point, none tracked where it is undecidable.

Modules: :mod:`.scenarios` (what is rendered), :mod:`.run` (render and track one scenario),
:mod:`.metrics` (per-target metrics), :mod:`.evaluation` (pooled metrics and the acceptance),
:mod:`.report` (``stability.md`` and ``stability.json``). ``FLIP_DEG`` and ``SETTLE_FRAMES`` are
:mod:`ar_anchor.bench.report`'s.
"""

from __future__ import annotations

from ..report import FLIP_DEG, SETTLE_FRAMES
from .evaluation import ACCEPTANCE, OFFLINE_ACCEPTANCE, acceptance, evaluate, offline_acceptance
from .metrics import (
    DECISIVE_MARGIN_PX,
    DECISIVE_RATIO,
    ambiguous_vs_raw,
    fractional_lag,
    is_decisive,
    lag_frames,
    longest_stretch,
    misfit_rows,
    predicted_error_stats,
    wrong_tracked,
)
from .report import acceptance_table, offline_table, stability_markdown, stability_table, write_stability_report
from .run import ScenarioRun, TargetSeries, run_scenario
from .scenarios import Scenario, discontinuity_scenarios, handheld_scenarios, stability_scenarios

__all__ = [
    "ACCEPTANCE",
    "DECISIVE_MARGIN_PX",
    "DECISIVE_RATIO",
    "FLIP_DEG",
    "OFFLINE_ACCEPTANCE",
    "SETTLE_FRAMES",
    "Scenario",
    "ScenarioRun",
    "TargetSeries",
    "acceptance",
    "acceptance_table",
    "ambiguous_vs_raw",
    "evaluate",
    "handheld_scenarios",
    "is_decisive",
    "discontinuity_scenarios",
    "fractional_lag",
    "lag_frames",
    "longest_stretch",
    "misfit_rows",
    "offline_acceptance",
    "offline_table",
    "predicted_error_stats",
    "run_scenario",
    "stability_markdown",
    "stability_scenarios",
    "stability_table",
    "wrong_tracked",
    "write_stability_report",
]
