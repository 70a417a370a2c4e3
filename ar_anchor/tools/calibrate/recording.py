"""The calibration's rerun recording (entity tree in :mod:`ar_anchor.tools.calibrate`), logged through
:class:`ar_anchor.viz.sinks.Recording`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .report import format_report
from .solve import CalibrationReport
from .views import View, jpeg_preview

if TYPE_CHECKING:
    from ...viz.sinks import Recording

__all__ = ["CalibrationRecording"]

_CORNERS = [(40, 220, 80)]
_REPROJECTED = [(255, 60, 60)]
_COVERAGE_CORNERS = [(255, 255, 255)]


class CalibrationRecording:
    """The calibration's rerun recording (``.rrd`` file and/or a spawned viewer).

    The file is written beside its final name and renamed there by :meth:`close` when the
    calibration succeeded (``keep``); a failed run leaves no recording behind.
    """

    def __init__(self, rrd_path: Path | None, *, spawn: bool) -> None:
        # (imports rerun: only when a calibration runs, not on every CLI start)
        from ...viz.blueprints import calibrate_blueprint
        from ...viz.sinks import Recording

        self.recording: Recording = Recording(
            "ar_anchor_calibrate",
            path=rrd_path,
            partial=True,
            spawn=spawn,
            blueprint=calibrate_blueprint(),
            name="ar-anchor calibrate",
            option="--rrd",
        )

    def event(self, text: str, *, frame: int | None = None, warn: bool = False) -> None:
        """A line of the ``events`` log: on the ``frame`` timeline when given, static otherwise."""
        if frame is not None:
            self.recording.time("frame", sequence=frame)
        self.recording.text("events", text, warn=warn, static=frame is None)

    def live_view(self, view: View, image: np.ndarray) -> None:
        """A view a device just kept (on the ``frame`` timeline), so the viewer shows progress."""
        recording = self.recording
        recording.time("frame", sequence=view.frame)
        preview, scale = (view.preview, view.preview_scale) if view.preview else jpeg_preview(image)
        recording.encoded_image("views/image", preview, "image/jpeg")
        recording.image_points("views/image/corners", view.corners, radius=2.0, colours=_CORNERS, scale=scale)

    def result(self, report: CalibrationReport) -> None:
        """Every view considered (on the ``view`` timeline): its corners, errors of the first and final
        fits and reprojected corners, or why it was dropped; then the coverage and the report."""
        recording = self.recording
        result = report.result
        final = {id(v): i for i, v in enumerate(result.views)}
        for position, (view, first_error) in enumerate(zip(result.first_views, result.first_errors_px)):
            recording.time("view", sequence=position)
            recording.time("frame", sequence=view.frame)
            scale = view.preview_scale
            if view.preview:
                recording.encoded_image("views/image", view.preview, "image/jpeg")
            recording.image_points("views/image/corners", view.corners, radius=2.0, colours=_CORNERS, scale=scale)
            recording.scalar("metrics/view_error_px/first_fit", first_error)
            index = final.get(id(view))
            if index is not None:
                recording.scalar("metrics/view_error_px/final", result.errors_px[index])
                if index < len(result.reprojected):
                    recording.image_points(
                        "views/image/reprojected",
                        result.reprojected[index],
                        radius=1.0,
                        colours=_REPROJECTED,
                        scale=scale,
                    )
                text = f"view {position}: {view.name}, {view.count} corners, {result.errors_px[index]:.3f} px"
                recording.text("events", text)
            else:
                recording.clear("views/image/reprojected")
                why = next((d for d in result.dropped if d.name == view.name and d.frame == view.frame), None)
                recording.text("events", f"view {position}: {why or view.name}", warn=True)
        self._coverage(report)
        for line in format_report(report).splitlines():
            recording.text("events", line)

    def _coverage(self, report: CalibrationReport) -> None:
        """The coverage heat map (log scale, at most 640 px wide) with every used corner on it."""
        width, height = report.image_size
        counts = report.coverage.counts.astype(np.float64)
        level = np.log1p(counts) / max(np.log1p(counts.max()), 1e-9)
        colours = cv2.applyColorMap(np.round(level * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        colours[counts == 0] = (40, 40, 40)
        scale = min(1.0, 640.0 / width)
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        image = cv2.resize(colours, size, interpolation=cv2.INTER_NEAREST)
        ok, png = cv2.imencode(".png", image)
        if ok:
            self.recording.encoded_image("coverage", png.tobytes(), "image/png", static=True)
        corners = np.concatenate([v.corners for v in report.result.views])
        self.recording.image_points(
            "coverage/corners", corners, radius=1.0, colours=_COVERAGE_CORNERS, scale=scale, static=True
        )

    def close(self, *, keep: bool) -> None:
        """Flush and close; the file is renamed into place when ``keep``, removed otherwise."""
        self.recording.close(keep=keep, timeout_s=10.0)
