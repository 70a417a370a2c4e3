"""How the camera moves over a synthetic clip: calm sweeps, orbits, a hand-held webcam, a folder of
unrelated stills, and a video with a cut.

The calm kinds (``sweep``, ``orbit``, ``static``, ``approach``), ``stills`` and ``cut`` are functions of
normalised time ``u`` in [0, 1]; ``handheld`` is a function of time in seconds, so a different ``fps``
samples the same motion.

``stills`` (issue 32) is one explicit view per frame (:func:`still_view`; :func:`turntable_stills` is the
benchmark's seeded set: a lone marker turned -70..+70 deg about a vertical axis at several distances and
image positions, shuffled), so consecutive frames are unrelated photos. ``cut`` plays one path up to a
cut and another after it (``parts`` and ``cuts_u``): the camera jumps at the cut.

Hand-held motion (``Trajectory(kind="handheld")``) is built from seeded sums of sinusoids and smooth
bursts: sway of the viewpoint at 0.1-0.5 Hz around the targets (azimuth, elevation, roll, and a
wandering aim point), approach and retreat between ``near_m`` and ``far_m`` (0.05-0.2 Hz), tremor at
5-10 Hz (a small rotation about the camera's own centre) and quick turns: raised-cosine bursts of
rotation about the camera centre (out and back, ``turn_every_s`` apart on average) whose angular
speed peaks at exactly ``turn_peak_deg_s``. Everything is deterministic for the trajectory's seed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..geometry import Pose, look_at

__all__ = ["StillView", "Trajectory", "still_view", "turntable_stills"]

KINDS = ("sweep", "orbit", "static", "handheld", "approach", "stills", "cut")

# One still (kind="stills"): turn, tilt, roll (deg), distance (m), right, down (deg): the camera views the
# target from ``turn_deg`` azimuth and ``tilt_deg`` elevation (the target turned about a vertical and a
# horizontal axis), rolled by ``roll_deg``, at ``distance_m``, the target's centre ``right_deg`` right of
# and ``down_deg`` below the optical axis.
StillView = tuple[float, float, float, float, float, float]


def still_view(
    turn_deg: float,
    distance_m: float,
    *,
    tilt_deg: float = 0.0,
    roll_deg: float = 0.0,
    right_deg: float = 0.0,
    down_deg: float = 0.0,
) -> StillView:
    """One still of a ``kind="stills"`` trajectory (see ``StillView``)."""
    if not distance_m > 0:
        raise ValueError(f"still_view: distance_m must be > 0, got {distance_m}")
    return (float(turn_deg), float(tilt_deg), float(roll_deg), float(distance_m), float(right_deg), float(down_deg))


def turntable_stills(
    seed: int,
    *,
    turns_deg: tuple[float, ...] = tuple(range(-70, 71, 10)),
    near_m: float = 0.3,
    far_m: float = 1.5,
    first_m: float = 0.5,
    sets: int = 3,
    max_tilt_deg: float = 15.0,
    max_roll_deg: float = 20.0,
    max_right_deg: float = 12.0,
    max_down_deg: float = 6.0,
) -> tuple[StillView, ...]:
    """Seeded unrelated photos of one target, one per frame: ``sets`` times every turn of ``turns_deg``
    (about a vertical axis); the first set centred, untilted, at ``first_m``; the others each at a
    seeded distance (log-uniform in ``near_m``..``far_m``), tilt, roll and image position (up to
    ``max_right_deg`` / ``max_down_deg`` off the optical axis); all shuffled (seeded). The first set's
    photos share one camera position, so no two of them are in a row (two would be a turn of the target
    without any motion, what the benchmark counts as a twitch)."""
    rng = np.random.default_rng([seed, 0x571])
    first = [still_view(turn, first_m) for turn in turns_deg]
    others = []
    for _ in range(sets - 1):
        for turn in turns_deg:
            distance = float(np.exp(rng.uniform(math.log(near_m), math.log(far_m))))
            tilt, roll = rng.uniform(-max_tilt_deg, max_tilt_deg), rng.uniform(-max_roll_deg, max_roll_deg)
            right, down = rng.uniform(-max_right_deg, max_right_deg), rng.uniform(-max_down_deg, max_down_deg)
            others.append(still_view(turn, distance, tilt_deg=tilt, roll_deg=roll, right_deg=right, down_deg=down))
    first = [first[i] for i in rng.permutation(len(first))]
    others = [others[i] for i in rng.permutation(len(others))]
    total = len(first) + len(others)
    if len(first) > (total + 1) // 2:  # one set (or too few others): plainly shuffled
        return tuple(first + others)
    # positions of the first set with no two adjacent: k-th smallest of a sample of the spare slots, + k
    spare = sorted(rng.choice(total - len(first) + 1, size=len(first), replace=False).tolist())
    slots = {q + k for k, q in enumerate(spare)}
    first_iter, others_iter = iter(first), iter(others)
    return tuple(next(first_iter) if i in slots else next(others_iter) for i in range(total))


@dataclass(frozen=True)
class Trajectory:
    """Camera path over the clip.

    The calm kinds are functions of normalised time ``u`` in [0, 1] (:meth:`camera_from_world`);
    ``handheld`` is a function of time in seconds (:meth:`at_time`), so the motion does not change
    with the frame rate or the clip length.

    kind:
        ``sweep``: distance grows from ``near_m`` to ``far_m`` while the camera swings in azimuth
        and elevation (the demo's path: near, well-conditioned views to far, ambiguous ones).
        ``orbit``: constant distance ``near_m``, azimuth swings ``±azimuth_deg``.
        ``static``: a fixed camera at ``near_m``, ``azimuth_deg``, ``elevation_deg``.
        ``approach``: the camera comes from ``far_m`` to ``near_m`` (eased), viewing from about
        ``azimuth_deg`` / ``elevation_deg`` with a small sway (a far marker's flip is undecidable, a
        near one's is plain: the case where later frames settle earlier ones).
        ``handheld``: a hand-held webcam looking roughly at ``look_at``: the viewpoint sways
        (0.1-0.5 Hz, up to ``azimuth_deg`` / ``elevation_deg`` / ``roll_deg``, aim point wandering
        by ``aim_m``), the distance goes back and forth between ``near_m`` and ``far_m``, tremor
        (5-10 Hz, ``tremor_deg``) shakes it, and quick turns (out and back by up to ``turn_deg``,
        peak angular speed ``turn_peak_deg_s``, one every ``turn_every_s`` on average; 0 disables)
        jerk it away from the targets and back. The phases, frequencies and turn times come from
        ``seed``.
        ``stills``: one view per frame, ``stills[i]`` (a :data:`StillView`, around ``look_at``) at
        ``u`` nearest ``i / (len(stills) - 1)``: a folder of unrelated photos played as a clip (a scene
        of ``len(stills)`` frames shows each exactly once).
        ``cut``: ``parts[k]`` (each evaluated at the same ``u``) from ``cuts_u[k - 1]`` (inclusive) to
        ``cuts_u[k]``: a video with cuts between unrelated paths.
    """

    kind: str = "sweep"
    near_m: float = 0.35
    far_m: float = 3.0
    azimuth_deg: float = 35.0
    elevation_deg: float = 20.0
    roll_deg: float = 10.0
    cycles: float = 1.5
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # handheld only
    tremor_deg: float = 0.15
    turn_peak_deg_s: float = 200.0
    turn_deg: float = 15.0
    turn_every_s: float = 2.5
    aim_m: float = 0.02
    seed: int = 0
    duration_s: float = 10.0  # handheld: the time u = 1 maps to in camera_from_world(u)
    # stills only
    stills: tuple[StillView, ...] = ()
    # cut only
    parts: tuple[Trajectory, ...] = ()
    cuts_u: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"trajectory kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind == "stills":
            if not self.stills or any(len(v) != 6 or not v[3] > 0 for v in self.stills):
                raise ValueError("stills: give at least one view of 6 numbers (see still_view), distance > 0")
        if self.kind == "cut":
            cuts = self.cuts_u
            if len(self.parts) < 2 or len(cuts) != len(self.parts) - 1:
                raise ValueError("cut: give two or more parts and one cut (cuts_u) between each two")
            if not all(a < b for a, b in zip((0.0, *cuts), (*cuts, 1.0))):
                raise ValueError(f"cut: cuts_u must increase strictly inside (0, 1), got {cuts}")
        if not (0 < self.near_m and (self.kind not in ("sweep", "handheld", "approach") or self.near_m <= self.far_m)):
            raise ValueError(f"trajectory distances must satisfy 0 < near <= far, got {self.near_m}, {self.far_m}")
        if self.kind == "handheld":
            if self.turn_peak_deg_s < 0 or self.turn_deg < 0 or self.tremor_deg < 0 or self.aim_m < 0:
                raise ValueError("handheld: tremor_deg, turn_deg, turn_peak_deg_s and aim_m must be >= 0")
            if self.turn_peak_deg_s > 0 and self.turn_deg > 0 and not self.turn_every_s > 0:
                raise ValueError("handheld: turn_every_s must be > 0")

    def camera_from_world(self, u: float) -> Pose:
        """``camera_from_world`` at normalised time ``u`` in [0, 1] (``handheld``: at ``u * duration_s`` seconds)."""
        if self.kind == "handheld":
            return self.at_time(u * self.duration_s)
        if self.kind == "stills":
            index = min(max(int(math.floor(u * (len(self.stills) - 1) + 0.5)), 0), len(self.stills) - 1)
            return self._still(self.stills[index])
        if self.kind == "cut":
            part = sum(1 for cut in self.cuts_u if u >= cut)
            return self.parts[part].camera_from_world(u)
        az, el, roll, dist = self._angles(u)
        return self._view(az, el, roll, dist)

    def _view(self, az: float, el: float, roll: float, dist: float) -> Pose:
        """``camera_from_world`` looking at ``look_at`` from azimuth ``az``, elevation ``el`` (rad) at
        ``dist``, rolled by ``roll`` (rad)."""
        centre = np.asarray(self.look_at, dtype=np.float64)
        direction = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        pose = look_at(centre + dist * direction, centre, up=(0.0, 1.0, 0.0))
        if roll:
            roll_pose = Pose(np.array([0.0, 0.0, roll]), np.zeros(3))
            pose = roll_pose.compose(pose)
        return pose

    def _still(self, view: StillView) -> Pose:
        """``camera_from_world`` of one still: the view's pose, then the camera turned about its own centre
        so ``look_at`` is seen ``right_deg`` right of and ``down_deg`` below the optical axis."""
        turn, tilt, roll, dist, right, down = view
        pose = self._view(math.radians(turn), math.radians(tilt), math.radians(roll), dist)
        offset = Pose(np.array([0.0, math.radians(right), 0.0]), np.zeros(3)).compose(
            Pose(np.array([-math.radians(down), 0.0, 0.0]), np.zeros(3))
        )
        return offset.compose(pose)

    def at_time(self, t_s: float, clip_s: float | None = None) -> Pose:
        """``camera_from_world`` at ``t_s`` seconds; the calm kinds need the clip length ``clip_s``
        (``u = t_s / clip_s``)."""
        if self.kind != "handheld":
            if clip_s is None or not clip_s > 0:
                raise ValueError(f"{self.kind} trajectories need clip_s > 0 to be evaluated at a time")
            return self.camera_from_world(t_s / clip_s)
        return self._handheld(float(t_s))

    def _angles(self, u: float) -> tuple[float, float, float, float]:
        az0, el0, roll0 = (math.radians(v) for v in (self.azimuth_deg, self.elevation_deg, self.roll_deg))
        if self.kind == "static":
            return az0, el0, roll0, self.near_m
        phase = 2.0 * math.pi * self.cycles * u
        if self.kind == "approach":
            sway = math.radians(3.0)
            dist = self.far_m - (self.far_m - self.near_m) * (0.5 - 0.5 * math.cos(math.pi * u))
            return az0 + sway * math.sin(phase), el0 + sway * math.sin(0.73 * phase + 0.9), roll0, dist
        az = az0 * math.sin(phase)
        el = el0 * math.sin(0.73 * phase + 0.9)
        roll = roll0 * math.sin(0.41 * phase + 0.3)
        if self.kind == "orbit":
            return az, el, roll, self.near_m
        dist = self.near_m + (self.far_m - self.near_m) * (0.5 - 0.5 * math.cos(math.pi * u))
        return az, el, roll, dist

    # ------------------------------------------------------------------ handheld

    @functools.cached_property
    def _handheld_terms(self) -> dict[str, np.ndarray]:
        """Seeded frequencies (Hz), phases and weights of every sum of sinusoids."""
        rng = np.random.default_rng([self.seed, 0x4A4D])

        def band(n: int, low: float, high: float) -> np.ndarray:
            weights = rng.uniform(0.5, 1.0, n)
            # columns: frequency, phase, weight (weights sum to 1: the sum stays within its amplitude)
            return np.column_stack([rng.uniform(low, high, n), rng.uniform(0, 2 * np.pi, n), weights / weights.sum()])

        terms = {name: band(3, 0.1, 0.5) for name in ("az", "el", "roll", "aim_x", "aim_y")}
        terms["dist"] = band(2, 0.05, 0.2)
        for axis in "xyz":
            terms[f"tremor_{axis}"] = band(3, 5.0, 10.0)
        return terms

    @staticmethod
    def _sines(terms: np.ndarray, t_s: float) -> float:
        return float(np.sum(terms[:, 2] * np.sin(2 * np.pi * terms[:, 0] * t_s + terms[:, 1])))

    def _turn(self, t_s: float) -> np.ndarray:
        """Rotation vector (camera frame) of the quick turns at ``t_s``: raised-cosine bursts out and
        back, ``A (1 - cos(2 pi s)) / 2`` over ``D = pi A / peak`` seconds, so the angular speed peaks at
        exactly ``turn_peak_deg_s`` in every burst. Burst ``k`` starts near ``(k + 0.5) * turn_every_s``
        (seeded jitter), with a seeded size (50-100 % of ``turn_deg``) and direction."""
        if not (self.turn_peak_deg_s > 0 and self.turn_deg > 0):
            return np.zeros(3)
        period = self.turn_every_s
        rotation = np.zeros(3)
        k0 = math.floor(t_s / period)
        for k in (k0 - 1, k0, k0 + 1):
            if k < 0:
                continue
            rng = np.random.default_rng([self.seed, 0x7E4, k])
            size_deg = self.turn_deg * rng.uniform(0.5, 1.0)
            duration = math.pi * size_deg / self.turn_peak_deg_s
            start = (k + 0.5 + rng.uniform(-0.25, 0.25)) * period
            start = min(start, (k + 1) * period - duration)  # a burst stays inside its slot: no overlaps
            direction = rng.uniform(0, 2 * np.pi)
            axis = np.array([math.sin(direction), math.cos(direction), 0.2 * rng.uniform(-1, 1)])
            axis /= np.linalg.norm(axis)
            s = (t_s - start) / duration
            if 0.0 <= s <= 1.0:
                rotation += axis * math.radians(size_deg) * 0.5 * (1.0 - math.cos(2 * math.pi * s))
        return rotation

    def _handheld(self, t_s: float) -> Pose:
        terms = self._handheld_terms
        az = math.radians(self.azimuth_deg) * self._sines(terms["az"], t_s)
        el = math.radians(self.elevation_deg) * self._sines(terms["el"], t_s)
        roll = math.radians(self.roll_deg) * self._sines(terms["roll"], t_s)
        mix = 0.5 + 0.5 * self._sines(terms["dist"], t_s)
        dist = self.near_m + (self.far_m - self.near_m) * mix
        aim = np.asarray(self.look_at, dtype=np.float64) + self.aim_m * np.array(
            [self._sines(terms["aim_x"], t_s), self._sines(terms["aim_y"], t_s), 0.0]
        )
        direction = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        pose = look_at(aim + dist * direction, aim, up=(0.0, 1.0, 0.0))
        tremor = math.radians(self.tremor_deg) * np.array([self._sines(terms[f"tremor_{axis}"], t_s) for axis in "xyz"])
        about_centre = np.array([0.0, 0.0, roll]) + tremor + self._turn(t_s)
        # rotations about the camera's own centre: applied in the camera frame, translation-free
        return Pose(about_centre, np.zeros(3)).compose(pose)
