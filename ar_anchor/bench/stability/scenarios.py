"""The benchmark's synthetic clips: the calm grid, the unrelated-frames scenes (issue 32: a folder of
stills, a video with a cut, a crisper far static scene) and the hand-held webcam scenarios.

A :class:`Scenario` says what is rendered (markers, camera path, camera, image degradations) and how
the tracker is configured to track it; :func:`stability_scenarios` is the grid ``ar-anchor bench
stability`` runs. See :mod:`ar_anchor.sources.synthetic` for how each effect is rendered.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

from ...camera import CameraModel
from ...config import TrackerConfig
from ...geometry import Pose
from ...synthetic import Lighting, Occluder, PlacedMarker, SyntheticScene, Trajectory, marker_sheet, webcam_camera
from ...synthetic.trajectory import turntable_stills

__all__ = ["Scenario", "discontinuity_scenarios", "handheld_scenarios", "scenario_dict", "stability_scenarios"]

STILL_STEP_DEG = 10.0  # motion="stills": the turns are -tilt_deg..+tilt_deg in steps of this


@dataclass(frozen=True)
class Scenario:
    """One synthetic clip: a lone marker (``sheet`` 0) or a rigid sheet of ``sheet`` markers (ids 0..K-1,
    ``sheet_cols`` per row, ``sheet_gap_m`` apart), seen by a static, moving or hand-held camera.

    The default camera is the benchmark's (720p); ``resolution`` asks for a webcam-like camera of
    that size (``hfov_deg``, radial distortion ``k1``/``k2``). The hand-held options map onto
    :class:`~ar_anchor.sources.synthetic.SyntheticScene`'s: ``fps``, ``content_fps`` (duplicated
    frames), ``exposure_s``, ``rolling_shutter_s``, ``compression`` (``jpeg_quality``, ``h264_kbps``),
    ``lighting``, ``occluders``; the hand-held path: ``distance_m`` to ``far_m``, sway up to
    ``tilt_deg`` (azimuth), ``tremor_deg``, quick turns to ``turn_peak_deg_s`` (0: none),
    ``turn_every_s``, aim wander ``aim_m`` around ``aim_offset_m`` (an offset pushes the targets towards
    the image border). ``min_perimeter_rate`` overrides the detector's
    (far markers).

    ``motion="stills"`` (issue 32): unrelated photos of the marker, one per frame
    (:func:`~ar_anchor.synthetic.trajectory.turntable_stills` with ``seed``): turned -``tilt_deg``..
    +``tilt_deg`` about a vertical axis in ``STILL_STEP_DEG`` steps, a first set centred at 0.5 m, the
    others at ``distance_m``..``far_m`` and elsewhere in the image, shuffled; ``frames`` must be a whole
    number of sets. ``motion="cut"``: a video with a cut at the middle frame: the hand-held path of this
    scenario (no quick turns unless asked), then an unrelated one, ``cut_to`` = (distance m, far m, tilt
    deg, seed) of the hand-held path after the cut.
    """

    name: str
    marker_m: float
    distance_m: float
    motion: str = "static"  # static | wobble | orbit | fast | sweep | approach | handheld | stills | cut
    tilt_deg: float = 0.0
    noise: float = 2.0
    blur: float = 0.6
    frames: int = 150
    far_m: float | None = None  # sweep, approach, handheld: the far end
    hidden: tuple[tuple[int, int], ...] = ()
    seed: int = 0
    # hand-held webcam realism (defaults: the calm scenario)
    sheet: int = 0
    sheet_cols: int = 3
    sheet_gap_m: float | None = None  # default: half a marker
    resolution: tuple[int, int] | None = None
    hfov_deg: float = 62.0
    k1: float = 0.0
    k2: float = 0.0
    fps: float = 30.0
    content_fps: float | None = None
    exposure_s: float = 0.0
    rolling_shutter_s: float = 0.0
    compression: str = ""
    jpeg_quality: int = 70
    h264_kbps: float = 1000.0
    lighting: Lighting | None = None
    occluders: tuple[Occluder, ...] = ()
    tremor_deg: float = 0.15
    turn_peak_deg_s: float = 0.0
    turn_deg: float = 12.0
    turn_every_s: float = 2.5
    aim_m: float = 0.02
    aim_offset_m: tuple[float, float] = (0.0, 0.0)  # where the hand-held camera aims, off the targets' centre
    min_perimeter_rate: float | None = None
    cut_to: tuple[float, float, float, int] = ()  # motion="cut": the second path (distance m, far m, tilt deg, seed)

    @property
    def moving(self) -> bool:
        return self.motion != "static"

    @property
    def marker_ids(self) -> tuple[int, ...]:
        return tuple(range(self.sheet)) if self.sheet else (0,)

    def trajectory(self) -> Trajectory:
        """The camera path for ``motion`` (static, wobble, orbit, fast, sweep, approach, handheld, stills, cut)
        at ``distance_m``."""
        seconds = self.frames / 30.0
        if self.motion == "static":
            return Trajectory(
                kind="static", near_m=self.distance_m, azimuth_deg=self.tilt_deg, elevation_deg=0.0, roll_deg=0.0
            )
        orbits = {  # motion: azimuth, elevation, roll (deg), cycles of an orbit at constant distance
            "wobble": (self.tilt_deg + 4.0, 3.0, 2.0, 1.0),  # nearly fronto-parallel, small hand-held motion
            "orbit": (35.0, 15.0, 10.0, seconds * 45.0 / (2 * math.pi * 35.0)),  # about 45 deg/s at the peak
            "fast": (45.0, 5.0, 0.0, seconds * 90.0 / (2 * math.pi * 45.0)),  # 90 deg/s at the peak
        }
        if self.motion in orbits:
            azimuth, elevation, roll, cycles = orbits[self.motion]
            return Trajectory(
                kind="orbit",
                near_m=self.distance_m,
                azimuth_deg=azimuth,
                elevation_deg=elevation,
                roll_deg=roll,
                cycles=cycles,
            )
        if self.motion == "sweep":
            return Trajectory(
                kind="sweep",
                near_m=self.distance_m,
                far_m=self.far_m or self.distance_m * 4,
                azimuth_deg=30.0,
                elevation_deg=15.0,
                roll_deg=10.0,
                cycles=1.0,
            )
        if self.motion == "approach":
            return Trajectory(
                kind="approach",
                near_m=self.distance_m,
                far_m=self.far_m or self.distance_m * 6,
                azimuth_deg=self.tilt_deg,
                elevation_deg=0.5 * self.tilt_deg,
                roll_deg=5.0,
                cycles=1.0,
            )
        if self.motion == "handheld":
            return self._handheld(self.distance_m, self.far_m or self.distance_m, self.tilt_deg, self.seed)
        if self.motion == "stills":
            turns = tuple(
                -self.tilt_deg + STILL_STEP_DEG * k for k in range(int(round(2 * self.tilt_deg / STILL_STEP_DEG)) + 1)
            )
            if self.frames % len(turns):
                raise ValueError(f"stills: frames ({self.frames}) must be a multiple of the {len(turns)} turns")
            stills = turntable_stills(
                self.seed, turns_deg=turns, near_m=self.distance_m, far_m=self.far_m or self.distance_m,
                sets=self.frames // len(turns),
            )  # fmt: skip
            return Trajectory(kind="stills", stills=stills)
        if self.motion == "cut":
            if len(self.cut_to) != 4:
                raise ValueError("cut: cut_to must be (distance m, far m, tilt deg, seed) of the path after the cut")
            near, far, tilt, seed = self.cut_to
            duration = max(self.frames - 1, 1) / self.fps  # the parts' u = 1: the clip's last frame, in seconds
            first = self._handheld(self.distance_m, self.far_m or self.distance_m, self.tilt_deg, self.seed)
            second = self._handheld(near, far, tilt, int(seed))
            parts = tuple(dataclasses.replace(p, duration_s=duration) for p in (first, second))
            middle = self.frames // 2  # the first frame after the cut
            return Trajectory(kind="cut", parts=parts, cuts_u=((middle - 0.5) / max(self.frames - 1, 1),))
        raise ValueError(f"unknown motion {self.motion!r}")

    def _handheld(self, near_m: float, far_m: float, tilt_deg: float, seed: int) -> Trajectory:
        """The hand-held path with this scenario's tremor, turns and aim, from ``near_m`` to ``far_m``."""
        return Trajectory(
            kind="handheld",
            near_m=near_m,
            far_m=far_m,
            azimuth_deg=tilt_deg,
            elevation_deg=0.6 * tilt_deg,
            roll_deg=6.0,
            tremor_deg=self.tremor_deg,
            turn_peak_deg_s=self.turn_peak_deg_s,
            turn_deg=self.turn_deg,
            turn_every_s=self.turn_every_s,
            aim_m=self.aim_m,
            look_at=(*self.aim_offset_m, 0.0),
            seed=seed,
        )

    def camera_model(self, default: CameraModel) -> CameraModel:
        """The scenario's camera: ``default`` unless it asks for a resolution (then a webcam-like one)."""
        if self.resolution is None:
            return default
        return webcam_camera(*self.resolution, hfov_deg=self.hfov_deg, k1=self.k1, k2=self.k2)

    def scene(self, camera: CameraModel, dictionary: str = "DICT_4X4_50") -> SyntheticScene:
        sheets = ()
        if self.sheet:
            gap = self.marker_m / 2 if self.sheet_gap_m is None else self.sheet_gap_m
            markers, paper = marker_sheet(range(self.sheet), length_m=self.marker_m, cols=self.sheet_cols, gap_m=gap)
            sheets = (paper,)
        else:
            markers = (PlacedMarker(0, self.marker_m, Pose.identity()),)
        return SyntheticScene(
            camera=camera,
            dictionary=dictionary,
            markers=markers,
            trajectory=self.trajectory(),
            frames=self.frames,
            fps=self.fps,
            seed=self.seed,
            noise_sigma=self.noise,
            blur_sigma=self.blur,
            hidden=self.hidden,
            exposure_s=self.exposure_s,
            rolling_shutter_s=self.rolling_shutter_s,
            lighting=self.lighting,
            occluders=self.occluders,
            content_fps=self.content_fps,
            compression=self.compression,
            jpeg_quality=self.jpeg_quality,
            h264_kbps=self.h264_kbps,
            sheets=sheets,
        )

    def tracker_config(self, config: TrackerConfig) -> TrackerConfig:
        """``config`` tracking exactly this scenario's markers: lone markers of ``marker_m`` with the
        scene's ids, no per-id lengths, no boards, filter on (and the scenario's detector override)."""
        config = config.with_overrides(marker_length_m=self.marker_m, filter_enabled=True)
        detector = config.detector
        if self.min_perimeter_rate is not None:
            detector = dataclasses.replace(detector, min_perimeter_rate=self.min_perimeter_rate)
        return dataclasses.replace(
            config,
            detector=detector,
            markers=dataclasses.replace(config.markers, length_m=self.marker_m, lengths_m={}, ids=self.marker_ids),
            boards=(),
        )


