"""The studies' Markdown: each study's table and the facts it shows, and a one-line headline."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from .jitter import ONSET_FACTOR, STYLES
from .pnp import OTHER_SOLVERS, RANSAC_SAMPLE

__all__ = ["headline", "jitter_markdown", "metres", "outliers_markdown", "ransac_markdown", "seconds_text"]


def metres(value: float | None) -> str:
    """A length in the unit that suits it (m, cm, mm); ``failed`` for None."""
    if value is None:
        return "failed"
    if value >= 1.0:
        return f"{value:.2f} m"
    if value >= 0.01:
        return f"{value * 100:.1f} cm"
    return f"{value * 1e3:.2f} mm"


def _num(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def outliers_markdown(result: dict[str, Any]) -> str:
    """``outliers.md``: setup, the error table and what it shows."""
    s, summary = result["settings"], result["summary"]
    plain, ransac = summary["plain_error_m"], summary["ransac_error_m"]
    inliers, honest_inliers = summary["inliers"], summary["honest_inliers"]
    honest = summary["honest_points"]
    lines = [
        "# Outlier rescue: least squares vs RANSAC",
        "",
        _produced(result),
        "",
        f"{s['points']} points at {s['depth_m'][0]:g}-{s['depth_m'][1]:g} m depth, drawn in the camera frame (uniform "
        "pixel, uniform depth) and expressed in the world frame with the inverse of the true pose "
        f"(rvec {_vector(s['true_rvec'])}, tvec {_vector(s['true_tvec_m'])} m); camera {s['camera']}; "
        f"pixel noise {s['noise_px']:g} px per coordinate; {s['contamination']:.0%} of the correspondences "
        f"replaced by uniform random pixels. Plain `solvePnP` (iterative) uses all points; `solvePnPRansac` "
        f"({s['threshold_px']:g} px, {s['iterations']} iterations, confidence {s['confidence']:g}) is followed by "
        "`solvePnPRefineLM` on its inliers. Translation error: `||t - t_true||`.",
        "",
        "![outliers](outliers.png)",
        "",
        f"| over {s['seeds']} seeds | median | 10th pct | 90th pct | max |",
        "|---|---|---|---|---|",
        f"| translation error, `solvePnP` | {metres(plain['median'])} | {metres(plain['p10'])} "
        f"| {metres(plain['p90'])} | {metres(plain['max'])} |",
        *[
            f"| translation error, `solvePnP` {name.upper()} | {metres(summary[f'{name}_error_m']['median'])} "
            f"| {metres(summary[f'{name}_error_m']['p10'])} | {metres(summary[f'{name}_error_m']['p90'])} "
            f"| {metres(summary[f'{name}_error_m']['max'])} |"
            for name, _ in OTHER_SOLVERS
        ],
        f"| translation error, RANSAC + LM | {metres(ransac['median'])} | {metres(ransac['p10'])} "
        f"| {metres(ransac['p90'])} | {metres(ransac['max'])} |",
        f"| rotation error, `solvePnP` (deg) | {_num(summary['plain_rotation_deg']['median'])} "
        f"| {_num(summary['plain_rotation_deg']['p10'])} | {_num(summary['plain_rotation_deg']['p90'])} "
        f"| {_num(summary['plain_rotation_deg']['max'])} |",
        f"| rotation error, RANSAC + LM (deg) | {_num(summary['ransac_rotation_deg']['median'], 4)} "
        f"| {_num(summary['ransac_rotation_deg']['p10'], 4)} | {_num(summary['ransac_rotation_deg']['p90'], 4)} "
        f"| {_num(summary['ransac_rotation_deg']['max'], 4)} |",
        f"| RANSAC inliers | {_num(inliers['median'], 0)} | {_num(inliers['p10'], 0)} | {_num(inliers['p90'], 0)} "
        f"| {_num(inliers['max'], 0)} |",
        f"| honest points among them (of {honest}) | {_num(honest_inliers['median'], 0)} "
        f"| {_num(honest_inliers['p10'], 0)} | {_num(honest_inliers['p90'], 0)} | {_num(honest_inliers['max'], 0)} |",
        "",
        "What this shows:",
        "",
        f"- {s['contamination']:.0%} of wrong correspondences drag least squares off by {metres(plain['median'])} "
        f"(median; 10-90 % of seeds: {metres(plain['p10'])} to {metres(plain['p90'])}; the non-iterative "
        + " and ".join(f"{n.upper()} {metres(summary[f'{n}_error_m']['median'])}" for n, _ in OTHER_SOLVERS)
        + f"); RANSAC + LM recovers "
        f"{metres(ransac['median'])} (90th percentile {metres(ransac['p90'])}). "
        f"{ransac['failed']} RANSAC and {plain['failed']} `solvePnP` solves failed outright.",
        f"- RANSAC keeps all {honest} honest points in {summary['all_honest_recovered_pct']:.0f} % of the seeds and "
        f"misses at most one in {summary['at_most_one_honest_missed_pct']:.0f} %; "
        + (
            "no replaced point slipped into an inlier set. "
            if summary["replaced_admitted_max"] == 0
            else f"at most {summary['replaced_admitted_max']} replaced point(s) slipped into an inlier set. "
        )
        + "The inlier set is "
        "the one of RANSAC's best minimal-sample model, which is itself noisy: at the refined pose, all honest "
        f"points lie within the threshold in {summary['all_honest_within_refined_pct']:.0f} % of the seeds.",
        "",
    ]
    return "\n".join(lines)


def ransac_markdown(result: dict[str, Any]) -> str:
    """``ransac.md``: error, recall and success tables over threshold x contamination, and what they show."""
    s = result["settings"]
    thresholds, contaminations = s["thresholds_px"], s["contaminations_pct"]
    cells = {(c["threshold_px"], c["contamination_pct"]): c for c in result["cells"]}
    header = "| threshold \\ contamination | " + " | ".join(f"{c:g} %" for c in contaminations) + " |"
    rule = "|---|" + "---|" * len(contaminations)

    def table(fmt: Callable[[dict[str, Any]], str]) -> list[str]:
        return [header, rule] + [
            f"| {t:g} px | " + " | ".join(fmt(cells[t, c]) for c in contaminations) + " |" for t in thresholds
        ]

    lines = [
        "# RANSAC inlier threshold vs contamination",
        "",
        _produced(result),
        "",
        f"The problem of the [outliers study](outliers.md) ({s['points']} points, {s['noise_px']:g} px noise, camera "
        f"{s['camera']}), {s['seeds']} seeds per cell (the same problems in every cell of a column), "
        f"`solvePnPRansac` with {s['iterations']} iterations then `solvePnPRefineLM` on its inliers. "
        "*Recall*: share of the honest (not replaced) points that RANSAC marks inlier. A seed *succeeds* "
        f"when its {s['success']}; a cell fails when fewer than half its seeds succeed.",
        "",
        "![ransac](ransac.png)",
        "",
        "Median translation error (mm; *fail*: more than half the solves failed):",
        "",
        *table(lambda c: "fail" if c["median_error_m"] is None else f"{c['median_error_m'] * 1e3:.3g}"),
        "",
        "Median inlier recall:",
        "",
        *table(lambda c: f"{c['median_recall']:.2f}"),
        "",
        "Seeds that succeed (%):",
        "",
        *table(lambda c: f"{c['success_pct']:.0f}"),
        "",
        "What this shows:",
        "",
    ]
    lines += _ransac_findings(result, cells)
    return "\n".join(lines) + "\n"


def _ransac_findings(result: dict[str, Any], cells: dict[tuple[float, float], dict[str, Any]]) -> list[str]:
    """The ransac Markdown's "What this shows" bullets."""
    s, summary = result["settings"], result["summary"]
    thresholds, contaminations = s["thresholds_px"], s["contaminations_pct"]
    default = summary["default_threshold_px"]
    d = summary["thresholds"][f"{default:g}"]
    lowest = summary["thresholds"][f"{thresholds[0]:g}"]
    clean = summary["clean_sample_probability"]
    failing = d["first_failing_contamination_pct"]
    lines: list[str] = []
    up_to = {t: summary["thresholds"][f"{t:g}"]["succeeds_up_to_pct"] for t in thresholds}
    wide = [t for t in thresholds if t >= default]
    lines.append(
        "- Thresholds >= "
        f"{default:g} px succeed up to "
        + ", ".join(f"{_num(up_to[t], 0)} % ({t:g} px)" for t in wide)
        + " contamination."
    )
    if failing is None:
        lines.append(
            f"- The default threshold ({default:g} px) does not fail within the contaminations measured "
            f"(up to {contaminations[-1]:g} %)."
        )
    else:
        lines.append(
            f"- The default threshold ({default:g} px) starts failing at {failing:g} % contamination "
            f"(success in {cells[default, failing]['success_pct']:.0f} % of seeds; it succeeds in at least 90 % of "
            f"seeds up to {_num(d['reliable_up_to_pct'], 0)} %). The cause is sampling, not the threshold: "
            f"OpenCV draws {RANSAC_SAMPLE}-point minimal samples, and {s['iterations']} of them contain at least one "
            "free of outliers with probability 1 - (1 - (1 - e)^5)^N = "
            + ", ".join(f"{clean[f'{c:g}']:.0%} at {c:g} %" for c in contaminations if c >= failing - 10.0)
            + "; every threshold fails together there."
        )
    lines.append(
        f"- A threshold far below the pixel noise fails even with no outliers: at {thresholds[0]:g} px "
        f"(noise {s['noise_px']:g} px per coordinate) RANSAC keeps a median "
        f"{lowest['recall_at_lowest_contamination']:.0%} "
        f"of the honest points at {contaminations[0]:g} % contamination. An honest point's distance from its true "
        f"projection is Rayleigh-distributed, so even the exact pose has only 1 - exp(-t^2 / 2 sigma^2) = "
        f"{lowest['recall_bound']:.0%} of them within {thresholds[0]:g} px; the consensus is then a random "
        "subset of the good data, and the winning model the one that happens to fit that subset. "
        "The sweet spot is a threshold of 3-4 sigma or more: "
        + ", ".join(f"{t:g} px keeps {summary['thresholds'][f'{t:g}']['recall_bound']:.2%}" for t in thresholds[:4])
        + " of honest points at best."
    )
    disc = math.pi * thresholds[-1] ** 2 / (s["image_size"][0] * s["image_size"][1])
    lines.append(
        f"- Large thresholds cost nothing here because the replaced pixels are uniform over the whole image (a "
        f"{thresholds[-1]:g} px disc covers {disc:.2%} of it); "
        "wrong matches that land near their true position (repeated texture) would be admitted by them."
    )
    return lines


