"""The synthetic scene as a frame source: :class:`SyntheticSource` renders a
:class:`~ar_anchor.synthetic.scene.SyntheticScene` frame by frame, each with its exact ground truth.

What is in the scene and how it moves is :mod:`ar_anchor.synthetic.scene` (and
:mod:`~ar_anchor.synthetic.trajectory`); how its camera renders it is :mod:`ar_anchor.synthetic.render`.
This adapter adds the container: frame indices and timestamps, duplicated frames (``content_fps``),
dropouts (``hidden``), and the H.264 round trip, which is sequential over the clip.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..camera import CameraModel
from ..geometry import Pose
from ..synthetic.render import H264RoundTrip, Renderer
from ..synthetic.scene import SyntheticScene
from .base import ClosingSource, Frame, SourceInfo

__all__ = ["SyntheticSource"]


class SyntheticSource(ClosingSource):
    """Renders :class:`SyntheticScene` frames with per-frame ground truth (a :class:`FrameSource`)."""

    def __init__(self, scene: SyntheticScene) -> None:
        self.scene = scene
        self._renderer = Renderer(scene)
        self._closed = False
        # the last rendered content frame: (content index, hidden) -> (image, truth); duplicates reuse it
        self._last: tuple[tuple[int, bool], np.ndarray, dict[str, Pose]] | None = None
        self._h264: H264RoundTrip | None = None
        self._h264_next = 0  # the container frame the codec expects next

    # FrameSource
    @property
    def resolution(self) -> tuple[int, int]:
        return self.scene.camera.size

    @property
    def camera(self) -> CameraModel:
        return self.scene.camera

    @property
    def info(self) -> SourceInfo:
        return SourceInfo(fps=self.scene.fps, frame_count=self.scene.frames)

    def close(self) -> None:
        self._closed = True
        self._h264 = None

    def __iter__(self) -> Iterator[Frame]:
        for index in range(self.scene.frames):
            if self._closed:
                return
            yield self.frame(index)

    # rendering
    def frame(self, index: int) -> Frame:
        """Frame ``index`` of the clip (deterministic for the scene's seed)."""
        scene = self.scene
        hidden = scene.is_hidden(index)
        key = (scene.content_index(index), hidden)
        if self._last is not None and self._last[0] == key:
            image, truth = self._last[1], self._last[2]  # a duplicated frame: same pixels, same truth
        else:
            rng = np.random.default_rng([scene.seed, key[0]])
            image = self._renderer.render_frame(index, rng, targets=not hidden)
            truth = {} if hidden else scene.truth(scene.camera_from_world(index))
            self._last = (key, image, truth)
        if scene.compression == "h264":
            image = self._h264_frame(index)
        timestamp_ns = int(round(index * 1e9 / scene.fps))
        return Frame(image, index, timestamp_ns, truth)

    def _h264_frame(self, index: int) -> np.ndarray:
        """Container frame ``index`` after the H.264 round trip (sequential; out of order restarts)."""
        assert self._last is not None
        if self._h264 is None or index != self._h264_next:
            width, height = self.scene.camera.size
            self._h264 = H264RoundTrip(width, height, self.scene.fps, self.scene.h264_kbps, self.scene.h264_gop)
            self._h264_next = 0
            last = self._last
            for earlier in range(index):  # replay the stream up to here (random access only)
                self.frame(earlier)
            self._last = last
        self._h264_next = index + 1
        return self._h264(self._last[1])

    def camera_from_world(self, index: int) -> Pose:
        """``camera_from_world`` when container frame ``index``'s image was taken (mid-exposure, first row)."""
        return self.scene.camera_from_world(index)

    def camera_at(self, t_s: float) -> Pose:
        """``camera_from_world`` at any time (seconds); the calm trajectories span the container's
        ``(frames - 1) / fps`` seconds."""
        return self.scene.camera_at(t_s)

    def render_view(
        self, camera_from_world: Pose, rng: np.random.Generator | None = None, *, targets: bool = True
    ) -> np.ndarray:
        """BGR uint8 image from any camera pose, with the scene's blur and noise (noise needs ``rng``)."""
        return self._renderer.render_view(camera_from_world, rng, targets=targets)

    def exposure_samples(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Sub-frame times (N,) and per-row weights (H, N) of a frame taken at ``t_s`` (see
        :meth:`Renderer.exposure_samples <ar_anchor.synthetic.render.Renderer.exposure_samples>`)."""
        return self._renderer.exposure_samples(t_s)

    def truth(self, camera_from_world: Pose) -> dict[str, Pose]:
        """``camera_from_target`` of every target fully in view (all four corners of a marker;
        at least one marker of a board)."""
        return self.scene.truth(camera_from_world)
