"""Live sources: a capture thread that always hands the tracker the newest frame.

:class:`LiveSource` runs a :class:`Grabber` (a V4L2 webcam, or the synthetic scene paced in real
time) in a thread. Frames go through a bounded buffer: when the tracker is slower than the
camera the oldest waiting frame is dropped and counted, never queued without bound. Frames get
monotonic timestamps; a frame whose timestamp does not increase is dropped. If the device stops
delivering (unplugged, stalled), the thread tries to reopen it for ``reconnect_s`` seconds and
then ends the stream, so the run finishes cleanly with all outputs finalised.
"""

from __future__ import annotations

import collections
import glob
import logging
import stat
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from ..camera import CameraModel
from ..errors import SourceError, printable
from ..geometry import Pose
from .base import ClosingSource, Frame, SourceInfo
from .checks import file_kind
from .files import to_bgr8
from .synthetic import SyntheticScene, SyntheticSource

__all__ = [
    "CLIP_FRAMES",
    "Captured",
    "Grabber",
    "LiveSource",
    "LiveStats",
    "SyntheticGrabber",
    "WebcamGrabber",
    "video_devices",
]

log = logging.getLogger(__name__)

CLIP_FRAMES = 60  # frames the synthetic camera renders when it opens (see SyntheticGrabber)


@dataclass(frozen=True)
class Captured:
    """One image as the device delivered it."""

    image: np.ndarray
    timestamp_ns: int
    truth: Mapping[str, Pose] | None = None


class Grabber(Protocol):
    """A device the capture thread reads from. ``read`` returns None when the device failed.

    ``granted``: the settings the device accepted when it opened (width, height, fps, fourcc), empty
    for a device that has none to negotiate."""

    name: str
    granted: Mapping[str, object]

    def open(self) -> tuple[int, int]: ...

    def read(self) -> Captured | None: ...

    def close(self) -> None: ...


@dataclass
class LiveStats:
    """A live source's counters (frames captured, delivered, dropped; reconnects) and why it ended; thread-safe."""

    captured: int = 0
    delivered: int = 0
    dropped_queue: int = 0
    dropped_non_monotonic: int = 0
    reconnects: int = 0
    ended_because: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def as_dict(self) -> dict[str, int | str]:
        with self._lock:
            return {
                "captured": self.captured,
                "delivered": self.delivered,
                "dropped_queue": self.dropped_queue,
                "dropped_non_monotonic": self.dropped_non_monotonic,
                "reconnects": self.reconnects,
                "ended_because": self.ended_because,
            }


class LiveSource(ClosingSource):
    """A :class:`~ar_anchor.sources.base.FrameSource` fed by a capture thread (``info.live``: the run
    loop must not make it wait; it hands over the newest frame itself, so it is not prefetched).

    Parameters
    ----------
    grabber : the device.
    queue_size : frames waiting for the tracker at most (1: always the newest).
    reconnect_s : how long to keep trying to reopen a device that stopped delivering.
    stall_s : how long the consumer waits for a frame before it gives up on the device.
    camera : the device's own calibration when it has one (synthetic), else None.
    fps : the frame rate asked of the device (``info.fps``), None when it runs at its own default.
    """

    def __init__(
        self,
        grabber: Grabber,
        *,
        queue_size: int = 1,
        reconnect_s: float = 5.0,
        stall_s: float = 10.0,
        camera: CameraModel | None = None,
        fps: float | None = None,
    ) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be >= 1")
        self.grabber = grabber
        self.queue_size = queue_size
        self.reconnect_s = reconnect_s
        self.stall_s = stall_s
        self.camera = camera
        self._fps = fps
        self.stats = LiveStats()
        self._resolution = grabber.open()
        self._buffer: collections.deque[Frame] = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._finished = False
        self._thread: threading.Thread | None = None

    @property
    def resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def info(self) -> SourceInfo:
        return SourceInfo(live=True, fps=self._fps)

    def __enter__(self) -> LiveSource:
        self.start()
        return self

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._capture_loop, name=f"capture:{self.grabber.name}", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the capture thread (waits up to 5 s) and close the device."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.grabber.close()

    # ------------------------------------------------------------------ capture thread
    def _capture_loop(self) -> None:
        index = 0
        last_ns: int | None = None
        failing_since: float | None = None
        try:
            while not self._stop.is_set():
                captured = self.grabber.read()
                if captured is None:
                    now = time.monotonic()
                    if failing_since is None:
                        failing_since = now
                        log.warning(
                            "%s: stopped delivering frames; retrying for %.0f s", self.grabber.name, self.reconnect_s
                        )
                    if now - failing_since > self.reconnect_s:
                        self.stats.ended_because = f"{self.grabber.name} gone for more than {self.reconnect_s:g} s"
                        log.warning("%s: giving up after %.0f s without frames", self.grabber.name, self.reconnect_s)
                        return
                    self._stop.wait(0.2)
                    self._reopen()  # the clock keeps running until a frame actually arrives
                    continue
                failing_since = None
                with self.stats._lock:
                    self.stats.captured += 1
                if last_ns is not None and captured.timestamp_ns <= last_ns:
                    with self.stats._lock:
                        self.stats.dropped_non_monotonic += 1
                    continue
                last_ns = captured.timestamp_ns
                frame = Frame(captured.image, index, captured.timestamp_ns, captured.truth, time.monotonic_ns())
                index += 1
                with self._cond:
                    if len(self._buffer) >= self.queue_size:
                        self._buffer.popleft()
                        with self.stats._lock:
                            self.stats.dropped_queue += 1
                    self._buffer.append(frame)
                    self._cond.notify()
        except Exception as err:  # the device failed in a way it should not: end the stream, say why
            log.error("%s: capture failed: %s", self.grabber.name, err)
            self.stats.ended_because = f"capture failed: {err}"
        finally:
            with self._cond:
                self._finished = True
                self._cond.notify_all()

    def _reopen(self) -> bool:
        try:
            self.grabber.close()
            size = self.grabber.open()
        except SourceError:
            return False
        if size != self._resolution:
            log.warning("%s: reopened at %dx%d instead of %dx%d", self.grabber.name, *size, *self._resolution)
            return False
        with self.stats._lock:
            self.stats.reconnects += 1
        log.warning("%s: reconnected", self.grabber.name)
        return True

    # ------------------------------------------------------------------ consumer
    def __iter__(self) -> Iterator[Frame]:
        self.start()
        while True:
            with self._cond:
                deadline = time.monotonic() + self.stall_s
                while not self._buffer and not self._finished and not self._stop.is_set():
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(min(remaining, 0.5))
                if self._buffer:
                    frame = self._buffer.popleft()
                elif self._finished or self._stop.is_set():
                    return
                else:
                    self.stats.ended_because = f"no frame for {self.stall_s:g} s (device stalled)"
                    log.warning("%s: no frame for %.0f s: ending the stream", self.grabber.name, self.stall_s)
                    return
            with self.stats._lock:
                self.stats.delivered += 1
            yield frame