def scenario_dict(scenario: Scenario) -> dict[str, Any]:
    """JSON-friendly description: the calm fields always, the hand-held ones when they are not defaults."""
    out = {}
    defaults = Scenario("", 0.05, 1.0)
    calm = {
        *("name", "marker_m", "distance_m", "motion", "tilt_deg", "noise", "blur", "frames", "far_m", "hidden"),
        "seed",
    }
    for f in dataclasses.fields(Scenario):
        value = getattr(scenario, f.name)
        if f.name in calm or value != getattr(defaults, f.name):
            if isinstance(value, (Lighting, Occluder)):
                value = dataclasses.asdict(value)
            elif isinstance(value, tuple) and value and isinstance(value[0], Occluder):
                value = [dataclasses.asdict(v) for v in value]
            out[f.name] = value
    return json.loads(json.dumps(out, default=list))


def handheld_scenarios(quick: bool = False) -> list[Scenario]:
    """Hand-held webcam scenarios: a 6-marker sheet (5 cm, or 4 cm far away) or lone markers, sway,
    tremor, quick turns, blur over the exposure, rolling shutter, compression, 5-60 fps,
    duplicated frames, a hand, lighting, distortion."""
    seconds = 3.0 if quick else 5.0
    vga, hd = (640, 480), (1280, 720)
    common = dict(
        motion="handheld", sheet=6, resolution=vga, noise=2.0, blur=0.5, exposure_s=0.012,
        rolling_shutter_s=0.02, turn_peak_deg_s=120.0, lighting=Lighting(gain_drift=0.1, offset_drift=5.0, steps=()),
    )  # fmt: skip

    def clip(name: str, fps: float = 30.0, **kw: Any) -> Scenario:
        options = {**common, **kw}
        return Scenario(name, options.pop("marker_m", 0.05), options.pop("distance_m", 0.35),
                        frames=int(round(seconds * fps)), fps=fps, **options)  # fmt: skip

    hand = (Occluder(int(0.4 * seconds * 30), int(0.75 * seconds * 30), from_xy=(-0.3, 0.6), to_xy=(1.3, 0.4)),)
    grid = [
        clip("hh vga h264 sheet6 30fps", far_m=0.8, tilt_deg=25, compression="h264", h264_kbps=800.0, seed=1),
        clip("hh 720p mjpeg sheet6", resolution=hd, far_m=1.0, tilt_deg=25, compression="jpeg", jpeg_quality=60, seed=2,
             exposure_s=0.016, rolling_shutter_s=0.03),
        clip("hh vga 5fps sheet6", fps=5.0, far_m=0.8, tilt_deg=25, compression="jpeg", exposure_s=0.03, seed=3),
        clip("hh vga 60fps sheet6", fps=60.0, far_m=0.8, tilt_deg=25, compression="jpeg", exposure_s=0.008, seed=4,
             rolling_shutter_s=0.012),
        clip("hh vga 30fps dup12 sheet6", content_fps=12.0, far_m=0.8, tilt_deg=25, compression="h264", seed=5,
             exposure_s=0.02),
        clip("hh vga strong blur turns 200deg/s", far_m=0.7, tilt_deg=30, exposure_s=0.03, turn_peak_deg_s=200.0,
             turn_deg=15.0, turn_every_s=1.5, compression="jpeg", seed=6),
        clip("hh vga hand occlusion sheet6", far_m=0.7, tilt_deg=20, occluders=hand, compression="jpeg", seed=7,
             turn_peak_deg_s=0.0),
        clip("hh 720p far 4cm 2-3m sheet6", resolution=hd, hfov_deg=50.0, marker_m=0.04, distance_m=2.0, far_m=3.0,
             tilt_deg=15, aim_m=0.05, turn_peak_deg_s=60.0, turn_deg=4.0, compression="jpeg", jpeg_quality=80, seed=8,
             min_perimeter_rate=0.015),
        clip("hh vga distortion k1-0.25 sheet6", k1=-0.25, k2=0.08, hfov_deg=70.0, far_m=0.8, tilt_deg=25, seed=9,
             compression="jpeg", aim_m=0.06),
        clip("hh vga lighting step border lone 6cm", sheet=0, marker_m=0.06, distance_m=0.4, far_m=0.9, tilt_deg=30,
             aim_m=0.1, aim_offset_m=(0.3, 0.04), compression="h264", seed=10,
             lighting=Lighting(gain_drift=0.12, offset_drift=6.0, steps=((0.4 * seconds, 0.6),))),
    ]  # fmt: skip
    return [grid[i] for i in (0, 4, 6)] if quick else grid


