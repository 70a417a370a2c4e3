"""The viewer layouts: the tracker run's, the calibration's and a study's (rerun blueprints)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import rerun.blueprint as rrb

__all__ = ["PROJECTED", "RUN_PLOTS", "Framing", "calibrate_blueprint", "run_blueprint", "study_blueprint"]

PROJECTED = (  # the "AR overlay" view's contents: the camera's image, and the 3D world projected onto it
    "+ $origin/**",
    "+ /world/**",
    "- /world/camera_trajectory",
    "- /world/causal",
    "- /world/hypotheses",
    "- /world/labels",
    "- /world/truth_camera",
)


@dataclass(frozen=True)
class Framing:
    """Where the 3D view's eye starts: at ``eye``, looking at ``target`` (world coordinates, metres)."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]

    @classmethod
    def on(cls, centres: np.ndarray, sizes: np.ndarray, camera: np.ndarray | None) -> Framing:
        """Framed on targets at ``centres`` (N, 3) of side ``sizes`` (N,), seen from the side of ``camera``
        (the camera centre; None: the anchor's front, +z). The eye is far enough for the whole group, and
        near enough that a single marker fills the view rather than being a dot beside the camera."""
        centres = np.asarray(centres, np.float64).reshape(-1, 3)
        look = centres.mean(axis=0)
        radius = float(np.max(np.linalg.norm(centres - look, axis=1) + np.asarray(sizes, np.float64)))
        toward = np.array([0.0, 0.0, 1.0]) if camera is None else np.asarray(camera, np.float64) - look
        toward = toward / (np.linalg.norm(toward) or 1.0)
        oblique = toward + np.array([0.35, 0.45, 0.0])  # a little from the right and above: depth shows
        eye = look + oblique / np.linalg.norm(oblique) * max(3.0 * radius, 0.15)
        return cls(tuple(map(float, eye)), tuple(map(float, look)))  # type: ignore[arg-type]


#: The run layout's time series: (origin, title).
RUN_PLOTS = (
    ("metrics/reproj_px", "Reprojection error (px)"),
    ("metrics/ambiguity", "IPPE ambiguity ratio"),
    ("metrics/flip_evidence_px", "Flip evidence (px, + = branch 0)"),
    ("metrics/rotation_error_deg", "Rotation error vs truth (deg)"),
    ("metrics/inliers", "Board inliers (corners)"),
    ("metrics/latency", "Latency (ms)"),
)


def run_blueprint(
    *, overlay_image: bool = False, framing: Framing | None = None, root: str | None = None
) -> rrb.Blueprint:
    """A tracker run: the camera with the AR overlay as the main view, the 3D scene beside it, the plots in
    a column on the right, the tracker's events below.

    The camera views' origin is the camera's pinhole (``world/camera``), the image its child. "AR overlay"
    (the active tab) also holds the 3D world, which the viewer projects through the pinhole onto the
    frame: the targets' overlay meshes, marker squares and axes (not the camera's own trajectory, the
    filter's hypotheses, the 3D labels, which the 2D outlines' ids repeat, or the true camera). "Camera" is
    the frame and its 2D detections alone; "Overlay image" (``overlay_image``: ``[recording]
    overlay_images``) the annotated image the run drew itself. The 3D eye starts at ``framing`` (the
    recorder sends the layout again, framed on the targets, once it has placed them; before, the viewer
    frames the whole scene), a decimetre grid gives scale. The plots have no legend over their data
    (hovering a line names it); the ambiguity plot shows 1..5 (values near 1 are the ambiguous ones; the
    data itself is not clipped).

    ``root``: the run's entities are under it (a named camera's, ``cameras/<name>``: :class:`~.sinks.Recording`),
    and so is every origin and contents rule here; the views' names say the camera's name.
    """

    def at(path: str) -> str:
        return f"{root}/{path}" if root else path

    projected = [rule.replace(" /world", f" /{at('world')}") for rule in PROJECTED]
    named = f" ({root.rsplit('/', 1)[-1]})" if root else ""
    camera_views = [
        rrb.Spatial2DView(origin=at("world/camera"), contents=projected, name=f"AR overlay{named}"),
        rrb.Spatial2DView(origin=at("world/camera"), contents="$origin/**", name=f"Camera{named}"),
    ]
    if overlay_image:
        camera_views.append(rrb.Spatial2DView(origin=at("camera/overlay"), name=f"Overlay image{named}"))
    eye = None
    if framing is not None:
        eye = rrb.EyeControls3D(
            kind=rrb.Eye3DKind.Orbital, position=framing.eye, look_target=framing.target, eye_up=(0, 1, 0)
        )
    plots = [
        rrb.TimeSeriesView(
            origin=at(origin),
            name=title,
            plot_legend=rrb.PlotLegend(visible=False),
            axis_y=rrb.ScalarAxis(range=(1.0, 5.0)) if origin == "metrics/ambiguity" else None,
        )
        for origin, title in RUN_PLOTS
    ]
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Tabs(*camera_views, active_tab=f"AR overlay{named}"),
                rrb.Spatial3DView(
                    origin=at("world"),
                    name=f"3D scene{named}",
                    line_grid=rrb.LineGrid3D(visible=True, spacing=0.1),
                    eye_controls=eye,
                ),
                rrb.Vertical(*plots),
                column_shares=[4, 3, 2],
            ),
            rrb.TextLogView(origin=at("events"), name=f"Tracker events{named}"),
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