# ---------------------------------------------------------------------------- devices


def video_devices() -> list[str]:
    """The ``/dev/video*`` device nodes on this machine."""
    return sorted(glob.glob("/dev/video*"), key=lambda p: (len(p), p))


class WebcamGrabber:
    """A V4L2 camera by path (``/dev/video0``) or index, with requested size, fps and FOURCC."""

    def __init__(
        self,
        device: str | int,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        fourcc: str | None = "MJPG",
        api: int = cv2.CAP_V4L2,
    ) -> None:
        self.device = device
        self.api = api  # cv2.CAP_V4L2; another backend lets tests drive this code with a video file
        self.name = str(device)
        self.requested = (width, height, fps, fourcc)
        self._capture: cv2.VideoCapture | None = None
        self.granted: dict[str, object] = {}

    def open(self) -> tuple[int, int]:
        """Open the device with the requested settings, record what it ``granted``; its (width, height) in pixels."""
        device = self.device
        if isinstance(device, str) and not device.isdigit():
            try:
                mode: int | None = Path(device).stat().st_mode
            except OSError:
                mode = None
            if mode is None or self.api == cv2.CAP_V4L2 and not (stat.S_ISCHR(mode) or stat.S_ISREG(mode)):
                found = video_devices()
                listing = ", ".join(found) if found else "there are none on this machine"
                what = "no such video device" if mode is None else f"is {file_kind(mode)}, not a video device"
                raise SourceError(f"{printable(device)}: {what} (video devices: {listing})")
        target: str | int = int(device) if isinstance(device, str) and device.isdigit() else device
        capture = cv2.VideoCapture(target, self.api)
        if not capture.isOpened():
            capture.release()
            found = video_devices()
            listing = ", ".join(found) if found else "there are none on this machine"
            raise SourceError(f"{device}: cannot be opened as a V4L2 camera (video devices: {listing})")
        width, height, fps, fourcc = self.requested
        if fourcc:
            capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
        if width:
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            capture.set(cv2.CAP_PROP_FPS, fps)
        capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # keep the driver's queue short: we want the newest frame
        granted_fourcc = int(capture.get(cv2.CAP_PROP_FOURCC))
        self.granted = {
            "width": int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": capture.get(cv2.CAP_PROP_FPS),
            "fourcc": granted_fourcc.to_bytes(4, "little").decode("ascii", "replace") if granted_fourcc > 0 else "",
        }
        differs = any(
            want and str(want) != str(got) and not (isinstance(want, float) and abs(want - float(got)) < 0.5)
            for want, got in zip(
                self.requested,
                (self.granted["width"], self.granted["height"], self.granted["fps"], self.granted["fourcc"]),
            )
        )
        log.log(
            logging.WARNING if differs else logging.INFO,
            "%s: granted %dx%d at %.4g fps, %s (requested %sx%s at %s fps, %s)",
            self.name,
            self.granted["width"],
            self.granted["height"],
            self.granted["fps"],
            self.granted["fourcc"] or "?",
            width or "default",
            height or "default",
            fps or "default",
            fourcc or "default",
        )
        self._capture = capture
        return int(self.granted["width"]), int(self.granted["height"])

    def read(self) -> Captured | None:
        """The next image (BGR8) stamped with ``time.monotonic_ns()``, or None when the device fails."""
        if self._capture is None:
            return None
        ok, image = self._capture.read()
        timestamp_ns = time.monotonic_ns()
        image = to_bgr8(image) if ok else None
        if image is None:
            return None
        return Captured(image, timestamp_ns)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class SyntheticGrabber:
    """The synthetic scene as a camera: a frame is due every ``1 / fps`` seconds of real time.

    Rendering a frame with its supersampled markers and sensor noise takes 70-170 ms (720p-1080p),
    far longer than a camera's frame period, and in this process it would take the GIL from the
    tracker it is meant to feed. So the camera's clip is rendered once when it opens (``cached``
    frames, evenly spread over the scene, played forth and back so that the motion never jumps),
    held as JPEG (quality 95, as an MJPEG webcam delivers it) and decoded when due, which releases the
    GIL like a real capture does. ``cached=0`` renders every frame when due instead (slow: frames
    whose time has passed are skipped, as a real camera's would be). ``eager``: how many of the clip's
    first frames to render when it opens (default all): a run that takes only a few frames
    (``--max-frames``) does not wait for the whole clip; a clip frame not rendered yet is rendered when
    it is first due (the frames due meanwhile are skipped, as above).
    """

    name = "synthetic"

    def __init__(
        self, scene: SyntheticScene, *, loop: bool = True, cached: int = CLIP_FRAMES, eager: int | None = None
    ) -> None:
        self.source = SyntheticSource(scene)
        self.scene = scene
        self.granted: Mapping[str, object] = {}  # nothing to negotiate: it renders at the scene's size and rate
        self.loop = loop
        self.cached = min(max(int(cached), 0), scene.frames)
        self.eager = self.cached if eager is None else min(max(int(eager), 1), self.cached)
        self._clip: list[tuple[bytes, Mapping[str, Pose] | None] | None] = []
        self._start_ns: int | None = None
        self._next_slot = 0

    def open(self) -> tuple[int, int]:
        """Restart the clock, render the clip's first ``eager`` frames once (JPEG); the camera's (width, height)
        in pixels."""
        self._start_ns = None
        self._next_slot = 0
        if self.cached >= 2 and not self._clip:
            log.info("synthetic camera: rendering %d of its %d-frame clip", self.eager, self.cached)
            self._clip = [None] * self.cached
            for k in range(self.eager):
                self._clip[k] = self._render_clip_frame(k)
        return self.scene.camera.size

    def _render_clip_frame(self, k: int) -> tuple[bytes, Mapping[str, Pose] | None]:
        """The clip's frame ``k`` (of ``cached``, evenly spread over the scene) as JPEG, with its truth."""
        frame = self.source.frame(round(k * (self.scene.frames - 1) / (self.cached - 1)))
        ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        if not ok:
            raise SourceError("synthetic camera: cannot encode its frames")
        return jpeg.tobytes(), frame.truth

    def _frames(self) -> int:
        return len(self._clip) if self._clip else max(self.scene.frames, 1)

    def _clip_index(self, slot: int) -> int:
        """Slot -> clip frame: forth and back over a cached clip, around a rendered one."""
        frames = self._frames()
        if not self._clip or frames < 2:
            return slot % frames
        period = 2 * (frames - 1)
        phase = slot % period
        return phase if phase < frames else period - phase

    def read(self) -> Captured | None:
        """Wait until the next frame is due, then return it with its truth; None once a non-looping clip is over."""
        now = time.monotonic_ns()
        if self._start_ns is None:
            self._start_ns = now
        period_ns = 1e9 / self.scene.fps
        slot = max(self._next_slot, int((now - self._start_ns) // period_ns))
        due = self._start_ns + int(slot * period_ns)
        if due > now:
            time.sleep((due - now) * 1e-9)
        self._next_slot = slot + 1
        if not self.loop and slot >= self._frames():
            time.sleep(0.05)
            return None  # the clip is over: like an unplugged camera
        index = self._clip_index(slot)
        if self._clip:
            cached = self._clip[index]
            if cached is None:
                cached = self._clip[index] = self._render_clip_frame(index)
            jpeg, truth = cached
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        else:
            frame = self.source.frame(index)
            image, truth = frame.image, frame.truth
        return Captured(image, max(due, time.monotonic_ns()), truth)

    def close(self) -> None:
        pass