def discontinuity_scenarios(quick: bool = False) -> list[Scenario]:
    """Issue 32, "tracked means right on every sequence": clips whose frames are unrelated, where a pose
    carried over from an earlier frame is wrong: a folder of stills (a lone 8 cm marker turned -70..+70 deg
    in 10-deg steps, at 0.3-1.5 m and anywhere in the image, shuffled: 45 photos played at 30 fps), a video
    with a cut at the middle frame (two unrelated hand-held paths of a lone 6 cm marker: swaying up to 25
    deg, then nearly fronto-parallel, where the frame alone hardly decides the flip and a pose carried
    over from before the cut is tempting), and (full grid only) the far, nearly fronto-parallel static
    scene rendered with less sensor noise (1 grey level) and turned the other way (tilt -3 deg): where a
    corner bias that follows the marker's bits picked the wrong branch in every frame."""
    grid = [
        Scenario("stills 8cm 0.3-1.5m turn ±70", 0.08, 0.3, "stills", far_m=1.5, tilt_deg=70, frames=45, seed=32),
        Scenario("cut 6cm hh 0.5-0.7m tilt25 to 0.6-0.8m fronto", 0.06, 0.5, "cut", far_m=0.7, tilt_deg=25,
                 frames=150, aim_offset_m=(0.1, 0.05), cut_to=(0.6, 0.8, 6.0, 33), seed=31),
        Scenario("static 4cm 3m tilt-3 noise1", 0.04, 3.0, "static", tilt_deg=-3, noise=1.0, blur=0.6, frames=150),
    ]  # fmt: skip
    return grid[:2] if quick else grid  # quick: the same stills and cut (a shorter cut would cut elsewhere)


