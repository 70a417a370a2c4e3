"""``speed_stages.md`` and ``speed_stages.json`` (``ar-anchor bench speed --stages``): the in-process per-stage
run and its report, section by section."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from ...config import TrackerConfig
from ..report import fmt, fmt_sig, write_json
from .end_to_end import E2E_STAGES
from .measure import ONE_THREAD_PIPELINES, PIPELINE_LABELS, PIPELINES, ROI_FLOOR, primary_kind
from .scenes import EXTRA_CLIPS, NOISE_SHIFT, SCENES, SIZES
from .stages_run import run_stages_benchmark

__all__ = ["stages_markdown", "write_stages_report"]


def write_stages_report(
    out_dir: Path,
    quick: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    command: str = "ar-anchor bench speed --stages",
    *,
    config: TrackerConfig | None = None,
    frames: int | None = None,
    sizes: Sequence[tuple[int, int, float]] = SIZES,
    scenes: Sequence[str] = SCENES,
    extra: Sequence[str] = EXTRA_CLIPS,
    one_thread: bool | str | None = None,
    end_to_end: bool = True,
    realdata: Path | None = None,
) -> dict[str, Any]:
    """Run the benchmark, write ``speed_stages.md`` and ``speed_stages.json`` to ``out_dir``, return the results.

    ``quick``: 90 frames per clip instead of 300, the one-core pass at the largest size only. ``frames``,
    ``sizes``, ``scenes``, ``extra``, ``one_thread``, ``end_to_end``, ``realdata``: see
    :func:`~ar_anchor.bench.speed.stages_run.run_stages_benchmark`.
    """
    frames = frames or (90 if quick else 300)
    results = run_stages_benchmark(
        frames,
        sizes,
        scenes,
        extra=extra,
        realdata=realdata,
        config=config,
        one_thread=("largest" if quick else True) if one_thread is None else one_thread,
        end_to_end=end_to_end,
        memory_frames=min(frames, 10 if quick else 30),
        progress=progress,
    )
    results["meta"]["command"] = command
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "speed_stages.json", results)
    (out_dir / "speed_stages.md").write_text(stages_markdown(results, command))
    return results


def stages_markdown(results: Mapping[str, Any], command: str) -> str:
    """The report of :func:`~ar_anchor.bench.speed.stages_run.run_stages_benchmark`'s ``results``."""
    meta, clips, e2e = results["meta"], results["clips"], results["end_to_end"]
    lines = _headline(meta, clips, command)
    for note in results.get("notes", []):
        lines += ["", f"Note: {note}."]
    lines += _stages(clips) + _per_marker(clips) + _accuracy(clips)
    if any(c["one_thread"] for c in clips):
        lines += _one_core(meta, clips)
    if e2e:
        lines += _end_to_end(e2e)
    lines += _memory(results["memory"]) + _pipeline_memory(meta, clips) + _how_measured(meta, clips)
    return "\n".join(lines)


def _headline(meta: Mapping[str, Any], clips: Sequence[Mapping[str, Any]], command: str) -> list[str]:
    """Title, the headline table (default threads) and the board clip's note."""
    lines = [
        "# Speed: plain OpenCV loops vs. the tracker (full frame and ROI)",
        "",
        f"Produced by `{command}` in {meta['wall_time_s']:.0f} s; {meta['frames_per_clip']} frames per synthetic "
        "clip, the same frames for every pipeline.",
        *_table_section(
            "Headline (default OpenCV threads: " + str(meta["opencv_threads"]) + ")",
            "Per-frame cost, median: opencv = grey conversion + `detectMarkers` (default `DetectorParameters()`; "
            "*SUBPIX*: `cornerRefinementMethod = CORNER_REFINE_SUBPIX`) + `solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)` "
            "per marker; tracker = detect + pose + filter (`FrameResult.latency_ms`). *tracker / plain*: the "
            "tracker's median over the plain loop's, in this run on the same frames (above 1: the tracker is "
            "slower). *found / frame*: markers detected per frame, mean. Errors: median over every target in "
            "view and every frame, of each pipeline's output pose (the tracker's filtered pose, opencv's first "
            "IPPE solution); boards for the board clip, markers otherwise; empty for real video (no truth). "
            "*ROI within 10 %*: the ROI tracker's median rotation and translation errors are at most 110 % of "
            f"the full-frame tracker's, plus {ROI_FLOOR['rot_median_deg']:g} deg / "
            f"{ROI_FLOOR['trans_median_pct']:g} % (a few micrometres: these clean frames give both trackers errors "
            "so small that 10 % of them is below what they resolve; the JSON also has the plain 10 % test).",
            [
                "clip",
                "opencv",
                "opencv SUBPIX",
                "tracker full frame",
                "tracker ROI",
                "ROI / SUBPIX",
                "ROI / opencv",
                "full / SUBPIX",
                "full / opencv",
                "found / frame opencv / SUBPIX / full / ROI",
                "rot err med deg opencv / SUBPIX / full / ROI",
                "ROI errors within 10 % of full frame",
            ],
        ),
    ]
    for clip in clips:
        lines.append(_headline_row(clip))
    if any(c["scene"] == "board" for c in clips):
        lines += [
            "",
            "Board clip: opencv has no board pose, so its errors there are its per-marker errors (the board's "
            "four markers, each on its own); the trackers' are the board pose's.",
        ]
    return lines


