"""From observations to a map: initialisation (:mod:`.initialise`), bundle adjustment (:mod:`.adjust`), outliers
dropped and the map adjusted again, uncertainty.

Outliers
    Observations still off by more than ``max(OUTLIER_PX, 5 x median)`` after a solve (a misread id, a smeared
    corner) are dropped and the map solved again; a marker left with fewer than ``MIN_FRAMES`` observations
    is unplaced.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ...camera import CameraModel
from ...errors import InputError
from ...geometry import Pose
from .adjust import bundle_adjust, marker_sigmas
from .initialise import MIN_FRAMES, initialise
from .model import FrameObservations, MarkerMap
from .problem import Problem, Progress

__all__ = ["OUTLIER_PX", "MapSolution", "build_map"]

OUTLIER_PX = 3.0  # an observation whose RMS corner error stays above max(this, 5 x median) is dropped


@dataclass
class MapSolution:
    """A solved map with what the report shows about it."""

    map: MarkerMap
    camera_from_world: dict[str, Pose]  # frame name -> pose, the frames the final adjustment used
    frame_order: list[str]
    observations_per_marker: dict[int, int]
    observation_errors: list[tuple[str, int, float]]  # (frame name, marker id, RMS corner error px)
    corner_errors_px: np.ndarray  # every used corner's reprojection distance
    dropped: list[tuple[str, int, float]]  # outlier observations: (frame name, marker id, RMS px at the drop)
    unplaced: dict[int, str]
    first_rms_px: float
    evaluations: int
    seconds: float
    frames_in: int

    @property
    def rms_px(self) -> float:
        """RMS of the used corners' reprojection distances."""
        errors = self.corner_errors_px
        return math.sqrt(float(np.mean(errors**2))) if errors.size else math.nan


def _rms(errors: np.ndarray) -> float:
    return math.sqrt(float(np.mean(errors**2))) if errors.size else math.nan


def build_map(
    frames: list[FrameObservations],
    cameras: list[CameraModel],
    length_m: float,
    *,
    origin: int | None = None,
    progress: Progress | None = None,
) -> MapSolution:
    """Initialise, adjust, drop outliers and adjust again, then the uncertainties (module doc).

    Raises :class:`~ar_anchor.errors.InputError` when fewer than two markers are ever seen together.
    """
    started = time.monotonic()
    together = {int(i) for frame in frames for i in frame.ids.tolist()}
    if len(together) < 2 or not frames:
        raise InputError(
            "fewer than two markers were ever seen together in one frame: a map needs frames showing two "
            "markers or more (check the video covers the markers, and --dictionary / --marker-length)"
        )
    problem = Problem(frames, cameras, length_m)
    initial = initialise(problem, origin, progress)
    if len(initial.world_from_marker) < 2:
        reasons = "; ".join(f"{m}: {why}" for m, why in sorted(initial.unplaced.items())[:6])
        raise InputError(
            f"could place no marker beside the reference marker {initial.reference_id} ({reasons}); "
            "film the markers together from several viewpoints"
        )
    if progress is not None:
        progress(
            f"bundle adjustment: {len(initial.world_from_marker)} markers, {len(initial.camera_from_world)} frames"
        )
    adjusted = bundle_adjust(problem, initial.world_from_marker, initial.camera_from_world, initial.reference_id)
    first_rms = _rms(adjusted.corner_errors_px)
    evaluations = adjusted.evaluations
    unplaced = dict(initial.unplaced)
    dropped: list[tuple[str, int, float]] = []
    for _ in range(3):
        errors = adjusted.errors_px
        limit = max(OUTLIER_PX, 5.0 * float(np.median(errors))) if errors.size else OUTLIER_PX
        bad = errors > limit
        if not bad.any():
            break
        for (f, k), error in zip(np.array(adjusted.observations)[bad].tolist(), errors[bad].tolist()):
            dropped.append((frames[f].name, int(frames[f].ids[k]), float(error)))
        kept = [o for o, is_bad in zip(adjusted.observations, bad) if not is_bad]
        markers = dict(adjusted.world_from_marker)
        per_marker = Counter(int(frames[f].ids[k]) for f, k in kept)
        for marker_id in list(markers):
            if marker_id != initial.reference_id and per_marker[marker_id] < MIN_FRAMES:
                del markers[marker_id]
                unplaced[marker_id] = f"only {per_marker[marker_id]} observation(s) left after dropping outliers"
        kept = [(f, k) for f, k in kept if int(frames[f].ids[k]) in markers]
        if progress is not None:
            progress(f"dropped {int(bad.sum())} outlier observation(s) (> {limit:.2f} px); adjusting again")
        adjusted = bundle_adjust(problem, markers, adjusted.camera_from_world, initial.reference_id, observations=kept)
        evaluations += adjusted.evaluations
    if len(adjusted.world_from_marker) < 2:
        raise InputError("after dropping outlier observations fewer than two markers are left in the map")
    sigmas = marker_sigmas(adjusted)
    sigmas[initial.reference_id] = 0.0
    marker_map = MarkerMap(length_m, initial.reference_id, dict(sorted(adjusted.world_from_marker.items())), sigmas)
    names = {f: frames[f].name for f in adjusted.frames}
    observation_errors = [
        (frames[f].name, int(frames[f].ids[k]), float(e))
        for (f, k), e in zip(adjusted.observations, adjusted.errors_px)
    ]
    return MapSolution(
        map=marker_map,
        camera_from_world={names[f]: adjusted.camera_from_world[f] for f in adjusted.frames},
        frame_order=[names[f] for f in adjusted.frames],
        observations_per_marker=dict(sorted(Counter(m for _, m, _ in observation_errors).items())),
        observation_errors=observation_errors,
        corner_errors_px=adjusted.corner_errors_px.ravel(),
        dropped=dropped,
        unplaced={m: why for m, why in sorted(unplaced.items()) if m not in adjusted.world_from_marker},
        first_rms_px=first_rms,
        evaluations=evaluations,
        seconds=time.monotonic() - started,
        frames_in=len(frames),
    )
