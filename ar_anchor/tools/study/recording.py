"""A study's rerun recording: its figure and table, its numbers as time series, and (outliers) the
problem's points, (jitter) each distance's view and the per-frame rotation errors."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2

from ...errors import OutputError
from ...geometry import Pose, angle_between_deg
from .jitter import JITTER_SERIES, STYLES, JitterSetup
from .pnp import PnPSetup, make_correspondences

__all__ = ["PLOTS", "StudyRecording", "jitter_frame_logger", "record_result"]

# each study's time-series views: (entity origin, title)
PLOTS = {
    "outliers": [("outliers/translation_error_m", "Translation error (m)"), ("outliers/inliers", "Inliers")],
    "ransac": [
        ("ransac/median_error_mm", "Median translation error (mm)"),
        ("ransac/median_recall", "Median recall"),
        ("ransac/success_pct", "Seeds that succeed (%)"),
    ],
    "jitter": [
        ("jitter/rotation_std_deg", "Orientation std (deg)"),
        ("jitter/distance_std_mm", "Distance std (mm)"),
        ("jitter/frames/rotation_error_deg", "Rotation error per frame (deg)"),
    ],
}


class StudyRecording:
    """One study's rerun recording, written to ``<out>/<name>.rrd`` (renamed into place when complete)."""

    def __init__(self, path: Path, name: str, plots: Sequence[tuple[str, str]]) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        self.rr = rr
        self.path = path
        self.partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        self.rec = rr.RecordingStream("ar_anchor_study")
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin=f"{name}/figure", name="Figure"),
                    rrb.TextDocumentView(origin=f"{name}/table", name="Table"),
                    row_shares=[3, 2],
                ),
                rrb.Vertical(*[rrb.TimeSeriesView(origin=origin, name=title) for origin, title in plots]),
                column_shares=[3, 2],
            ),
            collapse_panels=True,
        )
        self.rec.set_sinks(rr.FileSink(str(self.partial)), default_blueprint=blueprint)
        self.rec.send_recording_name(f"ar-anchor study {name}")

    def scalar(self, entity: str, value: float | None) -> None:
        if value is not None and math.isfinite(value):
            self.rec.log(entity, self.rr.Scalars(float(value)))

    def time(self, timeline: str, value: int) -> None:
        self.rec.set_time(timeline, sequence=int(value))

    def documents(self, name: str, figure: Path, markdown: str) -> None:
        rr = self.rr
        self.rec.log(f"{name}/figure", rr.EncodedImage(path=figure), static=True)
        self.rec.log(f"{name}/table", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)

    def close(self) -> None:
        try:
            self.rec.flush(timeout_sec=30.0)
        finally:
            self.rec.disconnect()
        try:
            os.replace(self.partial, self.path)
        except OSError as err:
            self.partial.unlink(missing_ok=True)
            raise OutputError(f"{self.path}: cannot write ({err.strerror})") from None


def record_result(
    recording: StudyRecording, name: str, setup: PnPSetup | JitterSetup, result: dict[str, Any], views: Any
) -> None:
    """A finished study's numbers as time series (outliers: also each seed's pixels and the points;
    jitter: each distance's noise-free ``views``)."""
    if name == "outliers":
        _record_outliers(recording, setup, result)
    elif name == "ransac":
        _record_ransac(recording, result)
    else:
        _record_jitter_summary(recording, {**result, "views": views})


def _record_outliers(recording: StudyRecording, setup: PnPSetup, result: dict[str, Any]) -> None:
    rr = recording.rr
    for row in result["seeds"]:
        recording.time("seed", row["seed"])
        recording.scalar("outliers/translation_error_m/solvePnP", row["plain_error_m"])
        recording.scalar("outliers/translation_error_m/ransac_lm", row["ransac_error_m"])
        recording.scalar("outliers/inliers/ransac", row["inliers"])
        recording.scalar("outliers/inliers/honest", row["honest_inliers"])
        problem = make_correspondences(setup, result["settings"]["contamination"], row["seed"])
        recording.rec.log(
            "outliers/image/honest",
            rr.Points2D(problem.pixels[problem.honest] + 0.5, radii=3.0, colors=[(40, 200, 80)]),
        )
        recording.rec.log(
            "outliers/image/replaced",
            rr.Points2D(problem.pixels[~problem.honest] + 0.5, radii=3.0, colors=[(230, 50, 50)]),
        )
    first = make_correspondences(setup, result["settings"]["contamination"], result["seeds"][0]["seed"])
    recording.rec.log(
        "outliers/world/points", rr.Points3D(first.points_in_world, radii=0.03, colors=[(200, 200, 200)]), static=True
    )
    recording.rec.log(
        "outliers/world/true_camera",
        rr.Points3D(
            [setup.camera_from_world.camera_centre()], radii=0.08, colors=[(40, 200, 80)], labels=["true camera"]
        ),
        static=True,
    )


def _record_ransac(recording: StudyRecording, result: dict[str, Any]) -> None:
    for cell in result["cells"]:
        recording.time("contamination_pct", round(cell["contamination_pct"]))
        key = f"{cell['threshold_px']:g}px".replace(".", "_")
        error = cell["median_error_m"]
        recording.scalar(f"ransac/median_error_mm/{key}", None if error is None else 1e3 * error)
        recording.scalar(f"ransac/median_recall/{key}", cell["median_recall"])
        recording.scalar(f"ransac/success_pct/{key}", cell["success_pct"])


def _record_jitter_summary(recording: StudyRecording, result: dict[str, Any]) -> None:
    rr = recording.rr
    for row, view in zip(result["distances"], result["views"]):
        recording.time("distance_mm", round(1e3 * row["distance_m"]))
        for target, pipeline in STYLES:
            metrics = row[f"{target}_{pipeline}"]
            for metric in ("rotation_std_deg", "distance_std_mm", "flipped_pct"):
                recording.scalar(f"jitter/{metric}/{target}_{pipeline}", metrics.get(metric))
        small = cv2.resize(view, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
        if ok:
            recording.rec.log("jitter/view", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))


def jitter_frame_logger(recording: StudyRecording, setup: JitterSetup) -> Callable[..., None]:
    """Per-frame rotation error against the truth, raw and tracked, on one ``frame`` timeline across distances."""

    def log_frame(d_index: int, index: int, result: Any, truth: dict[str, Pose]) -> None:
        recording.time("frame", d_index * setup.frames + index)
        recording.time("distance_mm", round(1e3 * setup.distances_m[d_index]))
        for target, name in JITTER_SERIES:
            measured, true = result.targets.get(name), truth.get(name)
            if measured is None or true is None:
                continue
            if measured.raw is not None:
                recording.scalar(
                    f"jitter/frames/rotation_error_deg/{target}_raw",
                    angle_between_deg(measured.raw.rotation, true.rotation),
                )
            recording.scalar(
                f"jitter/frames/rotation_error_deg/{target}_tracker",
                angle_between_deg(measured.pose.rotation, true.rotation),
            )

    return log_frame
