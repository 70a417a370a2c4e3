"""Per-target metrics of one pipeline's poses against truth (and against the raw measurement).

Pure functions of per-frame pose lists (None where there is no pose); see :mod:`ar_anchor.bench.stability`
for what each metric means. ``FLIP_DEG`` and ``SETTLE_FRAMES`` are :mod:`ar_anchor.bench.report`'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ...geometry import Pose, angle_between_deg, mean_rotation, pose_errors
from ..report import FLIP_DEG, SETTLE_FRAMES

__all__ = [
    "DECISIVE_MARGIN_PX",
    "DECISIVE_RATIO",
    "LAG_TOLERANCE",
    "MAX_LAG_FRAMES",
    "ambiguous_vs_raw",
    "count_twitches",
    "fractional_lag",
    "is_decisive",
    "lag_frames",
    "longest_stretch",
    "misfit_rows",
    "predicted_error_stats",
    "rotation_errors",
    "series_metrics",
    "wrong_tracked",
]

# A raw measurement is *decisive* when its pick is the only valid IPPE solution, or when the other
# solution reprojects at least DECISIVE_RATIO times worse AND at least DECISIVE_MARGIN_PX px worse
# (the ratio alone would call sub-0.1 px differences on sharp near markers decisive; the margin alone
# would call 3 px vs 3.3 px decisive on a blurred one). Used by the longest-stretch metric.
DECISIVE_RATIO = 3.0
DECISIVE_MARGIN_PX = 0.3


def is_decisive(hypotheses: Sequence[Any]) -> bool:
    """Is a raw measurement with these IPPE solutions (lower error first, each with ``reproj_px``)
    decisive: one valid solution, or the other reprojects >= ``DECISIVE_RATIO`` x and >=
    ``DECISIVE_MARGIN_PX`` px worse?"""
    if len(hypotheses) == 1:
        return True
    if len(hypotheses) != 2:
        return False
    best, other = float(hypotheses[0].reproj_px), float(hypotheses[1].reproj_px)
    if not (math.isfinite(best) and math.isfinite(other)):
        return False
    return other >= DECISIVE_RATIO * best and other - best >= DECISIVE_MARGIN_PX


def rotation_errors(poses: Sequence[Pose | None], truth: Sequence[Pose | None]) -> np.ndarray:
    """Per-frame rotation error (deg) against truth; NaN where either is missing."""
    return np.array(
        [
            angle_between_deg(p.rotation, t.rotation) if p is not None and t is not None else math.nan
            for p, t in zip(poses, truth)
        ],
        dtype=float,
    )


def longest_stretch(
    output: Sequence[Pose | None], raw: Sequence[Pose | None], decisive: Sequence[bool], *, gaps_end: bool = True
) -> int:
    """Longest run of consecutive frames whose output is more than ``FLIP_DEG`` from a decisive raw
    measurement. ``gaps_end=False``: frames without a decisive measurement (or without an output)
    neither extend nor end the run (the gap-tolerant ``ignored_run``)."""
    best = run = 0
    for out, measured, is_decisive_ in zip(output, raw, decisive):
        if out is None or measured is None or not is_decisive_:
            if gaps_end:
                run = 0
            continue
        if angle_between_deg(out.rotation, measured.rotation) > FLIP_DEG:
            run += 1
            best = max(best, run)
        else:
            run = 0
    return best


def wrong_tracked(output: Sequence[Pose | None], truth: Sequence[Pose | None], state: Sequence[str]) -> dict[str, Any]:
    """Frames the tracker calls ``tracked`` that are more than ``FLIP_DEG`` off the truth: count and %
    of the tracked frames with truth."""
    errors = rotation_errors(output, truth)
    tracked = np.array([s == "tracked" for s in state]) & np.isfinite(errors)
    count = int(np.sum(errors[tracked] > FLIP_DEG))
    total = int(tracked.sum())
    return {"wrong_tracked": count, "wrong_tracked_pct": 100.0 * count / total if total else 0.0}


def predicted_error_stats(
    output: Sequence[Pose | None], truth: Sequence[Pose | None], state: Sequence[str]
) -> dict[str, Any]:
    """Rotation error of the ``predicted`` rows against truth: count, median and p95 (None without any)."""
    errors = rotation_errors(output, truth)
    predicted = errors[np.array([s == "predicted" for s in state], dtype=bool) & np.isfinite(errors)]
    if predicted.size == 0:
        return {"predicted_frames": 0, "predicted_median_deg": None, "predicted_p95_deg": None}
    return {
        "predicted_frames": int(predicted.size),
        "predicted_median_deg": float(np.median(predicted)),
        "predicted_p95_deg": float(np.percentile(predicted, 95)),
    }


MEASURED_STATES = ("tracked", "ambiguous")


def misfit_rows(state: Sequence[str], reproj_px: Sequence[float], bound_px: Sequence[float]) -> dict[str, Any]:
    """Issue 32: measured rows (``tracked`` or ``ambiguous`` with this frame's solutions; ``bound_px``
    finite) whose output does not fit its own frame: its RMS reprojection error on the frame's corners
    (``reproj_px``, ``TargetResult.reproj_px``) is above the bound (``bound_px``:
    :func:`ar_anchor.track.fit.fit_bound_px` of the frame's best solution's error and ``[pose]
    fit_margin_px``), or is not a number. ``misfit_rows``: how many; ``fit_rows``: the measured rows;
    ``misfit_worst_px``: the largest excess over the bound (None without a misfit, or when it is not
    finite)."""
    rows = misfits = 0
    worst: float | None = None
    for st, error, bound in zip(state, reproj_px, bound_px):
        if st not in MEASURED_STATES or not math.isfinite(bound):
            continue
        rows += 1
        if error <= bound:  # False for NaN: an output whose error is unknown does not fit
            continue
        misfits += 1
        excess = float(error - bound)
        if math.isfinite(excess) and (worst is None or excess > worst):
            worst = excess
    return {"fit_rows": rows, "misfit_rows": misfits, "misfit_worst_px": worst}


def ambiguous_vs_raw(
    output: Sequence[Pose | None], raw: Sequence[Pose | None], truth: Sequence[Pose | None], state: Sequence[str]
) -> dict[str, Any]:
    """On the ``ambiguous`` rows that have a raw measurement: how many frames the output and the raw
    per-frame pick are each more than 10 deg off (the output must be at least as good)."""
    out = raw_wrong = rows = 0
    for pose, measured, true, st in zip(output, raw, truth, state):
        if st != "ambiguous" or pose is None or measured is None or true is None:
            continue
        rows += 1
        out += angle_between_deg(pose.rotation, true.rotation) > FLIP_DEG
        raw_wrong += angle_between_deg(measured.rotation, true.rotation) > FLIP_DEG
    return {"ambiguous_rows": rows, "ambiguous_wrong": out, "ambiguous_raw_wrong": raw_wrong}


def count_twitches(poses: Sequence[Pose | None]) -> int:
    """Consecutive poses more than ``FLIP_DEG`` apart in rotation with less than 1 cm of motion."""
    return sum(
        1
        for a, b in zip(poses, poses[1:])
        if a is not None
        and b is not None
        and angle_between_deg(a.rotation, b.rotation) > FLIP_DEG
        and np.linalg.norm(a.tvec - b.tvec) < 0.01
    )


LAG_TOLERANCE = 0.05  # a shift must lower the median error by more than this fraction to count as lag
MAX_LAG_FRAMES = 6  # the largest shift searched


def lag_frames(poses: Sequence[Pose | None], truth: Sequence[Pose | None], *, signed: bool = False) -> int:
    """The shift (frames) that best aligns ``poses`` with ``truth``: ``poses[i]`` against ``truth[i - shift]``.

    Positive: the output lags (it shows at frame ``i`` what was true ``shift`` frames earlier); negative
    (``signed`` only): it leads (it shows what will be true ``-shift`` frames later). Shifts 0..
    ``MAX_LAG_FRAMES`` (``signed``: -``MAX_LAG_FRAMES``..+``MAX_LAG_FRAMES``; an offline output, which sees
    the future, may lead). The smallest ``|shift|`` whose median rotation error is within
    ``LAG_TOLERANCE`` of the best shift's (the lower error first on a tie of ``|shift|``): where the curve
    is flat (an undecidable target's error is its ambiguity, not lag) noise would pick any shift; raw,
    which cannot lag, showed 5."""
    shifts = range(-MAX_LAG_FRAMES if signed else 0, MAX_LAG_FRAMES + 1)
    medians = {}
    for shift in shifts:
        errors = [
            angle_between_deg(poses[i].rotation, truth[i - shift].rotation)  # type: ignore[union-attr]
            for i in range(max(shift, 0), min(len(poses), len(truth) + shift))
            if poses[i] is not None and truth[i - shift] is not None
        ]
        medians[shift] = float(np.median(errors)) if errors else math.inf
    best = min(medians.values())
    within = [s for s in shifts if medians[s] <= best * (1.0 + LAG_TOLERANCE)]
    return min(within, key=lambda s: (abs(s), medians[s]))


def fractional_lag(poses: Sequence[Pose | None], truth: Sequence[Pose | None]) -> float | None:
    """The shift (frames, fractional) at which ``poses`` best match ``truth``: the minimum of a parabola
    through the median rotation error at the best whole shift (-``MAX_LAG_FRAMES``..+``MAX_LAG_FRAMES``)
    and its two neighbours (the best whole shift itself at the range's ends). Signs as
    :func:`lag_frames`. None when there is nothing to compare."""
    medians = []
    for shift in range(-MAX_LAG_FRAMES, MAX_LAG_FRAMES + 1):
        errors = [
            angle_between_deg(poses[i].rotation, truth[i - shift].rotation)  # type: ignore[union-attr]
            for i in range(max(shift, 0), min(len(poses), len(truth) + shift))
            if poses[i] is not None and truth[i - shift] is not None
        ]
        medians.append(float(np.median(errors)) if errors else math.inf)
    if not np.isfinite(medians).any():
        return None
    k = int(np.argmin(medians))
    if k == 0 or k == len(medians) - 1 or not np.isfinite([medians[k - 1], medians[k + 1]]).all():
        return float(k - MAX_LAG_FRAMES)
    before, at, after = medians[k - 1], medians[k], medians[k + 1]
    curvature = before - 2.0 * at + after
    offset = 0.5 * (before - after) / curvature if curvature > 0 else 0.0
    return float(k - MAX_LAG_FRAMES + offset)


def series_metrics(
    poses: list[Pose | None], truth: list[Pose | None], moving: bool, *, signed_lag: bool = False
) -> dict[str, Any]:
    """One pipeline's poses of one target against truth: frames, wrong frames, rotation and translation
    error statistics, twitches; jitter after ``SETTLE_FRAMES`` (static) or lag in frames (``moving``:
    :func:`lag_frames`, ``signed_lag`` lets it be negative: an output that leads)."""
    pairs = [(p, t) for p, t in zip(poses, truth) if p is not None and t is not None]
    if not pairs:
        return {"frames": 0, "wrong_frames": 0, "twitches": count_twitches(poses)}
    rot, trans = np.array([pose_errors(p, t) for p, t in pairs]).T
    out: dict[str, Any] = {
        "frames": len(pairs),
        "wrong_frames": int(np.sum(rot > FLIP_DEG)),
        "flipped_pct": 100.0 * float(np.mean(rot > FLIP_DEG)),
        "rot_median_deg": float(np.median(rot)),
        "rot_p95_deg": float(np.percentile(rot, 95)),
        "trans_median_pct": float(np.median(trans)),
    }
    out["twitches"] = count_twitches(poses)
    settled = [p for p in poses[SETTLE_FRAMES:] if p is not None]
    if not moving and len(settled) > 1:
        mean = mean_rotation([p.rotation for p in settled])
        out["jitter_deg"] = float(np.sqrt(np.mean([angle_between_deg(p.rotation, mean) ** 2 for p in settled])))
    if moving:
        out["lag_frames"] = lag_frames(poses, truth, signed=signed_lag)
    return out
