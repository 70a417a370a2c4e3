"""The studies' figures (matplotlib's object API: no pyplot, no global state, no display)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .jitter import ONSET_FACTOR, STYLES
from .pnp import SUCCESS_ERROR_M, SUCCESS_RECALL
from .report import metres

__all__ = ["plot_jitter", "plot_outliers", "plot_ransac"]


def _figure(width_in: float, height_in: float, columns: int) -> tuple[Any, Any]:
    from matplotlib.figure import Figure  # no pyplot: no global state, no display backend

    figure = Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    return figure, figure.subplots(1, columns)


def _save(figure: Any, path: Path) -> None:
    figure.savefig(path, dpi=100, format="png")  # (the path may be a partial name: the format is not from it)


def _log_scale_if_positive(ax: Any, values: Any) -> bool:
    """A log y axis when some value is positive (a log axis of none fails to draw: no detection at any
    distance, or no noise); a linear one saying so otherwise. Whether the axis is log."""
    array = np.asarray([v for v in values if v is not None], dtype=np.float64)
    if np.any(np.isfinite(array) & (array > 0)):
        ax.set_yscale("log")
        return True
    ax.text(0.5, 0.5, "no positive value to plot", transform=ax.transAxes, ha="center", va="center", color="grey")
    return False


def plot_outliers(result: dict[str, Any], path: Path) -> None:
    """Per-seed translation errors (log scale) and RANSAC's inlier counts."""
    rows, settings = result["seeds"], result["settings"]
    figure, (errors_ax, inliers_ax) = _figure(11.0, 4.2, 2)
    rng = np.random.default_rng(0)
    for position, (key, colour) in enumerate((("plain_error_m", "tab:red"), ("ransac_error_m", "tab:blue"))):
        values = np.array([r[key] for r in rows if r[key] is not None])
        errors_ax.scatter(position + rng.uniform(-0.15, 0.15, values.size), values, s=10, alpha=0.6, color=colour)
        if values.size:
            errors_ax.hlines(np.median(values), position - 0.3, position + 0.3, color="black", linewidth=2)
            errors_ax.annotate(
                metres(float(np.median(values))),
                (position + 0.32, float(np.median(values))),
                va="center",
                fontsize=9,
            )
    log = _log_scale_if_positive(errors_ax, [r[k] for r in rows for k in ("plain_error_m", "ransac_error_m")])
    errors_ax.set_xticks([0, 1], ["solvePnP\n(all points)", "solvePnPRansac\n+ RefineLM"])
    errors_ax.set_xlim(-0.6, 1.9)
    errors_ax.set_ylabel("translation error (m, log)" if log else "translation error (m)")
    errors_ax.set_title(f"{len(rows)} seeds, {settings['contamination']:.0%} of points replaced; bar: median")
    errors_ax.grid(True, axis="y", which="both", alpha=0.3)
    honest = result["summary"]["honest_points"]
    counts = np.array([r["inliers"] for r in rows])
    honest_counts = np.array([r["honest_inliers"] for r in rows])
    low = int(min(counts.min(initial=honest), honest_counts.min(initial=honest))) - 1
    bins = np.arange(low, int(counts.max(initial=honest)) + 2) - 0.5
    inliers_ax.hist(counts, bins=bins, color="tab:blue", alpha=0.6, label="RANSAC inliers")
    inliers_ax.hist(honest_counts, bins=bins, histtype="step", color="black", linewidth=1.5, label="honest among them")
    inliers_ax.axvline(honest, color="tab:green", linestyle="--", label=f"{honest} honest points")
    inliers_ax.set_xlabel("points")
    inliers_ax.set_ylabel("seeds")
    inliers_ax.set_title(f"inlier threshold {settings['threshold_px']:g} px, {settings['iterations']} iterations")
    inliers_ax.legend(fontsize=8)
    _save(figure, path)


