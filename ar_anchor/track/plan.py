"""The offline replay's plan (:class:`OfflinePlan`, what :func:`~ar_anchor.track.offline.decide` finds): per frame,
the measured targets' offline answers (:class:`FrameDecision`: state, chosen solution, pose), with every frame's
timestamp, blur, detail and count of measured targets, which the bridging of gaps (:mod:`.gaps`) reads too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import FilterConfig, PoseConfig
from ..geometry import Pose
from ..targets import TargetId, TrackState

__all__ = ["FrameDecision", "OfflinePlan"]


@dataclass(frozen=True)
class FrameDecision:
    """The offline answer for the measured targets of one frame (a few numbers each: the plan of a long
    recording stays small)."""

    names: tuple[TargetId, ...]
    states: tuple[TrackState, ...]
    poses: np.ndarray  # (K, 6): rvec, tvec
    choices: tuple[int, ...]  # index of the chosen solution in the frame's measurement
    causal_choices: tuple[int, ...]  # the forward (live) pass's, -1 where it published nothing
    segment_starts: tuple[bool, ...]  # the forward pass started a new track segment here (a cut, a jump, a refit)

    def pose(self, k: int) -> Pose:
        return Pose(self.poses[k, :3], self.poses[k, 3:])


@dataclass
class OfflinePlan:
    """What :func:`~.offline.decide` found: per frame position, the measured targets' offline answers (None for a
    repeated frame), and every frame's timestamp."""

    config: FilterConfig
    timestamps_ns: np.ndarray
    decided: list[FrameDecision | None]
    blurred: np.ndarray  # (frames,) bool: motion-blurred frames (no gap is bridged across one)
    detail: np.ndarray  # (frames,) each frame's fine-scale contrast (FrameResult.detail)
    measured: np.ndarray  # (frames,) how many targets each frame measured
    fit_margin_px: float = PoseConfig().fit_margin_px  # [pose] fit_margin_px: every output fits its frame

    def __len__(self) -> int:
        return len(self.decided)
