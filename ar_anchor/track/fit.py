"""Does an output fit its own frame? The one check every measured output passes before it is published.

Whatever a temporal layer believes (the causal flip filter, the offline replay's two passes, a board's
joint pose, a learned group's pose given to its members), an output published for a frame in which the
target was measured must explain that frame's corners: its RMS reprojection error on them may exceed
the frame's own best solution's by at most ``[pose] fit_margin_px``. Smoothing stays far inside that
(the output is held within a few standard deviations of the measurement: tenths of a pixel); a pose
held over from another view, a prediction across a cut, or a smoother that lagged a jump does not.
An output that does not fit is moved towards the frame's own best solution just far enough to fit, when
it stood on that solution's side and the move is small (a spike held back, a lag: the filter's answer,
corrected); else it is replaced by that solution (``tracked`` only when the frame alone decides the planar
flip) and the causal track restarts from it (:func:`refit`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from ..camera import CameraModel
from ..config import FilterConfig
from ..geometry import Pose, angle_between_deg
from ..targets import TrackState
from .filtering import TrackEvent, decided_alone, so3_exp, so3_log
from .pose import BoardPose, MarkerPose, reprojection_rms

if TYPE_CHECKING:
    from .results import TargetResult

__all__ = ["fit_bound_px", "misfit_px", "refit"]


def fit_bound_px(raw_px: float, margin_px: float) -> float:
    """The largest RMS reprojection error an output may have on a frame whose own best solution has
    ``raw_px``: ``raw_px + margin_px``."""
    return raw_px + margin_px


def misfit_px(pose: Pose, measurement: MarkerPose | BoardPose, camera: CameraModel, margin_px: float) -> float | None:
    """``pose``'s RMS reprojection error on ``measurement``'s points when it exceeds the bound
    (:func:`fit_bound_px` of the measurement's best solution), else None (it fits). A pose that cannot
    be projected (behind the camera, not finite) does not fit (its error is then ``inf``)."""
    error = reprojection_rms(pose, measurement.points_in_target, measurement.points_in_image, camera)
    if not math.isfinite(error):
        return math.inf
    return error if error > fit_bound_px(measurement.best.reproj_px, margin_px) else None


def refit(
    target: TargetResult,
    measurement: MarkerPose | BoardPose,
    camera: CameraModel,
    config: FilterConfig,
    margin_px: float,
) -> tuple[TargetResult, bool] | None:
    """``target`` (a measured output of this frame) made to fit the frame's corners when it does not
    (:func:`misfit_px` with ``margin_px``, ``[pose] fit_margin_px``); None when it fits. Returns the new
    result and whether the track must restart from it:

    - **pulled**: the output moved along the geodesic towards the frame's own best solution just far
      enough to fit (a bisection), when that moves it by at most ``reset_angle_deg`` and it stood on that
      solution's side (nearer it than the other solution): the filter's answer, corrected by what the frame
      shows (a spike held back, a smoother that lagged a turn). State kept, event ``fitted``; no restart.
    - **replaced**: otherwise (a pose held over a cut or from another photo, the other solution): the
      frame's own best solution, ``tracked`` only when the frame alone decides the planar flip
      (:func:`~.filtering.decided_alone`), else ``ambiguous``; event ``refit``; the caller restarts the
      causal track from it."""
    if not target.measured:
        return None
    error = misfit_px(target.pose, measurement, camera, margin_px)
    if error is None:
        return None
    best = measurement.best
    bound = fit_bound_px(best.reproj_px, margin_px)
    pulled, moved_deg = _pulled(target.pose, best.pose, measurement, camera, bound)
    others = [h.pose for h in measurement.hypotheses[1:]]
    beside = all(
        angle_between_deg(target.pose.rotation, best.pose.rotation)
        <= angle_between_deg(target.pose.rotation, other.rotation)
        for other in others
    )
    if beside and moved_deg <= config.reset_angle_deg:
        event = TrackEvent(
            "fitted",
            f"the output missed this frame's corners by {error:.2f} px RMS (its own solution: {best.reproj_px:.2f} "
            f"px): moved {moved_deg:.1f} deg towards that solution, to fit",
        )
        reproj = reprojection_rms(pulled, measurement.points_in_target, measurement.points_in_image, camera)
        return dataclasses.replace(target, pose=pulled, reproj_px=reproj, events=(*target.events, event)), False
    sure = decided_alone(measurement.hypotheses, config, len(measurement.points_in_target))
    event = TrackEvent(
        "refit",
        f"the {target.state.value} output missed this frame's corners by {error:.2f} px RMS (its own solution: "
        f"{best.reproj_px:.2f} px): this frame's own solution is output, the track restarts from it",
    )
    replaced = dataclasses.replace(
        target,
        state=TrackState.TRACKED if sure else TrackState.AMBIGUOUS,
        pose=best.pose,
        reproj_px=best.reproj_px,
        events=(*target.events, event),
        doubts=() if sure else ("refit",),
        committed=False,
        branch=-1,
        run_frames=1,
    )
    return replaced, True


_BISECTIONS = 12  # the pull's fraction to 1/4096 of the way


def _pulled(
    pose: Pose, best: Pose, measurement: MarkerPose | BoardPose, camera: CameraModel, bound_px: float
) -> tuple[Pose, float]:
    """The pose on the way from ``pose`` to ``best`` (rotation on the geodesic, translation on the straight
    line) nearest ``pose`` that reprojects on the measurement's points within ``bound_px`` (``best`` itself
    does), and how far it turned from ``pose`` (deg)."""
    turn = so3_log(pose.rotation.T @ best.rotation)

    def at(fraction: float) -> Pose:
        rotation = pose.rotation @ so3_exp(fraction * turn)
        return Pose.from_matrix(rotation, pose.tvec + fraction * (best.tvec - pose.tvec))

    low, high = 0.0, 1.0  # low misses, high fits
    for _ in range(_BISECTIONS):
        middle = 0.5 * (low + high)
        error = reprojection_rms(at(middle), measurement.points_in_target, measurement.points_in_image, camera)
        if math.isfinite(error) and error <= bound_px:
            high = middle
        else:
            low = middle
    return at(high), math.degrees(high * float(np.linalg.norm(turn)))