def _headline_row(clip: Mapping[str, Any]) -> str:
    """One clip's row of the headline table."""
    p, r = clip["pipelines"], clip.get("ratios", {})
    kind = primary_kind(clip["scene"])

    def err(pipe: Mapping[str, Any], metric: str) -> Any:
        acc = pipe["accuracy"][kind] if pipe["accuracy"][kind].get("found") else pipe["accuracy"]["marker"]
        return acc.get(metric)

    rot = " / ".join(fmt_sig(err(p[key], "rot_median_deg")) for key in PIPELINES)
    found = " / ".join(fmt(p[key]["found_per_frame"]["mean"], 1) for key in PIPELINES)
    check = clip["roi_vs_full"]
    if not clip.get("has_truth", True):
        verdict = "- (no truth)"
    else:
        verdict = "yes" if check["within"] else "no"
        verdict += (
            f" (ROI vs full: rot {fmt_sig(check['rot_median_deg']['roi'])} vs "
            f"{fmt_sig(check['rot_median_deg']['full'])} deg, trans {fmt_sig(check['trans_median_pct']['roi'])} vs "
            f"{fmt_sig(check['trans_median_pct']['full'])} %"
            + ("" if check["within_strict"] == check["within"] else "; 10 % alone: no")
            + ")"
        )
    times = " | ".join(f"{fmt(p[key]['total_ms']['median'])} ms" for key in PIPELINES)
    ratios = " | ".join(
        f"{fmt(r.get(name))}x"
        for name in (
            "tracker_roi/opencv_subpix",
            "tracker_roi/opencv",
            "tracker_full/opencv_subpix",
            "tracker_full/opencv",
        )
    )
    return f"| {clip['label']} | {times} | {ratios} | {found} | {rot} | {verdict} |"


