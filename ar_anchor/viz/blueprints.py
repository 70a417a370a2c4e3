"""The viewer layouts: the tracker run's, the calibration's and a study's (rerun blueprints)."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

__all__ = ["PROJECTED", "calibrate_blueprint", "run_blueprint", "study_blueprint"]

PROJECTED = (  # the "AR overlay" view's contents: the camera's image, and the 3D world projected onto it
    "+ $origin/**",
    "+ /world/**",
    "- /world/camera_trajectory",
    "- /world/causal",
    "- /world/hypotheses",
    "- /world/labels",
    "- /world/truth_camera",
)


def run_blueprint(*, overlay_image: bool = False) -> rrb.Blueprint:
    """A tracker run: the camera, 3D scene and plots side by side, the tracker's events below.

    The camera views' origin is the camera's pinhole (``world/camera``), the image its child. "AR overlay"
    also holds the 3D world, which the viewer projects through the pinhole onto the frame: the targets'
    overlay meshes, marker squares and axes (not the camera's own trajectory, the filter's hypotheses, the
    3D labels, which the 2D outlines' ids repeat, or the true camera). "Camera" is the frame and its 2D
    detections alone; "Overlay image" (``overlay_image``: ``[recording] overlay_images``) the annotated
    image the run drew itself. The 3D eye starts in front of
    the anchor (a marker frame: y up, z toward the viewer), a decimetre grid gives scale; the ambiguity plot
    shows 1..5 (values near 1 are the ambiguous ones; the data itself is not clipped).
    """
    camera_views = [
        rrb.Spatial2DView(origin="world/camera", contents=list(PROJECTED), name="AR overlay"),
        rrb.Spatial2DView(origin="world/camera", contents="$origin/**", name="Camera"),
    ]
    if overlay_image:
        camera_views.append(rrb.Spatial2DView(origin="camera/overlay", name="Overlay image"))
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Tabs(*camera_views),
                rrb.Spatial3DView(
                    origin="world",
                    name="3D scene",
                    line_grid=rrb.LineGrid3D(visible=True, spacing=0.1),
                    eye_controls=rrb.EyeControls3D(
                        kind=rrb.Eye3DKind.Orbital,
                        position=(0.9, 0.7, 1.8),
                        look_target=(0.0, 0.0, 0.4),
                        eye_up=(0, 1, 0),
                    ),
                ),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="metrics/reproj_px", name="Reprojection error (px)"),
                    rrb.TimeSeriesView(
                        origin="metrics/ambiguity", name="IPPE ambiguity ratio", axis_y=rrb.ScalarAxis(range=(1.0, 5.0))
                    ),
                    rrb.TimeSeriesView(origin="metrics/flip_evidence_px", name="Flip evidence (px, + = branch 0)"),
                    rrb.TimeSeriesView(origin="metrics/rotation_error_deg", name="Rotation error vs truth (deg)"),
                    rrb.TimeSeriesView(origin="metrics/inliers", name="Board inliers (corners)"),
                    rrb.TimeSeriesView(origin="metrics/latency", name="Latency (ms)"),
                ),
                column_shares=[3, 3, 2],
            ),
            rrb.TextLogView(origin="events", name="Tracker events"),
            row_shares=[5, 1],
        ),
        collapse_panels=True,
    )


def calibrate_blueprint() -> rrb.Blueprint:
    """``ar-anchor calibrate``: the views with their corners beside the coverage heat map and per-view errors."""
    return rrb.Blueprint(
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


def study_blueprint(name: str, plots: Sequence[tuple[str, str]]) -> rrb.Blueprint:
    """One study (``name``): its figure and table beside its ``plots`` (entity origin, title)."""
    return rrb.Blueprint(
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