def jitter_markdown(result: dict[str, Any]) -> str:
    """``jitter.md``: spread per distance, target and pipeline, and what it shows."""
    s, summary, rows = result["settings"], result["summary"], result["distances"]
    lines = [
        "# Jitter versus distance: a lone marker and a 2x2 board, raw and tracked",
        "",
        _produced(result),
        "",
        f"A static {s['marker_m'] * 100:g} cm marker and, beside it, a 2x2 grid board of the same markers "
        f"({s['board']}), seen {s['tilt_deg']:g} deg off their normal by a static {s['camera']} camera. Each "
        f"distance's view is rendered once (blur {s['blur_px']:g} px) and each of its {s['frames']} frames adds fresh "
        f"Gaussian sensor noise of {s['sensor_noise_grey']:g} grey levels per channel; the tracker ({s['config']}) "
        f"runs on those frames at {s['fps']:g} fps, and the first {s['settle_frames']} frames (the filter's "
        "settling time) are left out of the statistics. *raw*: the tracker's per-frame solution (lower-error "
        "IPPE solution for the marker, the joint solve for the board); *tracker*: its output. *orientation std*: "
        "RMS angle of the frames' rotations about their mean rotation; *flipped*: rotation error against the "
        f"ground truth above {s['flip_deg']:g} deg; *IPPE gap*: how much worse the second IPPE solution of the "
        "marker reprojects (median, px).",
        "",
        "![jitter](jitter.png)",
        "",
        "| distance | marker px | detected % marker / board | std ‖t‖ mm marker raw / trk | board raw / trk "
        "| orientation std deg marker raw / trk | board raw / trk | flipped % marker raw / trk | board raw / trk "
        "| IPPE gap px | noise-free margin px | marker tracked / ambiguous % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:

        def pair(target: str, metric: str, r: dict[str, Any] = r) -> str:
            return f"{_sig(r[f'{target}_raw'].get(metric))} / {_sig(r[f'{target}_tracker'].get(metric))}"

        states = r["marker_tracker_states_pct"]
        lines.append(
            f"| {r['distance_m']:g} m | {r['marker_px']:.0f} "
            f"| {r['marker_raw']['detected_pct']:.0f} / {r['board_raw']['detected_pct']:.0f} "
            f"| {pair('marker', 'distance_std_mm')} "
            f"| {pair('board', 'distance_std_mm')} | {pair('marker', 'rotation_std_deg')} "
            f"| {pair('board', 'rotation_std_deg')} | {pair('marker', 'flipped_pct')} "
            f"| {pair('board', 'flipped_pct')} | {_num(r['marker_gap_median_px'], 3)} "
            f"| {_num(r['marker_noise_free_margin_px'], 3)} | {states['tracked']:.0f} / {states['ambiguous']:.0f} |"
        )
    near, far = rows[0], rows[-1]
    onset, gap_onset = summary["onset_noise_m"], summary["onset_gap_m"]
    onset_text = f"at **{onset:g} m**" if onset is not None else "not reached within the distances measured"
    lines += [
        "",
        "What this shows:",
        "",
        f"- The raw marker's orientation std grows from {_num(near['marker_raw'].get('rotation_std_deg'), 4)} deg at "
        f"{near['distance_m']:g} m to {_num(far['marker_raw'].get('rotation_std_deg'), 3)} deg at "
        f"{far['distance_m']:g} m (it grows in {summary['raw_marker_growth_steps']} distance steps).",
        f"- Ambiguity onset (noise): the first distance at which the raw marker's orientation std exceeds "
        f"{ONSET_FACTOR:g}x the d^2 trend from the nearest distance. A well-conditioned planar pose's tilt noise "
        "grows like d^2 (the tilt is seen only through perspective foreshortening, which falls as (L/d)^2); faster "
        f"growth means the two IPPE solutions have merged into one shallow valley. Here it is {onset_text}. "
        + (
            f"The marker's IPPE gap falls below the filter's decision margin ({summary['decide_margin_px']:g} px) "
            f"from {gap_onset:g} m on: a single frame no longer tells the two solutions apart."
            if gap_onset is not None
            else f"The marker's IPPE gap stays above the filter's decision margin ({summary['decide_margin_px']:g} px)."
        ),
        "- Flipped frames: "
        + "; ".join(f"{STYLES[key][3]} {_flips(rows, *key)}" for key in STYLES)
        + ". Where the IPPE gap is below the margin the tracker holds one solution (state *ambiguous*) instead "
        "of alternating: steady, but not necessarily the right one. The raw rate need not grow monotonically "
        "with distance: the *noise-free margin* (how much better the right solution reprojects on the view "
        "without sensor noise, set by the small systematic corner error of renderer and detector) is what the "
        "noise has to overcome, and it varies from one distance to the next.",
        f"- At the far end the tracker's orientation std is {_num(summary['marker_raw_over_tracker_far'], 1)}x below "
        f"the raw marker's and {_num(summary['board_raw_over_tracker_far'], 1)}x below the raw board's.",
        "- Board below the lone marker at every distance? Orientation std: raw "
        f"{_yes(summary['board_not_below_marker_raw_rotation_std_deg'])}, tracker "
        f"{_yes(summary['board_not_below_marker_tracker_rotation_std_deg'])}; distance std: raw "
        f"{_yes(summary['board_not_below_marker_raw_distance_std_mm'])}, tracker "
        f"{_yes(summary['board_not_below_marker_tracker_distance_std_mm'])}.",
    ]
    return "\n".join(lines) + "\n"


def _yes(exceptions: Sequence[float]) -> str:
    """'yes', or 'no' with the distances where the board is not below the marker."""
    return "yes" if not exceptions else "**no** (not at " + ", ".join(f"{d:g}" for d in exceptions) + " m)"


def _flips(rows: Sequence[dict[str, Any]], target: str, pipeline: str) -> str:
    flipped = [(r["distance_m"], r[f"{target}_{pipeline}"].get("flipped_pct")) for r in rows]
    shown = [f"{pct:.1f} % at {d:g} m" for d, pct in flipped if pct]
    return ", ".join(shown) if shown else "none"


def _sig(value: float | None) -> str:
    """Three significant digits (the spreads span four decades)."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.3g}"


def _vector(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in values) + ")"


def seconds_text(value: float) -> str:
    """A duration for the terminal and the Markdown: ``12 s``, ``1.5 s``."""
    return f"{value:.0f} s" if value >= 10 else f"{value:.1f} s"


def _produced(result: dict[str, Any]) -> str:
    meta = result["meta"]
    return (
        f"Produced by `{meta['command']}` in {seconds_text(meta['wall_time_s'])} (OpenCV {meta['opencv']}, "
        f"{meta['machine']}, {meta['cpus']} CPUs)."
    )


def headline(result: dict[str, Any]) -> str:
    """One line of a study's result for the terminal."""
    summary = result["summary"]
    if result["study"] == "outliers":
        return (
            f"outliers: median translation error solvePnP {metres(summary['plain_error_m']['median'])}, "
            f"RANSAC + LM {metres(summary['ransac_error_m']['median'])}; all honest points kept in "
            f"{summary['all_honest_recovered_pct']:.0f} % of seeds"
        )
    if result["study"] == "ransac":
        default = summary["thresholds"][f"{summary['default_threshold_px']:g}"]
        failing = default["first_failing_contamination_pct"]
        return f"ransac: {summary['default_threshold_px']:g} px " + (
            "does not fail" if failing is None else f"starts failing at {failing:g} % contamination"
        )
    onset = summary["onset_noise_m"]
    return (
        "jitter: ambiguity onset "
        + ("not reached" if onset is None else f"at {onset:g} m")
        + f"; far end raw/tracker orientation std {_num(summary['marker_raw_over_tracker_far'], 1)}x (marker)"
    )
