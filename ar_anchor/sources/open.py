"""One opener for every kind of source: :func:`open_source` reads what the spec names.

========================================  ===========================================================
spec                                      source
========================================  ===========================================================
a video file                              :class:`~.files.VideoFileSource` (container timestamps)
a folder, a glob (``shots/*.png``),       :class:`~.files.ImageFolderSource` (natural order, ``fps``)
or one image
``/dev/videoN``, ``N`` (str or int)       :class:`~.live.LiveSource` over a :class:`~.live.WebcamGrabber`
``"synthetic"``                           :class:`~.live.LiveSource` over a :class:`~.live.SyntheticGrabber`:
                                          the demo scene (or ``scene``) in real time, with its truth
========================================  ===========================================================

``live`` overrides the guess: ``False`` reads any spec as a path (a file named ``synthetic``);
``True`` reads any spec as a device (``ar-anchor live --device``), so that a name that is no device
is reported as one.
"""

from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, overload

from ..camera import CameraModel
from ..config import TrackerConfig, demo_config
from ..errors import InputError, SourceError, printable
from ..synthetic import SyntheticScene, Trajectory, demo_scene
from .base import FrameSource
from .checks import file_kind, in_range
from .files import IMAGE_EXTENSIONS, ImageFolderSource, VideoFileSource
from .image_header import MAX_IMAGE_PIXELS
from .live import Grabber, LiveSource, SyntheticGrabber, WebcamGrabber

__all__ = [
    "LIVE_FPS_RANGE",
    "MAX_DEVICE_SIDE",
    "SYNTHETIC",
    "DeviceSettings",
    "is_device",
    "live_demo_scene",
    "open_source",
]

SYNTHETIC = "synthetic"  # the spec of the synthetic camera
_GLOB_CHARS = re.compile(r"[*?\[]")
_DEFAULT_FPS = 30.0  # image sequences and the synthetic camera, unless told otherwise
LIVE_FPS_RANGE = (0.01, 1000.0)  # frame rates asked of a device or the synthetic camera: a frame per 100 s .. 1 kHz
MAX_DEVICE_SIDE = 16384  # pixels: wider or taller than any capture device
_MAX_WAIT_S = 86400.0  # reconnect and stall timeouts: a day at most
_MAX_QUEUE = 1000  # frames waiting for the tracker at most (6 MB each at 1080p)


@dataclass(frozen=True)
class DeviceSettings:
    """What to ask of a live device beyond its frame rate, and how patiently to wait for it.

    ``width``, ``height``, ``fourcc``: requested (the device may grant others; it says which);
    ``queue_size``: frames waiting for the tracker at most (1: the newest only); ``reconnect_s``: how
    long a vanished device is reopened; ``stall_s``: how long without a frame ends the stream.
    """

    width: int | None = None
    height: int | None = None
    fourcc: str | None = "MJPG"
    queue_size: int = 1
    reconnect_s: float = 5.0
    stall_s: float = 10.0

    def __post_init__(self) -> None:
        """Each setting range-checked; an :class:`~ar_anchor.errors.InputError` names its option."""
        for option, side in (("--width", self.width), ("--height", self.height)):
            if side is not None and not (isinstance(side, int) and 1 <= side <= MAX_DEVICE_SIDE):
                raise InputError(f"{option}: must be a whole number of pixels in [1, {MAX_DEVICE_SIDE}], got {side}")
        if self.fourcc is not None and not (
            len(self.fourcc) == 4 and self.fourcc.isascii() and self.fourcc.isprintable()
        ):
            raise InputError(f"--fourcc: expected four characters such as MJPG or YUYV, got {self.fourcc!r}")
        if not (isinstance(self.queue_size, int) and 1 <= self.queue_size <= _MAX_QUEUE):
            raise InputError(f"--queue: must be in [1, {_MAX_QUEUE}] frames, got {self.queue_size}")
        in_range("--reconnect-s", self.reconnect_s, 0.0, _MAX_WAIT_S, unit=" s")
        if in_range("--stall-s", self.stall_s, 0.0, _MAX_WAIT_S, unit=" s") <= 0:
            raise InputError(f"--stall-s: must be more than 0 s, got {self.stall_s:g}")


def live_demo_scene(
    config: TrackerConfig | None = None,
    camera: CameraModel | None = None,
    *,
    fps: float = _DEFAULT_FPS,
    seed: int = 0,
) -> SyntheticScene:
    """The synthetic camera's scene: the demo scene (``config``'s targets, default the demo config) seen
    by ``camera`` (default the synthetic camera) on a 20 s orbit at ``fps`` (in :data:`LIVE_FPS_RANGE`, else an
    :class:`~ar_anchor.errors.InputError` naming ``--fps``)."""
    fps = in_range("--fps", fps, *LIVE_FPS_RANGE, unit=" fps")
    return demo_scene(
        config or demo_config(),
        camera or CameraModel.default_synthetic(),
        frames=max(int(20 * fps), 2),
        seed=seed,
        fps=fps,
        trajectory=Trajectory(kind="orbit", near_m=0.5, look_at=(-0.01, 0.0, 0.0)),
    )


