"""A study's rerun recording: its figure and table, its numbers as time series, and (outliers) the
problem's points, (jitter) each distance's view and the per-frame rotation errors; logged through
:class:`ar_anchor.viz.sinks.Recording`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import OutputError
from ...geometry import Pose, angle_between_deg
from .jitter import JITTER_SERIES, STYLES, JitterSetup
from .pnp import PnPSetup, make_correspondences

if TYPE_CHECKING:
    from ...viz.sinks import Recording

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

_HONEST, _REPLACED, _POINTS = (40, 200, 80), (230, 50, 50), (200, 200, 200)


class StudyRecording:
    """One study's rerun recording, written to ``<out>/.<name>.rrd.<pid>.tmp`` and renamed to ``<name>.rrd``
    by :meth:`close` (complete) or removed by :meth:`discard` (interrupted, failed);
    :attr:`recording` is the :class:`~ar_anchor.viz.sinks.Recording` the study's numbers are logged to."""

    def __init__(self, path: Path, name: str, plots: Sequence[tuple[str, str]]) -> None:
        # (imports rerun: only when a study runs, not on every CLI start)
        from ...viz.blueprints import study_blueprint
        from ...viz.sinks import Recording

        self.recording: Recording = Recording(
            "ar_anchor_study",
            path=path,
            partial=True,
            blueprint=study_blueprint(name, plots),
            name=f"ar-anchor study {name}",
        )

    def documents(self, name: str, figure: Path, markdown: str) -> None:
        """The study's figure (``<name>/figure``) and table (``<name>/table``), static."""
        self.recording.image_file(f"{name}/figure", figure)
        self.recording.markdown(f"{name}/table", markdown)

    def flush(self) -> None:
        """Write out what was logged (at most 30 s), so that :meth:`close` is quick."""
        self.recording.flush(timeout_s=30.0)

    def close(self) -> None:
        """Flush and rename the file into place: the recording is complete."""
        self.recording.close(keep=True, timeout_s=30.0)

    def discard(self) -> None:
        """Close and remove the partial file (an interrupted or failed study leaves no recording that
        looks final); a sink that cannot be flushed within a second is dropped all the same."""
        try:
            self.recording.close(keep=False, timeout_s=1.0)
        except OutputError:
            pass


def record_result(
    recording: StudyRecording, name: str, setup: PnPSetup | JitterSetup, result: dict[str, Any], views: Any
) -> None:
    """A finished study's numbers as time series (outliers: also each seed's pixels and the points;
    jitter: each distance's noise-free ``views``)."""
    if name == "outliers":
        _record_outliers(recording.recording, setup, result)
    elif name == "ransac":
        _record_ransac(recording.recording, result)
    else:
        _record_jitter_summary(recording.recording, {**result, "views": views})


def _record_outliers(rec: Recording, setup: PnPSetup, result: dict[str, Any]) -> None:
    for row in result["seeds"]:
        rec.time("seed", sequence=row["seed"])
        rec.scalar("outliers/translation_error_m/solvePnP", row["plain_error_m"])
        rec.scalar("outliers/translation_error_m/ransac_lm", row["ransac_error_m"])
        rec.scalar("outliers/inliers/ransac", row["inliers"])
        rec.scalar("outliers/inliers/honest", row["honest_inliers"])
        problem = make_correspondences(setup, result["settings"]["contamination"], row["seed"])
        rec.image_points("outliers/image/honest", problem.pixels[problem.honest], radius=3.0, colours=[_HONEST])
        rec.image_points("outliers/image/replaced", problem.pixels[~problem.honest], radius=3.0, colours=[_REPLACED])
    first = make_correspondences(setup, result["settings"]["contamination"], result["seeds"][0]["seed"])
    rec.points3d("outliers/world/points", first.points_in_world, radius=0.03, colours=[_POINTS], static=True)
    rec.points3d(
        "outliers/world/true_camera",
        np.array([setup.camera_from_world.camera_centre()]),
        radius=0.08,
        colours=[_HONEST],
        labels=["true camera"],
        static=True,
    )


def _record_ransac(rec: Recording, result: dict[str, Any]) -> None:
    for cell in result["cells"]:
        rec.time("contamination_pct", sequence=round(cell["contamination_pct"]))
        key = f"{cell['threshold_px']:g}px".replace(".", "_")
        error = cell["median_error_m"]
        rec.scalar(f"ransac/median_error_mm/{key}", None if error is None else 1e3 * error)
        rec.scalar(f"ransac/median_recall/{key}", cell["median_recall"])
        rec.scalar(f"ransac/success_pct/{key}", cell["success_pct"])


def _record_jitter_summary(rec: Recording, result: dict[str, Any]) -> None:
    for row, view in zip(result["distances"], result["views"]):
        rec.time("distance_mm", sequence=round(1e3 * row["distance_m"]))
        for target, pipeline in STYLES:
            metrics = row[f"{target}_{pipeline}"]
            for metric in ("rotation_std_deg", "distance_std_mm", "flipped_pct"):
                rec.scalar(f"jitter/{metric}/{target}_{pipeline}", metrics.get(metric))
        rec.jpeg("jitter/view", view, quality=80, scale=0.5)


def jitter_frame_logger(recording: StudyRecording, setup: JitterSetup) -> Callable[..., None]:
    """Per-frame rotation error against the truth, raw and tracked, on one ``frame`` timeline across distances."""
    rec = recording.recording

    def log_frame(d_index: int, index: int, result: Any, truth: dict[str, Pose]) -> None:
        rec.time("frame", sequence=d_index * setup.frames + index)
        rec.time("distance_mm", sequence=round(1e3 * setup.distances_m[d_index]))
        for target, name in JITTER_SERIES:
            measured, true = result.targets.get(name), truth.get(name)
            if measured is None or true is None:
                continue
            if measured.raw is not None:
                rec.scalar(
                    f"jitter/frames/rotation_error_deg/{target}_raw",
                    angle_between_deg(measured.raw.rotation, true.rotation),
                )
            rec.scalar(
                f"jitter/frames/rotation_error_deg/{target}_tracker",
                angle_between_deg(measured.pose.rotation, true.rotation),
            )

    return log_frame
