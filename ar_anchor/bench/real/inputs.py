"""The data files of ``ar-anchor bench real``: the video, its camera calibration and (optionally) the
printed layout, by default chessboard.avi from the shared real data."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ...errors import InputError

__all__ = ["DEFAULT_DICTIONARY", "DEFAULT_MARKER_LENGTH_M", "RealInputs", "default_realdata_root", "real_inputs"]

DEFAULT_DICTIONARY = "DICT_ARUCO_ORIGINAL"
DEFAULT_MARKER_LENGTH_M = 0.034
_CHESSBOARD = Path("aruco_testdata") / "chessboard"


def default_realdata_root() -> Path:
    """``$AR_ANCHOR_REALDATA``, else ``../shared/realdata`` beside the repository."""
    env = os.environ.get("AR_ANCHOR_REALDATA")
    return Path(env) if env else Path(__file__).resolve().parents[4] / "shared" / "realdata"


@dataclass(frozen=True)
class RealInputs:
    """The data files of a run, checked to exist. ``dictionary`` / ``marker_length_m``: overrides of
    the tracker config (None: the config's own, as ``ar-anchor replay``)."""

    video: Path
    camera: Path
    dictionary: str | None
    marker_length_m: float | None
    layout: Path | None


def real_inputs(
    video: str | os.PathLike[str] | None = None,
    camera: str | os.PathLike[str] | None = None,
    dictionary: str | None = None,
    marker_length_m: float | None = None,
    layout: str | os.PathLike[str] | None = None,
) -> RealInputs:
    """Resolve the options: without ``video``, chessboard.avi from the real data (its camera, dictionary,
    marker length and layout unless given). Raises :class:`InputError` (exit 2) for missing files."""
    if video is None:
        root = default_realdata_root()
        folder = root / _CHESSBOARD
        default_video = folder / "chessboard.avi"
        if not default_video.is_file():
            raise InputError(
                f"bench real: the default video {default_video} is missing (the real data lives in "
                f"../shared/realdata, or set AR_ANCHOR_REALDATA); give --video FILE --camera FILE instead"
            )
        video_path = default_video
        camera_path = Path(camera) if camera is not None else folder / "intrinsics.yml"
        dictionary = dictionary or DEFAULT_DICTIONARY
        marker_length_m = marker_length_m or DEFAULT_MARKER_LENGTH_M
        layout_path = Path(layout) if layout is not None else folder / "chessboardinfo_meters.yml"
    else:
        video_path = Path(video)
        if not video_path.exists():
            raise InputError(f"--video {video_path}: not found")
        if camera is None:
            beside = [video_path.parent / n for n in ("camera.yml", "intrinsics.yml")]
            found = next((p for p in beside if p.is_file()), None)
            if found is None:
                raise InputError(
                    f"--camera FILE is required: the calibration of the camera that took {video_path} "
                    f"(none found at {beside[0]} or {beside[1]})"
                )
            camera_path = found
        else:
            camera_path = Path(camera)
        layout_path = Path(layout) if layout is not None else None
    if not camera_path.is_file():
        raise InputError(f"--camera {camera_path}: not found")
    if layout_path is not None and not layout_path.is_file():
        raise InputError(f"--layout {layout_path}: not found")
    return RealInputs(video_path, camera_path, dictionary, marker_length_m, layout_path)
