"""The speed benchmark's real clip: the ArUco library's ``chessboard.avi`` (149 frames, 640x480, an
18-marker board moved by hand in front of a webcam), decoded into memory before any timing.

It is found under ``$AR_ANCHOR_REALDATA`` (else ``../shared/realdata``) as
``aruco_testdata/chessboard/chessboard.avi`` with its calibration ``intrinsics.yml``; when absent, the
clip is skipped with a one-line note. There is no truth: the accuracy columns stay empty and only the
markers found per frame are compared.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from ...camera import CameraModel
from ...config import TrackerConfig
from ...sources.base import Frame
from ..real.inputs import DEFAULT_DICTIONARY, DEFAULT_MARKER_LENGTH_M, default_realdata_root

__all__ = ["CHESSBOARD", "RealClip", "chessboard_files", "load_chessboard", "real_config"]

CHESSBOARD = "chessboard"
_FOLDER = Path("aruco_testdata") / "chessboard"


def chessboard_files(root: Path | None = None) -> tuple[Path, Path] | str:
    """``(video, calibration)`` of chessboard.avi under ``root`` (default: the real data root), or the
    one-line note saying why the clip is skipped."""
    root = default_realdata_root() if root is None else Path(root)
    video, camera = root / _FOLDER / "chessboard.avi", root / _FOLDER / "intrinsics.yml"
    missing = [p for p in (video, camera) if not p.is_file()]
    if missing:
        return (
            f"chessboard clip skipped: {missing[0]} not found (the real data lives in ../shared/realdata, "
            "or set AR_ANCHOR_REALDATA)"
        )
    return video, camera


def real_config(base: TrackerConfig, *, roi: bool) -> TrackerConfig:
    """``base`` set up for chessboard.avi as ``ar-anchor replay --dictionary DICT_ARUCO_ORIGINAL
    --marker-length 0.034`` builds it (every id, no boards), filter on, ROI tracking on or off."""
    return dataclasses.replace(
        base,
        detector=dataclasses.replace(base.detector, dictionary=DEFAULT_DICTIONARY, roi=roi),
        markers=dataclasses.replace(base.markers, length_m=DEFAULT_MARKER_LENGTH_M, lengths_m={}, ids=()),
        boards=(),
        filter=dataclasses.replace(base.filter, enabled=True),
    )


@dataclass(frozen=True)
class RealClip:
    """The decoded frames of a real video, the camera scaled to them, and the tracker configs."""

    video: Path
    camera: CameraModel
    frames: list[Frame]
    full: TrackerConfig
    roi: TrackerConfig


def load_chessboard(base: TrackerConfig, max_frames: int, root: Path | None = None) -> RealClip | str:
    """chessboard.avi's first ``max_frames`` frames in memory (decoded by ``open_source``, as ``ar-anchor
    replay`` reads it), or the note saying why the clip is skipped."""
    from ...sources import open_source

    files = chessboard_files(root)
    if isinstance(files, str):
        return files
    video, calibration = files
    frames: list[Frame] = []
    with open_source(video, live=False) as source:
        camera = CameraModel.from_yaml(calibration).scaled_to(*source.resolution)
        for frame in source:
            frames.append(frame)
            if len(frames) >= max_frames:
                break
    return RealClip(video, camera, frames, real_config(base, roi=False), real_config(base, roi=True))