def _per_marker(clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each stage's cost per marker found, and the markers found per frame, for every pipeline and clip."""
    lines = _table_section(
        "Per marker (default threads)",
        "ms per marker: the median over frames with at least one marker detected of (the stage's ms in that "
        "frame / the markers that pipeline detected in it). Detection has a fixed per-frame part, so its "
        "ms / marker falls as markers are added; pose and filter are the per-marker work. *found / frame*: "
        "markers detected per frame, mean (min-max); the tracker's are its detections (ROI: in its regions).",
        ["clip", "pipeline", "found / frame", "detect ms / marker", "pose ms / marker", "filter ms / marker",
         "total ms / marker"],
    )  # fmt: skip
    for clip, pipe in _clip_pipelines(clips):
        per, found = pipe.get("per_marker_ms", {}), pipe.get("found_per_frame", {})
        cells = " | ".join(fmt(per.get(stage), 3) for stage in ("detect_ms", "pose_ms", "filter_ms", "total_ms"))
        lines.append(
            f"| {clip['label']} | {pipe['label']} | {fmt(found.get('mean'), 1)} ({fmt(found.get('min'), 0)}-"
            f"{fmt(found.get('max'), 0)}) | {cells} |"
        )
    return lines


def _stages(clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """Per-stage times of every pipeline on every clip (default threads)."""
    lines = _table_section(
        "Stages (default threads)",
        "ms per frame, median / p95 / mean. *fps*: 1000 / mean of the total (that part of the pipeline alone).",
        ["clip", "pipeline", "detect", "pose", "filter", "total median / p95", "fps"],
    )
    for clip, pipe in _clip_pipelines(clips):

        def trip(stage: str, pipe: Mapping[str, Any] = pipe) -> str:
            s = pipe["stages"].get(stage)
            return " / ".join(fmt(s[k]) for k in ("median", "p95", "mean")) if s else "-"

        total = pipe["total_ms"]
        lines.append(
            f"| {clip['label']} | {pipe['label']} | {trip('detect_ms')} | {trip('pose_ms')} | {trip('filter_ms')} "
            f"| {fmt(total['median'])} / {fmt(total['p95'])} | {fmt(pipe['fps'], 0)} |"
        )
    return lines


def _accuracy(clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """Errors against ground truth of every pipeline on every clip."""
    lines = _table_section(
        "Accuracy against ground truth",
        "Over all frames (from frame 0: the tracker's filter start included) and every target in view. *found*: "
        "share of (frame, target in view) pairs with an output pose (the tracker also outputs predicted poses "
        "through short gaps). Markers: each marker's own pose (board members too); board: the board's pose.",
        [
            "clip",
            "pipeline",
            "markers found %",
            "marker rot med / p95 deg",
            "marker trans med / p95 %",
            "board found %",
            "board rot med / p95 deg",
            "board trans med / p95 %",
        ],
    )
    for clip, pipe in _clip_pipelines(clips):
        m, b = pipe["accuracy"]["marker"], pipe["accuracy"]["board"]

        def pair(acc: Mapping[str, Any], a: str, b: str) -> str:
            return f"{fmt_sig(acc.get(a))} / {fmt_sig(acc.get(b))}" if acc.get("found") else "-"

        lines.append(
            f"| {clip['label']} | {pipe['label']} | {fmt(m.get('found_pct'), 1)} "
            f"| {pair(m, 'rot_median_deg', 'rot_p95_deg')} | {pair(m, 'trans_median_pct', 'trans_p95_pct')} "
            f"| {fmt(b.get('found_pct'), 1) if b.get('in_view') else '-'} "
            f"| {pair(b, 'rot_median_deg', 'rot_p95_deg')} | {pair(b, 'trans_median_pct', 'trans_p95_pct')} |"
        )
    return lines


def _one_core(meta: Mapping[str, Any], clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """The one-core pass (``cv2.setNumThreads(1)``) against the default threads."""
    labels = [PIPELINE_LABELS[key] for key in ONE_THREAD_PIPELINES]
    lines = _table_section(
        "One core: `cv2.setNumThreads(1)`",
        f"The plain loop and the default tracker (ROI) again, on the same frames, with OpenCV limited to one "
        f"thread (restored to {meta['opencv_threads']} afterwards). Total ms per frame, median / p95; fps = "
        "1000 / mean; *slow-down*: one-thread median / default-threads median."
        + ("" if all(c["one_thread"] for c in clips) else " Run at the largest size only."),
        [
            "clip",
            *labels,
            "speed-up opencv / ROI",
            "fps " + " / ".join(labels),
            "slow-down vs default threads " + " / ".join(labels),
        ],
    )
    for clip in clips:
        single = clip["one_thread"]
        if not single:
            continue
        keys = [key for key in ONE_THREAD_PIPELINES if key in single]
        totals = " | ".join(
            f"{fmt(single[key]['total_ms']['median'])} / {fmt(single[key]['total_ms']['p95'])} ms" for key in keys
        )
        fps = " / ".join(fmt(single[key]["fps"], 0) for key in keys)
        slow = " / ".join(
            fmt(single[key]["total_ms"]["median"] / clip["pipelines"][key]["total_ms"]["median"])
            if clip["pipelines"][key]["total_ms"]["median"] > 0
            else "-"
            for key in keys
        )
        lines.append(
            f"| {clip['label']} | {totals} | {fmt(clip.get('ratio_opencv_over_roi_one_thread'))}x | {fps} | {slow}x |"
        )
    return lines


def _end_to_end(e2e: Mapping[str, Any]) -> list[str]:
    """Decode -> track -> overlay -> log, stage by stage."""
    lines = _table_section(
        f"End to end: {e2e['size']} one marker, tracker (ROI), default threads",
        f"Each frame goes through decode -> track -> overlay -> log, one stage after the other. *decode*: "
        f"`VideoFileSource` reading the clip encoded once to H.264 ({fmt(e2e['video_mb'], 1)} MB); *track*: "
        f"`Tracker.process`; *render*: `OverlayRenderer.annotate` (cube on `marker:*`); *log*: "
        f"`RerunRecorder.log_frame` (JPEG image and overlay, detections, 3D scene, metrics; default "
        f"recording settings) to a temporary .rrd ({fmt(e2e['rrd_mb'], 1)} MB). The first "
        f"{e2e['frames_excluded']} of {e2e['frames']} frames are left out (first-frame costs).",
        ["stage", "median ms", "p95 ms", "mean ms"],
    )
    names = {"decode_ms": "decode", "track_ms": "track", "render_ms": "render (overlay)", "log_ms": "log (rerun)"}
    for stage in E2E_STAGES:
        s = e2e["stages"][stage]
        lines.append(f"| {names[stage]} | {fmt(s['median'])} | {fmt(s['p95'])} | {fmt(s['mean'])} |")
    t = e2e["total_ms"]
    lines += [
        f"| **sum per frame** | **{fmt(t['median'])}** | **{fmt(t['p95'])}** | **{fmt(t['mean'])}** |",
        "",
        f"Sequential end-to-end throughput: **{fmt(e2e['fps'], 1)} fps** (1000 / mean sum). Of *track*, "
        f"detect + pose + filter took {fmt(e2e['tracker_detect_pose_filter_ms']['median'])} ms (median). "
        f"Closing the recording (flush) took {fmt(e2e['recorder_close_ms'], 0)} ms once at the end. rerun "
        "encodes and writes in its own threads, so *log* is the caller's share only. Accuracy on the decoded "
        f"frames: rot {fmt_sig(e2e['accuracy']['marker'].get('rot_median_deg'))} deg, trans "
        f"{fmt_sig(e2e['accuracy']['marker'].get('trans_median_pct'))} % (median).",
    ]
    return lines


def _table_section(title: str, text: str, columns: Sequence[str]) -> list[str]:
    """A section's first lines: its title, what it shows and the head of its table."""
    return ["", f"## {title}", "", text, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]


def _clip_pipelines(clips: Sequence[Mapping[str, Any]]) -> Iterator[tuple[Mapping[str, Any], Mapping[str, Any]]]:
    """(clip, one pipeline's results on it) for every pipeline (default threads) on every clip."""
    for clip in clips:
        for key in PIPELINES:
            yield clip, clip["pipelines"][key]


def _memory(memory: Mapping[str, Any]) -> list[str]:
    """Peak RSS at the start, with the frames in memory and during the end-to-end run; tracemalloc peaks."""
    lines = ["", "## Memory", ""]
    lines.append(f"- peak RSS at the start of the run: {fmt(memory['rss_peak_at_start_mb'], 0)} MB")
    lines.append(
        f"- peak RSS while rendering and timing (one clip's frames held in memory, up to "
        f"{fmt(memory.get('largest_frame_store_mb'), 0)} MB): {fmt(memory.get('rss_peak_with_frames_mb'), 0)} MB"
    )
    if "rss_peak_end_to_end_mb" in memory:
        since = (
            "peak since it was reset before the end-to-end run"
            if memory.get("peak_reset")
            else "peak since the process started (could not reset it)"
        )
        lines.append(
            f"- peak RSS of the end-to-end run (frames streamed, not held; {since}): "
            f"{fmt(memory['rss_peak_end_to_end_mb'], 0)} MB (RSS when it started, the clips' frames freed: "
            f"{fmt(memory.get('rss_before_end_to_end_mb'), 0)} MB)"
        )
    return lines


def _pipeline_memory(meta: Mapping[str, Any], clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each pipeline's tracemalloc peak on every clip."""
    if not any(c.get("peak_mb") for c in clips):
        return []
    lines = _table_section(
        "Peak memory per pipeline",
        "`tracemalloc` peak, MB: the Python-side allocations (NumPy arrays included; OpenCV's own C++ buffers "
        f"not) of a fresh instance of each pipeline over the first {meta.get('memory_frames', '-')} frames of "
        "each clip, run one pipeline at a time after the timing (the frames, allocated before, do not count). "
        "An RSS delta cannot be split between pipelines that take turns in one process; the RSS figures above "
        "are the whole run's.",
        ["clip", *(PIPELINE_LABELS[key] for key in PIPELINES)],
    )
    for clip in clips:
        peaks = clip.get("peak_mb") or {}
        if peaks:
            lines.append(f"| {clip['label']} | " + " | ".join(fmt(peaks.get(key), 2) for key in PIPELINES) + " |")
    return lines


def _how_measured(meta: Mapping[str, Any], clips: Sequence[Mapping[str, Any]]) -> list[str]:
    """The machine, the clips and the pipelines."""
    load = meta.get("load_average_start")
    load_end = meta.get("load_average_end")
    lines = [
        "",
        "## How measured",
        "",
        f"Machine: {meta['processor']} ({meta['machine']}, {meta['system']}), `os.cpu_count()` {meta['cpu_count']} "
        f"({meta['usable_cpus']} usable), Python {meta['python']}, NumPy {meta['numpy']}, OpenCV {meta['opencv']}, "
        f"`cv2.getNumThreads()` {meta['opencv_threads']}. Load average at start "
        f"{' / '.join(fmt(x) for x in load) if load else '-'}, at the end "
        f"{' / '.join(fmt(x) for x in load_end) if load_end else '-'} (other work on the machine slows every "
        "pipeline alike: they take turns frame by frame).",
        "",
        f"Clips: synthetic ({meta['frames_per_clip']} frames at 30 fps, rendered before any timing, kept in memory), "
        "DICT_4X4_50 markers on a cluttered wall, sensor noise "
        f"{fmt(meta['noise'], 0)} grey levels (one Gaussian field per clip, shifted at random by up to "
        f"{NOISE_SHIFT} px each frame), blur {fmt(meta['blur_px'], 1)} px. One marker, eight markers, 2x2 board: "
        "5 cm markers, the camera orbits them (azimuth +-35 deg, elevation +-15 deg, roll +-10 deg, up to 45 "
        "deg/s) at a constant distance; the board's markers are 1 cm apart. 50 markers (720p only): 3 cm "
        "markers, ids 0-49, on two 5x5 panels 1.5 cm apart hinged like an open book (each turned 20 deg toward "
        "the viewer), a hand-held camera (sway, aim wander, tremor; no quick turns) at 0.6-0.75 m, all 50 in "
        "view in every frame. "
        + "; ".join(
            f"{c['label']}: {fmt(c['distance_m'], 2)}"
            + (f"-{fmt(c['far_m'], 2)}" if c.get("far_m", c["distance_m"]) != c["distance_m"] else "")
            + f" m ({fmt(c['marker_px'], 0)} px markers at the nearest)"
            for c in clips
            if c.get("source", "synthetic") == "synthetic"
        )
        + ". 720p: fx 1000 px; 1080p: fx 1480 px; no lens distortion. Real: "
        + (
            "; ".join(
                f"{c['label']} ({c['frames']} frames, decoded into memory before timing, its calibration "
                f"intrinsics.yml, {c.get('dictionary')}, {fmt(c.get('marker_m'), 3)} m markers, every id, no "
                "boards; no truth)"
                for c in clips
                if c.get("source") == "real"
            )
            or "none in this run"
        )
        + ".",
        "",
        "Pipelines: *opencv* is `ArucoDetector(dictionary, DetectorParameters())` on the grey image (conversion "
        "counted in detect) and `solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)` per detected marker (pose; its first, "
        "lower-reprojection-error solution); no filter. *opencv SUBPIX*: the same with "
        "`cornerRefinementMethod = CORNER_REFINE_SUBPIX`. The *tracker* runs its configured pipeline "
        "(edge-fitted corners, both IPPE solutions, boards, flip-resolving filter) with ROI tracking off (*full "
        "frame*) or on (*ROI*, the default); its stage times are its own `latency_ms`. The four pipelines take "
        "turns on each frame (the one going first rotates), each on its own state; each first warms up on a "
        f"throw-away instance over {meta['warmup_frames']} frames. Time: `time.perf_counter`. The *default "
        f"threads* numbers run with OpenCV's own thread pool ({meta['opencv_threads']} threads); the *one core* "
        "numbers repeat the opencv and tracker (ROI) loops after `cv2.setNumThreads(1)` (only OpenCV's threads "
        "are limited, not NumPy's BLAS). Nothing else in the process runs during timing; the machine itself "
        "may be shared (load above).",
        "",
    ]
    return lines