def is_device(spec: str | int | os.PathLike[str]) -> bool:
    """``/dev/videoN`` or a camera index (an int, or a string of digits)."""
    if isinstance(spec, int):
        return True
    text = os.fspath(spec).strip()
    return text.isdigit() or text.startswith("/dev/video")


@overload
def open_source(
    spec: str | int | os.PathLike[str],
    *,
    live: Literal[True],
    fps: float | None = None,
    device: DeviceSettings | None = None,
    scene: SyntheticScene | None = None,
    frames: int | None = None,
) -> LiveSource: ...


@overload
def open_source(
    spec: str | os.PathLike[str], *, live: Literal[False], fps: float | None = None, max_pixels: int | None = None
) -> VideoFileSource | ImageFolderSource: ...


@overload
def open_source(
    spec: str | int | os.PathLike[str],
    *,
    live: None = None,
    fps: float | None = None,
    device: DeviceSettings | None = None,
    scene: SyntheticScene | None = None,
    max_pixels: int | None = None,
    frames: int | None = None,
) -> FrameSource: ...


def open_source(
    spec: str | int | os.PathLike[str],
    *,
    live: bool | None = None,
    fps: float | None = None,
    device: DeviceSettings | None = None,
    scene: SyntheticScene | None = None,
    max_pixels: int | None = None,
    frames: int | None = None,
) -> FrameSource:
    """The source ``spec`` names (see the module doc), opened; use it as a context manager.

    ``fps``: an image sequence's frame rate (default 30), the rate asked of a device (default: its own),
    or the default synthetic scene's (default 30). ``device``: what else to ask of a device.
    ``scene``: what the synthetic camera shows (default :func:`live_demo_scene`). ``max_pixels``: a file's
    frames of more pixels are refused (an image skipped, a video not opened; default
    :data:`~.image_header.MAX_IMAGE_PIXELS`, 50 MP), read from its header before it is decoded. ``frames``:
    how many frames the caller will take at most (``--max-frames``), if it knows: the synthetic camera then
    renders no more than that of its clip before it starts (:class:`~.live.SyntheticGrabber`).
    Raises :class:`~ar_anchor.errors.SourceError` naming the spec when it cannot be opened (a named pipe, a
    socket or a device node where a file is due is said to be one), and an
    :class:`~ar_anchor.errors.InputError` naming the option for a frame rate or device setting out of range.
    """
    if live is None:
        live = spec == SYNTHETIC or is_device(spec)
    if not live:
        limit = MAX_IMAGE_PIXELS if max_pixels is None else max_pixels
        return _open_path(os.fspath(spec), fps=_DEFAULT_FPS if fps is None else fps, max_pixels=limit)
    if fps is not None:
        fps = in_range("--fps", fps, *LIVE_FPS_RANGE, unit=" fps")
    settings = device or DeviceSettings()
    grabber: Grabber
    if spec == SYNTHETIC:
        scene = scene or live_demo_scene(fps=_DEFAULT_FPS if fps is None else fps)
        grabber, camera, fps = SyntheticGrabber(scene, loop=True, eager=frames), scene.camera, scene.fps
    else:
        name = spec if isinstance(spec, int) else os.fspath(spec)
        grabber = WebcamGrabber(name, width=settings.width, height=settings.height, fps=fps, fourcc=settings.fourcc)
        camera = None
    return LiveSource(
        grabber,
        queue_size=settings.queue_size,
        reconnect_s=settings.reconnect_s,
        stall_s=settings.stall_s,
        camera=camera,
        fps=fps,
    )


def _open_path(text: str, *, fps: float, max_pixels: int) -> VideoFileSource | ImageFolderSource:
    """A video file, an image folder, a glob of images, or a single image: the right source for it."""
    path = Path(text)
    try:
        mode = path.stat().st_mode
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
        raise SourceError(f"{printable(text)}: is {file_kind(mode)}, not a video, an image or a folder")
    if path.is_dir() or _GLOB_CHARS.search(text) and not path.exists():
        return ImageFolderSource(text, fps=fps, max_pixels=max_pixels)
    if path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS:
        return ImageFolderSource(text, fps=fps, max_pixels=max_pixels)
    return VideoFileSource(path, max_pixels=max_pixels)
