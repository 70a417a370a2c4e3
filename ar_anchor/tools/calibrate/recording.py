"""The calibration's rerun recording (entity tree in :mod:`ar_anchor.tools.calibrate`)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ...errors import OutputError
from .report import format_report
from .solve import CalibrationReport
from .views import View, jpeg_preview

__all__ = ["CalibrationRecording"]


class CalibrationRecording:
    """The calibration's rerun recording (``.rrd`` file and/or a spawned viewer).

    The file is written beside its final name and renamed there by :meth:`close` when the
    calibration succeeded (``keep``); a failed run leaves no recording behind.
    """

    def __init__(self, rrd_path: Path | None, *, spawn: bool) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        from ...viz.viewer import spawn_local_viewer

        self.rr = rr
        self.rec = rr.RecordingStream("ar_anchor_calibrate")
        self.path = rrd_path
        self.partial = None if rrd_path is None else rrd_path.with_name(f".{rrd_path.name}.{os.getpid()}.tmp.rrd")
        sinks: list[object] = []
        if rrd_path is not None and self.partial is not None:
            try:
                rrd_path.parent.mkdir(parents=True, exist_ok=True)
                if rrd_path.is_dir():
                    raise IsADirectoryError(21, "is a directory")
                self.partial.touch()
            except OSError as err:
                raise OutputError(f"--rrd {rrd_path}: cannot write ({err.strerror})") from None
            sinks.append(rr.FileSink(str(self.partial)))
        if spawn and (url := spawn_local_viewer()) is not None:
            sinks.append(rr.GrpcSink(url))
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin="views", name="Views"),
                    rrb.TextLogView(origin="events", name="Events"),
                    row_shares=[3, 1],
                ),
                rrb.Vertical(
                    rrb.Spatial2DView(origin="coverage", name="Coverage"),
                    rrb.TimeSeriesView(origin="metrics/view_error_px", name="Per-view RMS error (px)"),
                ),
                column_shares=[3, 2],
            ),
            collapse_panels=True,
        )
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=blueprint)
        self.rec.send_recording_name("ar-anchor calibrate")

    def event(self, text: str, *, frame: int | None = None, warn: bool = False) -> None:
        rr = self.rr
        if frame is not None:
            self.rec.set_time("frame", sequence=int(frame))
        level = rr.TextLogLevel.WARN if warn else rr.TextLogLevel.INFO
        self.rec.log("events", rr.TextLog(text, level=level), static=frame is None)

    def live_view(self, view: View, image: np.ndarray) -> None:
        """A view a device just kept (on the ``frame`` timeline), so the viewer shows progress."""
        rr = self.rr
        self.rec.set_time("frame", sequence=int(view.frame))
        preview, scale = (view.preview, view.preview_scale) if view.preview else jpeg_preview(image)
        self.rec.log("views/image", rr.EncodedImage(contents=preview, media_type="image/jpeg"))
        self.rec.log(
            "views/image/corners", rr.Points2D((view.corners + 0.5) * scale, radii=2.0, colors=[(40, 220, 80)])
        )

    def result(self, report: CalibrationReport) -> None:
        rr = self.rr
        result = report.result
        final = {id(v): i for i, v in enumerate(result.views)}
        for position, (view, first_error) in enumerate(zip(result.first_views, result.first_errors_px)):
            self.rec.set_time("view", sequence=position)
            self.rec.set_time("frame", sequence=int(view.frame))
            scale = view.preview_scale
            if view.preview:
                self.rec.log("views/image", rr.EncodedImage(contents=view.preview, media_type="image/jpeg"))
            self.rec.log(
                "views/image/corners",
                rr.Points2D((view.corners + 0.5) * scale, radii=2.0, colors=[(40, 220, 80)]),
            )
            self.rec.log("metrics/view_error_px/first_fit", rr.Scalars(first_error))
            index = final.get(id(view))
            if index is not None:
                self.rec.log("metrics/view_error_px/final", rr.Scalars(result.errors_px[index]))
                if index < len(result.reprojected):
                    self.rec.log(
                        "views/image/reprojected",
                        rr.Points2D((result.reprojected[index] + 0.5) * scale, radii=1.0, colors=[(255, 60, 60)]),
                    )
                text = f"view {position}: {view.name}, {view.count} corners, {result.errors_px[index]:.3f} px"
                self.rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.INFO))
            else:
                self.rec.log("views/image/reprojected", rr.Clear(recursive=False))
                why = next((d for d in result.dropped if d.name == view.name and d.frame == view.frame), None)
                self.rec.log("events", rr.TextLog(f"view {position}: {why or view.name}", level=rr.TextLogLevel.WARN))
        self._coverage(report)
        for line in format_report(report).splitlines():
            self.rec.log("events", rr.TextLog(line, level=rr.TextLogLevel.INFO), static=False)

    def _coverage(self, report: CalibrationReport) -> None:
        rr = self.rr
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
            self.rec.log("coverage", rr.EncodedImage(contents=png.tobytes(), media_type="image/png"), static=True)
        corners = np.concatenate([v.corners for v in report.result.views])
        self.rec.log(
            "coverage/corners", rr.Points2D((corners + 0.5) * scale, radii=1.0, colors=[(255, 255, 255)]), static=True
        )

    def close(self, *, keep: bool) -> None:
        try:
            self.rec.flush(timeout_sec=10.0)
        finally:
            self.rec.disconnect()
            if self.partial is not None and self.path is not None and self.partial.exists():
                if keep:
                    try:
                        os.replace(self.partial, self.path)
                    except OSError as err:
                        self.partial.unlink(missing_ok=True)
                        raise OutputError(f"--rrd {self.path}: cannot write ({err.strerror})") from None
                else:
                    self.partial.unlink(missing_ok=True)