def plot_ransac(result: dict[str, Any], path: Path) -> None:
    """Heatmaps over contamination x threshold: median translation error and median recall."""
    thresholds = result["settings"]["thresholds_px"]
    contaminations = result["settings"]["contaminations_pct"]
    error = np.full((len(thresholds), len(contaminations)), np.nan)
    recall = np.full_like(error, np.nan)
    success = np.full_like(error, np.nan)
    for cell in result["cells"]:
        i, j = thresholds.index(cell["threshold_px"]), contaminations.index(cell["contamination_pct"])
        error[i, j] = math.inf if cell["median_error_m"] is None else cell["median_error_m"]
        recall[i, j] = cell["median_recall"]
        success[i, j] = cell["success_pct"]
    from matplotlib.colors import LogNorm

    figure, (error_ax, recall_ax) = _figure(13.0, 4.6, 2)
    shown = np.where(np.isfinite(error), error * 1e3, 1e4)
    image = error_ax.imshow(shown, cmap="viridis_r", norm=LogNorm(vmin=0.3, vmax=1e4), aspect="auto")
    figure.colorbar(image, ax=error_ax, label="median translation error (mm, log)")
    image = recall_ax.imshow(recall, cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    figure.colorbar(image, ax=recall_ax, label="median inlier recall")
    for ax, values, title in (
        (error_ax, error, "translation error after RANSAC + LM"),
        (recall_ax, recall, "inlier recall (honest points kept)"),
    ):
        for i in range(len(thresholds)):
            for j in range(len(contaminations)):
                if ax is error_ax:
                    text = "fail" if not np.isfinite(values[i, j]) else f"{values[i, j] * 1e3:.3g}"
                else:
                    text = f"{values[i, j]:.2f}"
                if success[i, j] < 50.0:
                    text += "\n✗"
                if ax is error_ax:
                    dark = not np.isfinite(values[i, j]) or values[i, j] > 0.05
                else:
                    dark = values[i, j] < 0.5
                ax.text(j, i, text, ha="center", va="center", fontsize=7, color="white" if dark else "black")
        ax.set_xticks(range(len(contaminations)), [f"{c:g}" for c in contaminations])
        ax.set_yticks(range(len(thresholds)), [f"{t:g}" for t in thresholds])
        ax.set_xlabel("contamination (% of points replaced)")
        ax.set_ylabel("inlier threshold (px)")
        ax.set_title(title)
    figure.suptitle(
        f"{result['settings']['seeds']} seeds per cell, pixel noise {result['settings']['noise_px']:g} px, "
        f"{result['settings']['iterations']} iterations; ✗: fewer than half the seeds succeed "
        f"(error < {SUCCESS_ERROR_M * 100:g} cm and recall >= {SUCCESS_RECALL:.0%})",
        fontsize=10,
    )
    _save(figure, path)


def plot_jitter(result: dict[str, Any], path: Path) -> None:
    """Std of ||t|| and of orientation, and the flipped-frame rate, versus distance."""
    rows, summary = result["distances"], result["summary"]
    distances = [r["distance_m"] for r in rows]
    figure, axes = _figure(15.0, 4.6, 3)
    for ax, metric, label in (
        (axes[0], "distance_std_mm", "std of distance ||t|| (mm)"),
        (axes[1], "rotation_std_deg", "orientation std (deg, RMS about the mean)"),
        (axes[2], "flipped_pct", f"flipped frames (% > {result['settings']['flip_deg']:g} deg off)"),
    ):
        for (target, pipeline), (colour, line, marker, name) in STYLES.items():
            values = [r[f"{target}_{pipeline}"].get(metric, math.nan) for r in rows]
            ax.plot(distances, values, color=colour, linestyle=line, marker=marker, markersize=4, label=name)
        ax.set_xlabel("distance (m)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if metric != "flipped_pct":
            ax.set_xscale("log")
            _log_scale_if_positive(ax, [r[f"{t}_{p}"].get(metric) for r in rows for t, p in STYLES])
            ax.set_xticks(distances, [f"{d:g}" for d in distances], fontsize=7)
            ax.minorticks_off()
        if metric == "rotation_std_deg" and rows and rows[0]["marker_raw"].get(metric) is not None:
            near = rows[0]["marker_raw"][metric]
            trend = [ONSET_FACTOR * near * (d / distances[0]) ** 2 for d in distances]
            ax.plot(distances, trend, color="grey", linewidth=0.8, label=f"{ONSET_FACTOR:g}x d² trend of marker raw")
        for key, style, text in (("onset_noise_m", "-.", "noise onset"), ("onset_gap_m", ":", "IPPE gap < margin")):
            if summary.get(key) is not None:
                ax.axvline(
                    summary[key], color="grey", linestyle=style, linewidth=1.2, label=f"{text} {summary[key]:g} m"
                )
    axes[1].legend(fontsize=7)
    settings = result["settings"]
    figure.suptitle(
        f"static {settings['marker_m'] * 100:g} cm marker and 2x2 board, {settings['camera']}, "
        f"{settings['tilt_deg']:g} deg off-axis, {settings['frames']} frames per distance "
        f"(first {settings['settle_frames']} skipped), noise {settings['sensor_noise_grey']:g} grey levels",
        fontsize=10,
    )
    _save(figure, path)
