"""Frames to views, and a whole calibration run (:func:`calibrate_source`).

Files, globs and videos: every frame (videos: every ``k``-th, at most about
``CANDIDATES_PER_VIEW x max_views`` candidates) is detected, then the views are selected together.
Devices: views are kept online as they arrive until ``max_views``, ``duration_s`` or Ctrl-C.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from ...errors import InputError, SourceError
from ...sources.open import is_device
from .solve import (
    BOOTSTRAP_RESAMPLES,
    CalibrationReport,
    CalibrationResult,
    Coverage,
    Uncertainty,
    bootstrap_uncertainty,
    calibrate_views,
    coverage_of,
)
from .views import CharucoSpec, OnlineSelector, Rejection, View, ViewDetector, reason_counts, select_views

__all__ = ["CANDIDATES_PER_VIEW", "Progress", "calibrate_source", "quality_warnings"]

log = logging.getLogger(__name__)

CANDIDATES_PER_VIEW = 10  # videos: consider about this many frames per wanted view


Progress = Callable[[str], None]


def _gather_files(
    source: str, detector: ViewDetector, max_views: int, progress: Progress | None
) -> tuple[list[View], list[Rejection], int, tuple[int, int], int]:
    """Detect in the (sampled) frames of a folder, glob or video: (views, rejections, considered, size, step)."""
    from ...sources import open_source
    from ...sources.files import ImageFolderSource

    try:
        opened = open_source(source, live=False)
    except SourceError as err:
        message = str(err)
        raise SourceError(message if source in message else f"{source}: {message}") from None
    views: list[View] = []
    rejections: list[Rejection] = []
    considered = 0
    with opened as frames:
        is_folder = isinstance(frames, ImageFolderSource)
        count = frames.info.frame_count
        step = 1 if is_folder or not count else max(1, math.ceil(count / (CANDIDATES_PER_VIEW * max_views)))
        if step > 1:
            log.info("%s: %d frames, considering one in %d", source, count, step)
        size = frames.resolution
        last_report = time.monotonic()
        for frame in frames:
            if frame.index % step:
                continue
            considered += 1
            name = frames.files[frame.index].name if is_folder else f"frame {frame.index}"
            found = detector.detect(frame.image, name, frame.index)
            (views if isinstance(found, View) else rejections).append(found)
            if progress is not None and time.monotonic() - last_report > 2.0:
                last_report = time.monotonic()
                total = f"/{math.ceil(count / step)}" if count else ""
                progress(f"considered {considered}{total} frames, board in {len(views)}")
    if progress is not None:  # the last line counts what the report will: every frame considered
        sampled = f" (one in {step})" if step > 1 else ""
        progress(f"considered all {considered} frames{sampled}, board in {len(views)}")
    return views, rejections, considered, size, step


def _gather_device(
    source: str,
    detector: ViewDetector,
    *,
    max_views: int,
    duration_s: float,
    width: int | None,
    height: int | None,
    fps: float | None,
    progress: Progress | None,
    on_keep: Callable[[View, np.ndarray], None] | None = None,
    grabber: object | None = None,
) -> tuple[list[View], list[Rejection], int, tuple[int, int]]:
    """Capture from a device until ``max_views`` distinct sharp views or ``duration_s`` (or Ctrl-C)."""
    from ...sources.live import LiveSource, WebcamGrabber

    if grabber is None:
        grabber = WebcamGrabber(source.strip(), width=width, height=height, fps=fps)
    live = LiveSource(grabber, queue_size=1, reconnect_s=2.0, stall_s=5.0)  # type: ignore[arg-type]
    size = live.resolution
    selector = OnlineSelector(size, max_views)
    rejections: list[Rejection] = []
    considered = 0
    start = time.monotonic()
    last_status = start
    if progress is not None:
        progress(
            f"{source}: capturing at {size[0]}x{size[1]} for up to {duration_s:g} s or {max_views} views; "
            "move the board over the whole image, tilted 20-50 degrees (Ctrl-C: stop and calibrate)"
        )
    try:
        with live:
            first_ns: int | None = None
            for frame in live:
                now = time.monotonic() - start
                if now > duration_s:
                    break
                first_ns = frame.timestamp_ns if first_ns is None else first_ns
                considered += 1
                found = detector.detect(frame.image, f"frame {frame.index}", frame.index)
                if isinstance(found, View):
                    why = selector.offer(found, (frame.timestamp_ns - first_ns) * 1e-9)
                    if why is None:
                        if on_keep is not None:
                            on_keep(found, frame.image)
                        if progress is not None:
                            progress(
                                f"view {len(selector.kept)}/{max_views} kept: frame {frame.index}, "
                                f"{found.count} corners, edge width {found.edge_width_px:.2f} px ({now:.0f} s)"
                            )
                        if selector.full:
                            break
                    elif why.reason:
                        rejections.append(why)
                    else:
                        considered -= 1  # merely too soon: not a considered view
                else:
                    rejections.append(found)
                if progress is not None and time.monotonic() - last_status > 5.0:
                    last_status = time.monotonic()
                    progress(
                        f"{now:.0f} s: {len(selector.kept)}/{max_views} views kept, {considered} frames considered"
                    )
    except KeyboardInterrupt:
        if progress is not None:
            progress("capture stopped (Ctrl-C): calibrating with the views kept so far")
    if progress is not None:
        progress(f"capture ended: {considered} frames considered, {len(selector.kept)}/{max_views} views")
    return list(selector.kept), rejections, considered, size


def calibrate_source(
    source: str,
    spec: CharucoSpec,
    *,
    max_views: int = 40,
    min_views: int = 6,
    duration_s: float = 60.0,
    width: int | None = None,
    height: int | None = None,
    fps: float | None = None,
    previews: bool = False,
    progress: Progress | None = None,
    on_keep: Callable[[View, np.ndarray], None] | None = None,
    grabber: object | None = None,
    resamples: int = BOOTSTRAP_RESAMPLES,
) -> CalibrationReport:
    """Calibrate a camera from the ChArUco views in ``source`` (folder, glob, video or device).

    ``previews``: keep a JPEG of each view (for the recording). ``progress``: called with one-line
    progress messages. ``grabber``: a device stand-in (tests); ``on_keep``: called for each view a
    device keeps, with its frame. ``resamples``: calibrations on resampled views for the uncertainty
    (:func:`~.solve.bootstrap_uncertainty`).
    """
    if max_views < min_views:
        raise InputError(f"--max-views ({max_views}) must be at least --min-views ({min_views})")
    started = time.monotonic()
    detector = ViewDetector(spec, previews=previews)
    step = 1
    if grabber is not None or is_device(source):
        views, rejections, considered, size = _gather_device(
            source,
            detector,
            max_views=max_views,
            duration_s=duration_s,
            width=width,
            height=height,
            fps=fps,
            progress=progress,
            on_keep=on_keep,
            grabber=grabber,
        )
        kept = views
    else:
        views, rejections, considered, size, step = _gather_files(source, detector, max_views, progress)
        kept, more = select_views(views, size, max_views)
        rejections += more
    rejections.sort(key=lambda r: r.frame)
    for rejection in rejections:
        log.log(logging.DEBUG if rejection.reason == "no board" else logging.INFO, "rejected %s", rejection)
    _refuse_unusable(source, spec, detector, views, kept, rejections, considered, min_views)
    result = calibrate_views(spec, kept, size, min_views=min_views)
    uncertainty = bootstrap_uncertainty(spec, result, size, resamples=resamples, progress=progress)
    coverage = coverage_of(result.views, size)
    return CalibrationReport(
        source=str(source),
        spec=spec,
        image_size=(int(size[0]), int(size[1])),
        considered=considered,
        rejections=tuple(rejections),
        result=result,
        coverage=coverage,
        warnings=tuple(quality_warnings(result, coverage, uncertainty)),
        seconds=time.monotonic() - started,
        frame_step=step,
        uncertainty=uncertainty,
    )


def _refuse_unusable(
    source: str,
    spec: CharucoSpec,
    detector: ViewDetector,
    views: list[View],
    kept: list[View],
    rejections: list[Rejection],
    considered: int,
    min_views: int,
) -> None:
    """A :class:`SourceError` when no frame was read, an :class:`InputError` when the board was never
    found or too few views are usable."""
    if considered == 0:
        raise SourceError(f"{source}: no frame could be read")
    if not views:
        hint = (
            f" (markers of {spec.dictionary} were seen in {detector.markers_seen} view(s) but never as this board)"
            if detector.markers_seen
            else ""
        )
        raise InputError(
            f"no ChArUco board ({spec.describe()}) found in any of the {considered} view(s) of {source}{hint}; "
            "check --charuco/--dictionary/--legacy"
        )
    if len(kept) < min_views:
        raise InputError(
            f"only {len(kept)} usable view(s) of {considered} considered in {source}, --min-views is {min_views} "
            f"(rejected: {reason_counts(rejections) or 'none'}); add views of the whole board, sharp and from "
            "different angles"
        )


def quality_warnings(
    result: CalibrationResult, coverage: Coverage, uncertainty: Uncertainty | None = None
) -> list[str]:
    """The coverage's warnings, then a poorly constrained focal length (by ``uncertainty`` when given,
    else by OpenCV's estimate), why the uncertainty is not to be trusted, and a high RMS error."""
    warnings = list(coverage.warnings)
    fx, fy = result.camera.camera_matrix[0, 0], result.camera.camera_matrix[1, 1]
    sfx, sfy = (uncertainty.std if uncertainty is not None else result.std)[:2]
    if math.isfinite(sfx) and math.isfinite(sfy) and max(sfx / fx, sfy / fy) > 0.01:
        warnings.append(
            f"focal length poorly constrained (fx +- {sfx / fx:.1%}, fy +- {sfy / fy:.1%}): add views with the board "
            "tilted 20-50 degrees, near the image corners"
        )
    if uncertainty is not None and uncertainty.distrust:
        warnings.append(
            f"the uncertainty (+-) is itself unreliable: {'; '.join(uncertainty.distrust)}: take 10-20 sharp views "
            "of the board tilted 20-50 degrees in different directions"
        )
    if result.rms > 1.0:
        warnings.append(f"RMS reprojection error {result.rms:.2f} px is high (expect < 0.5 px): check the board spec")
    return warnings
