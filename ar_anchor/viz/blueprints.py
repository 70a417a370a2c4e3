"""The viewer layouts: the tracker run's, the calibration's and a study's (rerun blueprints)."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

__all__ = ["calibrate_blueprint", "run_blueprint", "study_blueprint"]


def run_blueprint() -> rrb.Blueprint:
    """A tracker run: image, 3D scene and plots side by side, the tracker's events below.

    The 3D eye starts in front of the anchor (a marker frame: y up, z toward the viewer), a
    decimetre grid gives scale; the ambiguity plot shows 1..5 (values near 1 are the ambiguous
    ones; the data itself is not clipped).
    """
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Tabs(
                    rrb.Spatial2DView(origin="camera/image", name="Camera"),
                    rrb.Spatial2DView(origin="camera/overlay", name="AR overlay"),
                ),
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
