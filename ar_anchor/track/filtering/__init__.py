"""Temporal filtering: resolve the planar flip with evidence over time, and smooth the pose, without
ever making the pose worse than the per-frame measurements it is fed.

Per target, a :class:`TargetTrack` carries

* **two branches**, one per IPPE solution. The two solutions of a square are mirror images through
  the line of sight (their normals' tilts away from it are opposite), so a small Kalman filter on
  branch 0's tilt (:class:`_TiltTracker`) tells which solution continues which branch, through
  crossings too (a view through fronto-parallel). It cannot go blind: unclear frames update it with
  inflated noise, its rate and uncertainty are bounded, and after a gap it restarts at rest from the
  branch's last measured orientation. Where the branch smoothers' own motion prediction contradicts
  the tilt's assignment, the frame's assignment is in doubt: no evidence is taken from it and
  nothing is vouched for.
* **evidence** for branch 0 against branch 1 over ``evidence_window_s``: per frame, the difference of
  their RMS reprojection errors. A branch is *committed* only when the window's mean difference
  exceeds ``decide_margin_px`` with ``decide_z`` standard errors of confidence. The margin is there
  because a corner detector's own bias (a few hundredths of a pixel) differs systematically between
  the branches too: evidence below it never decides, however long one waits. Such a target stays
  ``ambiguous``, and its output is a best guess that follows the per-frame pick's tendency without
  its flicker. A committed branch moves on sustained evidence (``switch_margin_px``, ``switch_z``) or,
  self-correcting, on ``decisive_frames`` frames that contradict it (the first one *decisive*: the
  other solution alone, or much better by ``decisive_ratio`` and ``decisive_sigmas``).
* a **smoother** per branch: an error-state Kalman filter on SO(3) (rotation error as a body-frame
  rotation vector, so no Euler angles and no trouble near 180 degrees) and, shared, one on
  translation, each an IMM (``filterpy``'s steps, taken for all of a frame's targets at once:
  :class:`KalmanBatch`) of a *still* model that averages a static marker over many
  frames and a *moving* constant-velocity model. Measurement noise is the pose covariance implied by
  the corner noise through the projection Jacobian (it grows with distance and shrinks with marker
  size in pixels; the corner noise is estimated online, and a blurred frame's larger residuals make
  its own measurement count less). No measurement is rejected: a smoother it lands far from restarts
  from it. The output is held within ``output_sigmas`` standard deviations of this frame's
  measurement (``output_sigmas_moving`` unless the measurements stayed put for ``still_s``), so
  smoothing lowers jitter but cannot lag behind real motion.
* **dropouts**: a missed frame is predicted (state ``predicted``, velocity decaying with
  ``predict_damping_s``) for at most ``predict_s`` and only while the motion since the last
  measurement may have moved the target less than ``predict_max_deg``; then nothing is published, but
  the track keeps its branches and evidence for ``memory_s``: a target that returns is not new.

``tracked`` is only said of the committed branch, measured this frame as the lower-error solution,
with no contradicting frame open, no doubt about the assignment, and an orientation whose 3-sigma
uncertainty is below ``flip_angle_deg``. All time constants are in seconds.

The package: :mod:`.smoothing` (the SO(3) and translation smoothers), :mod:`.noise` (the corner noise
and the pose covariance it implies), :mod:`.branches` (the two branches and the tilt tracker that
assigns each frame's solutions to them), :mod:`.evidence` (the evidence, the commitment, an undecided
target's best guess) and :mod:`.track` (:class:`TargetTrack`, which puts them together frame by frame).
"""

from .evidence import TrackEvent, decided_alone, decisive, margin_scale
from .noise import pose_covariance, unit_covariances_of
from .smoothing import KalmanBatch, RotationFilter, TranslationFilter, so3_exp, so3_log
from .track import SEGMENT_STARTS, TargetTrack, TrackUpdate

__all__ = [
    "SEGMENT_STARTS",
    "KalmanBatch",
    "RotationFilter",
    "TargetTrack",
    "TrackEvent",
    "TrackUpdate",
    "TranslationFilter",
    "decided_alone",
    "decisive",
    "margin_scale",
    "pose_covariance",
    "so3_exp",
    "so3_log",
    "unit_covariances_of",
]