def stability_scenarios(quick: bool = False) -> list[Scenario]:
    """The benchmark grid: the 15 calm scenarios (sizes 3-12 cm, 0.3-4 m, tilts down to
    fronto-parallel, static and moving, noise, dropouts, an approach from 4 m), the issue-32 scenes
    (:func:`discontinuity_scenarios`: stills, a cut, a sharper far static scene), then the hand-held ones."""
    frames = 90 if quick else 150
    grid = [
        Scenario("static 12cm 0.5m tilt30", 0.12, 0.5, "static", tilt_deg=30, frames=frames),
        Scenario("static 6cm 1m tilt20", 0.06, 1.0, "static", tilt_deg=20, frames=frames),
        Scenario("static 6cm 1m fronto", 0.06, 1.0, "static", tilt_deg=0, frames=frames),
        Scenario("static 4cm 3m tilt15", 0.04, 3.0, "static", tilt_deg=15, frames=frames),
        Scenario("static 4cm 3.5m fronto", 0.04, 3.5, "static", tilt_deg=0, frames=frames),
        Scenario("static 12cm 4m tilt20", 0.12, 4.0, "static", tilt_deg=20, frames=frames),
        Scenario("static 3cm 0.3m tilt40 noise4", 0.03, 0.3, "static", tilt_deg=40, noise=4.0, frames=frames),
        Scenario("wobble 5cm 0.6m fronto", 0.05, 0.6, "wobble", frames=frames),
        Scenario("wobble 4cm 2m fronto", 0.04, 2.0, "wobble", frames=frames),
        Scenario("orbit 6cm 1m", 0.06, 1.0, "orbit", frames=frames),
        Scenario("orbit 4cm 2m", 0.04, 2.0, "orbit", frames=frames),
        Scenario("fast 8cm 0.8m 90deg/s", 0.08, 0.8, "fast", frames=frames),
        Scenario("sweep 6cm 0.4-3m", 0.06, 0.4, "sweep", far_m=3.0, frames=frames),
        Scenario(
            "orbit 6cm 1m dropouts",
            0.06,
            1.0,
            "orbit",
            frames=frames,
            hidden=((frames // 3, frames // 3 + 6), (2 * frames // 3, 2 * frames // 3 + 20)),
        ),
        # issue 20: ambiguous far away, decisive near: the causal tracker is ambiguous early, the offline
        # replay decides from its first output frame (the 4 cm marker is first detected at about 3.2 m)
        Scenario("approach 4cm 4-0.5m tilt25", 0.04, 0.5, "approach", far_m=4.0, tilt_deg=25, frames=frames),
    ]
    calm = grid[::2] if quick else grid  # (quick keeps the approach: the last)
    return calm + discontinuity_scenarios(quick) + handheld_scenarios(quick)
