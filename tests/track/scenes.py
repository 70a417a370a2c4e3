"""Renders that several tests of tests/track play: made once in a process and handed out read-only.

Rendering a 1280x720 frame (its sensor noise above all) costs about as much as tracking it; a view that
tests of test_roi and test_pose_truth each played again is rendered here once per frame.
"""

from __future__ import annotations

import functools

import numpy as np

from ar_anchor.camera import CameraModel
from ar_anchor.geometry import Pose
from ar_anchor.sources.base import Frame
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import PlacedMarker, SyntheticScene, Trajectory

PAIR_CAMERA = CameraModel.from_fov(1280, 720, 1000.0)
PAIR_FRAMES = 64  # the longest clip played of the view (test_roi's newly appearing marker: 52 frames)


def pair_frame(index: int, both: bool, length_m: float = 0.05) -> Frame:
    """Frame ``index`` (with its truth) of a still 1280x720 camera (fx 1000) 0.6 m from marker 0 and, when
    ``both``, marker 1 beside it (``length_m`` each; sensor noise 1 grey level). Its image is read-only.

    The camera does not move: a frame's pixels and truth are those of its index alone (its sensor noise
    is drawn from the scene's seed and the index), whatever the length of the clip, so clips of any length
    up to :data:`PAIR_FRAMES`, one marker or both in each frame, are cut from the same renders."""
    if not 0 <= index < PAIR_FRAMES:
        raise IndexError(f"frame {index} of a {PAIR_FRAMES}-frame view")
    return _pair_frame(index, both, length_m)


@functools.cache
def _pair_frame(index: int, both: bool, length_m: float) -> Frame:
    frame = _pair_source(both, length_m).frame(index)
    frame.image.flags.writeable = False  # shared between tests: none may change it
    return frame


@functools.cache
def _pair_source(both: bool, length_m: float) -> SyntheticSource:
    trajectory = Trajectory(kind="static", near_m=0.6, look_at=(0.05, 0.0, 0.0))
    one = PlacedMarker(0, length_m, Pose(np.zeros(3), np.array([-0.06, 0.0, 0.0])))
    two = PlacedMarker(1, length_m, Pose(np.zeros(3), np.array([0.16, 0.03, 0.0])))
    markers = (one, two) if both else (one,)
    scene = SyntheticScene(
        camera=PAIR_CAMERA, markers=markers, trajectory=trajectory, frames=PAIR_FRAMES, noise_sigma=1.0
    )
    return SyntheticSource(scene)
