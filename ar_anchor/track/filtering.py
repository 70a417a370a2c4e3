"""Temporal filtering: resolve the planar flip with evidence over time, and smooth the pose, without
ever making the pose worse than the per-frame measurements it is fed.

Per target, a :class:`TargetTrack` carries

* **two branches**, one per IPPE solution. The two solutions of a square are mirror images through
  the line of sight (their normals' tilts away from it are opposite), so a small Kalman filter on
  branch 0's tilt (:class:`_TiltTracker`) tells which solution continues which branch, through
  crossings too (a view through fronto-parallel). It cannot go blind: unclear frames update it with
  inflated noise, its rate and uncertainty are bounded, and after a gap it restarts at rest from the
  branch's last measured orientation. Where the branch smoothers' own motion prediction contradicts
  the tilt's assignment, the frame's assignment is in doubt: no evidence is taken from it and
  nothing is vouched for.
* **evidence** for branch 0 against branch 1 over ``evidence_window_s``: per frame, the difference of
  their RMS reprojection errors. A branch is *committed* only when the window's mean difference
  exceeds ``decide_margin_px`` with ``decide_z`` standard errors of confidence. The margin is there
  because a corner detector's own bias (a few hundredths of a pixel) differs systematically between
  the branches too: evidence below it never decides, however long one waits. Such a target stays
  ``ambiguous``, and its output is a best guess that follows the per-frame pick's tendency without
  its flicker. A committed branch moves on sustained evidence (``switch_margin_px``, ``switch_z``) or,
  self-correcting, on ``decisive_frames`` frames that contradict it (the first one *decisive*: the
  other solution alone, or much better by ``decisive_ratio`` and ``decisive_sigmas``).
* a **smoother** per branch: an error-state Kalman filter on SO(3) (rotation error as a body-frame
  rotation vector, so no Euler angles and no trouble near 180 degrees) and, shared, one on
  translation, each an IMM (``filterpy``) of a *still* model that averages a static marker over many
  frames and a *moving* constant-velocity model. Measurement noise is the pose covariance implied by
  the corner noise through the projection Jacobian (it grows with distance and shrinks with marker
  size in pixels; the corner noise is estimated online, and a blurred frame's larger residuals make
  its own measurement count less). No measurement is rejected: a smoother it lands far from restarts
  from it. The output is held within ``output_sigmas`` standard deviations of this frame's
  measurement (``output_sigmas_moving`` unless the measurements stayed put for ``still_s``), so
  smoothing lowers jitter but cannot lag behind real motion.
* **dropouts**: a missed frame is predicted (state ``predicted``, velocity decaying with
  ``predict_damping_s``) for at most ``predict_s`` and only while the motion since the last
  measurement may have moved the target less than ``predict_max_deg``; then nothing is published, but
  the track keeps its branches and evidence for ``memory_s``: a target that returns is not new.

``tracked`` is only said of the committed branch, measured this frame as the lower-error solution,
with no contradicting frame open, no doubt about the assignment, and an orientation whose 3-sigma
uncertainty is below ``flip_angle_deg``. All time constants are in seconds.
"""

from __future__ import annotations

import collections
import logging
import math
import sys
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from ..camera import CameraModel
from ..config import FilterConfig
from ..geometry import Pose, angle_between_deg, matrix_from_rvec, rvec_from_matrix
from .pose import BoardPose, MarkerPose, PoseHypothesis

__all__ = [
    "RotationFilter",
    "decisive",
    "margin_scale",
    "TargetTrack",
    "TrackEvent",
    "TrackUpdate",
    "TranslationFilter",
    "pose_covariance",
]

log = logging.getLogger(__name__)


class _KalmanFilter(KalmanFilter):
    """filterpy's filter with the measurement log-likelihood (which the IMM reads every update)
    computed by a Cholesky solve instead of ``scipy.stats.multivariate_normal`` (~0.1 ms a call)."""

    @property
    def log_likelihood(self) -> float:
        if self._log_likelihood is None:
            innovation = np.asarray(self.y, np.float64).reshape(-1)
            try:
                lower = np.linalg.cholesky(np.asarray(self.S, np.float64))
            except np.linalg.LinAlgError:
                self._log_likelihood = math.log(sys.float_info.min)
                return self._log_likelihood
            whitened = np.linalg.solve(lower, innovation)
            self._log_likelihood = float(
                -0.5 * whitened @ whitened
                - np.log(np.diag(lower)).sum()
                - 0.5 * len(innovation) * math.log(2.0 * math.pi)
            )
        return self._log_likelihood


# ---------------------------------------------------------------------------- SO(3) helpers


def so3_exp(vector: np.ndarray) -> np.ndarray:
    return matrix_from_rvec(vector)


def so3_log(rotation: np.ndarray) -> np.ndarray:
    return rvec_from_matrix(rotation)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pose_covariance(
    pose: Pose, points_in_target: np.ndarray, camera: CameraModel, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of (rotation error, translation) implied by isotropic corner noise ``sigma_px``.

    Linearises the pinhole projection at ``pose`` with the rotation perturbed on the right
    (``R exp(dtheta)``, the filter's error convention): ``Sigma = sigma^2 (J^T J)^-1``. Returns the
    3x3 rotation block (rad^2, body frame) and the 3x3 translation block (m^2, camera frame).
    """
    rotation = pose.rotation
    fx, fy = camera.camera_matrix[0, 0], camera.camera_matrix[1, 1]
    points = np.asarray(points_in_target, dtype=np.float64).reshape(-1, 3)
    x, y, z = (points @ rotation.T + pose.tvec).T
    count = len(points)
    d_pixel_d_cam = np.zeros((count, 2, 3))  # the pinhole projection's Jacobian at each point
    d_pixel_d_cam[:, 0, 0] = fx / z
    d_pixel_d_cam[:, 0, 2] = -fx * x / z**2
    d_pixel_d_cam[:, 1, 1] = fy / z
    d_pixel_d_cam[:, 1, 2] = -fy * y / z**2
    skew = np.zeros((count, 3, 3))  # [p]_x per point
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -points[:, 2], points[:, 1], -points[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = points[:, 2], -points[:, 1], points[:, 0]
    d_cam = np.concatenate([-rotation @ skew, np.broadcast_to(np.eye(3), (count, 3, 3))], axis=2)  # (N, 3, 6)
    jacobian = (d_pixel_d_cam @ d_cam).reshape(2 * count, 6)
    information = jacobian.T @ jacobian
    information += np.eye(6) * 1e-9 * np.trace(information)  # keep it invertible at degenerate views
    covariance = sigma_px**2 * np.linalg.inv(information)
    return covariance[:3, :3], covariance[3:, 3:]


# 4 corners (8 coordinates), 6 pose parameters: E[RMS^2] = sigma^2 (8 - 6) / 4, so sigma = RMS * sqrt(2)
_RESIDUAL_TO_SIGMA = math.sqrt(2.0)


_POSITION, _VELOCITY = np.arange(3), np.arange(3, 6)  # the blocks of a 3D constant-velocity state [x, v]


def _cv_process_noise(dt: float, accel_sigma: float) -> np.ndarray:
    """Discrete white-noise-acceleration covariance for a 3D constant-velocity state [x, v]."""
    q = accel_sigma**2
    noise = np.zeros((6, 6))
    noise[_POSITION, _POSITION] = q * dt**3 / 3.0
    noise[_POSITION, _VELOCITY] = noise[_VELOCITY, _POSITION] = q * dt**2 / 2.0
    noise[_VELOCITY, _VELOCITY] = q * dt
    return noise


def _cv_transition(dt: float) -> np.ndarray:
    transition = np.eye(6)
    transition[_POSITION, _VELOCITY] = dt
    return transition


# ---------------------------------------------------------------------------- filters


class _TwoModeCV:
    """Kalman filter on a 3D quantity as an IMM of a "still" and a "moving" motion model.

    The still model holds the quantity constant (velocity zero, a tiny random walk) and so
    averages the measurements of a static target over many frames; the moving model is a
    constant-velocity model with a large white acceleration that follows real motion without lag.
    An interacting-multiple-model estimator weighs them by how well each predicted the measurements.
    State ``[q, q_dot]`` (6), measurement ``q`` (3).

    This is ``filterpy``'s :class:`~filterpy.kalman.IMMEstimator` over two of its
    :class:`~filterpy.kalman.KalmanFilter` (the same mixing, the same Joseph-form update), with the
    two models stacked in arrays: every target runs three of these per frame, and filterpy's
    per-filter Python loops cost about 0.3 ms a frame where these batched steps cost a tenth of
    that. ``tests/test_filtering.py`` checks it against filterpy's own IMM, step by step.
    """

    _H_ROWS = slice(0, 3)  # H = [I 0]: the measurement is the state's first three entries

    def __init__(
        self, x0: np.ndarray, p0: np.ndarray, still_sigma: float, accel_moving: float, switch_probability: float = 0.02
    ) -> None:
        self.still_sigma = still_sigma  # random walk of the still model, units / sqrt(s)
        self.accel_moving = accel_moving
        self.xs = np.repeat(np.asarray(x0, np.float64).reshape(1, 6), 2, axis=0)  # per model
        self.Ps = np.repeat(np.asarray(p0, np.float64).reshape(1, 6, 6), 2, axis=0)
        self.mu = np.array([0.5, 0.5])
        p = switch_probability
        self.M = np.array([[1 - p, p], [p, 1 - p]])  # noqa: N806 - the IMM's Markov matrix
        self._dt: float | None = None
        self._F = self._Q = np.zeros((2, 6, 6))  # noqa: N815
        self._combine()

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:  # noqa: N802 - the Kalman filter's name for it
        return self._P

    @property
    def moving_probability(self) -> float:
        return float(self.mu[1])

    def _combine(self) -> None:
        """The IMM's output: the models' states and covariances weighed by the mode probabilities."""
        self._x = self.mu @ self.xs
        spread = self.xs - self._x
        self._P = np.einsum("m,mij->ij", self.mu, self.Ps + spread[:, :, None] * spread[:, None, :])

    def _models(self, dt: float) -> None:
        """Transition and process noise of both models for a step of ``dt`` (the still model: position
        kept, velocity zeroed, a random walk; the moving one: :func:`_cv_transition`, :func:`_cv_process_noise`)."""
        if dt == self._dt:
            return
        still_f, still_q = np.zeros((6, 6)), np.zeros((6, 6))
        still_f[_POSITION, _POSITION] = 1.0
        still_q[_POSITION, _POSITION] = self.still_sigma**2 * dt
        still_q[_VELOCITY, _VELOCITY] = 1e-12
        self._F = np.stack([still_f, _cv_transition(dt)])
        self._Q = np.stack([still_q, _cv_process_noise(dt, self.accel_moving)])
        self._dt = dt

    def predict(self, dt: float) -> None:
        self._models(dt)
        # mixing: model j starts from the mixture of both models, weighed by P(was i | is j)
        cbar = self.mu @ self.M
        omega = self.M * self.mu[:, None] / cbar[None, :]  # omega[i, j]
        mixed_x = omega.T @ self.xs
        spread = self.xs[None, :, :] - mixed_x[:, None, :]  # [j, i, :]
        mixed_p = np.einsum("ij,ikl->jkl", omega, self.Ps) + np.einsum("ij,jik,jil->jkl", omega, spread, spread)
        self.xs = np.einsum("mij,mj->mi", self._F, mixed_x)
        self.Ps = self._F @ mixed_p @ self._F.transpose(0, 2, 1) + self._Q
        self._combine()

    def update(self, z: np.ndarray, cov: np.ndarray) -> None:
        z = np.asarray(z, np.float64).reshape(3)
        cov = np.asarray(cov, np.float64)
        rows = self._H_ROWS
        innovation = z - self.xs[:, rows]  # (2, 3)
        pht = self.Ps[:, :, rows]  # P H^T, (2, 6, 3)
        s = self.Ps[:, rows, rows] + cov  # (2, 3, 3)
        s_inv = np.linalg.inv(s)
        gain = pht @ s_inv  # (2, 6, 3)
        self.xs = self.xs + np.einsum("mij,mj->mi", gain, innovation)
        i_kh = np.repeat(np.eye(6)[None], 2, axis=0)
        i_kh[:, :, rows] -= gain
        self.Ps = i_kh @ self.Ps @ i_kh.transpose(0, 2, 1) + gain @ cov @ gain.transpose(0, 2, 1)
        self.mu = self.mu @ self.M * _likelihoods(innovation, s, s_inv)
        total = self.mu.sum()
        self.mu = self.mu / total if total > 0 and math.isfinite(total) else np.array([0.5, 0.5])
        self._combine()

    def shift(self, delta: np.ndarray) -> None:
        """Subtract ``delta`` from the first three state entries (after folding them into a nominal state)."""
        self.xs[:, :3] -= delta
        self._x = self._x.copy()
        self._x[:3] -= delta


def _likelihoods(innovations: np.ndarray, covariances: np.ndarray, inverses: np.ndarray) -> np.ndarray:
    """Gaussian likelihood of each model's innovation (M, 3) under its covariance (M, 3, 3) (with its
    inverse), relative to the largest: the IMM normalises them anyway, and relative values cannot all
    underflow to zero. A model whose covariance is not positive definite gets likelihood zero."""
    sign, log_det = np.linalg.slogdet(covariances)
    mahalanobis = np.einsum("mi,mij,mj->m", innovations, inverses, innovations)
    log_l = np.where((sign > 0) & (mahalanobis >= 0), -0.5 * mahalanobis - 0.5 * log_det, -np.inf)
    if not np.isfinite(log_l).any():
        return np.ones(len(innovations))
    return np.exp(log_l - log_l[np.isfinite(log_l)].max())


class RotationFilter:
    """Error-state filter on SO(3) with a constant angular velocity model (two process-noise modes).

    Nominal state: rotation ``R`` (``camera_from_target``); filter state ``x = [dtheta, omega]``:
    the body-frame rotation error, folded into ``R`` and reset to zero after every step, and the
    angular velocity (rad/s, body frame). ``R_true = R exp(dtheta)``; predict ``R <- R exp(omega dt)``.
    Working on a small error vector keeps the filter away from Euler angles and from the
    rotation-vector wrap at 180 degrees.
    """

    def __init__(
        self,
        rotation: np.ndarray,
        rotation_cov: np.ndarray,
        still_sigma: float,
        accel_moving: float,
        omega: np.ndarray | None = None,
        omega_sigma: float = 1.0,
    ) -> None:
        self.accels = (still_sigma, accel_moving)
        self.reset(rotation, rotation_cov, omega, omega_sigma)

    def reset(
        self, rotation: np.ndarray, rotation_cov: np.ndarray, omega: np.ndarray | None = None, omega_sigma: float = 1.0
    ) -> None:
        self.rotation = np.array(rotation, dtype=np.float64)
        x0 = np.zeros(6)
        if omega is not None:
            x0[3:] = omega
        p0 = np.block([[rotation_cov, np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3) * omega_sigma**2]])
        self.cv = _TwoModeCV(x0, p0, *self.accels)

    @property
    def omega(self) -> np.ndarray:
        return self.cv.x[3:].copy()

    def _fold(self) -> None:
        delta = self.cv.x[:3].copy()
        self.rotation = self.rotation @ so3_exp(delta)
        self.cv.shift(delta)

    def predict(self, dt: float) -> None:
        self.cv.predict(dt)
        self._fold()

    def innovation(self, measured: np.ndarray) -> np.ndarray:
        """Body-frame rotation vector from the current estimate to a measurement."""
        return so3_log(self.rotation.T @ measured)

    def update(self, measured: np.ndarray, cov: np.ndarray) -> None:
        self.cv.update(self.innovation(measured), cov)
        self._fold()


class TranslationFilter:
    """Constant-velocity filter on the translation (camera frame, metres), two process-noise modes."""

    def __init__(self, translation: np.ndarray, cov: np.ndarray, still_sigma: float, accel_moving: float) -> None:
        x0 = np.concatenate([np.asarray(translation, dtype=np.float64), np.zeros(3)])
        p0 = np.block([[cov, np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3) * 0.5**2]])
        self.cv = _TwoModeCV(x0, p0, still_sigma, accel_moving)

    @property
    def translation(self) -> np.ndarray:
        return self.cv.x[:3].copy()

    def predict(self, dt: float) -> None:
        self.cv.predict(dt)

    def update(self, measured: np.ndarray, cov: np.ndarray) -> None:
        self.cv.update(measured, cov)


# ---------------------------------------------------------------------------- the track


@dataclass(frozen=True)
class TrackEvent:
    """Something a user may want to see on the timeline: a start, commit, switch, uncommit, re-acquisition, reset."""

    kind: str
    message: str


@dataclass(frozen=True)
class TrackUpdate:
    """The track's answer for one frame."""

    state: str  # tracked | ambiguous | predicted
    pose: Pose
    branch: int  # the output branch (0 or 1)
    committed: bool
    evidence: float  # confidence bound of the window's mean error difference, in px (+: branch 0)
    hypotheses: tuple[Pose | None, Pose | None]  # this frame's measurement on each branch
    events: tuple[TrackEvent, ...] = ()


def tilt_of(pose: Pose) -> np.ndarray:
    """The target normal's tilt away from the line of sight, as 2 components (sines).

    The two IPPE solutions of a square are mirror images through the line of sight to the marker:
    their tilts are opposite (``tilt_of(A) ~ -tilt_of(B)``). Tracking the tilt of one branch tells
    which solution is which, even where they cross (tilt near zero: a fronto-parallel view).
    """
    sx, sy, sz = pose.tvec / math.sqrt(float(pose.tvec @ pose.tvec))
    normal = pose.rotation[:, 2]
    # e1 = sight x reference (reference: y, or x when the sight is near y), e2 = sight x e1
    e1 = np.array([-sz, 0.0, sx]) if abs(sy) < 0.9 else np.array([0.0, sz, -sy])
    e1 /= math.sqrt(float(e1 @ e1))
    e2 = np.array([sy * e1[2] - sz * e1[1], sz * e1[0] - sx * e1[2], sx * e1[1] - sy * e1[0]])
    return np.array([normal @ e1, normal @ e2])


class _TiltTracker:
    """Constant-velocity Kalman filter on branch 0's tilt (2D), used only to tell the branches apart.

    Each frame offers a mirror pair of tilts; branch 0 takes the one nearer the prediction, so a view
    through fronto-parallel (the solutions cross) keeps each branch on its own side: the rate carries
    it through. The filter can never go blind: a frame whose choice is unclear (the two candidates about
    equally near) still updates it, with the measurement noise inflated by that unclarity; the rate is
    bounded and the uncertainty capped, so after a dropout or a run of noisy frames it is back at once.
    """

    _MAX_RATE = 4.0  # tilt (sine) per second: a quarter-turn in about 0.25 s
    _MAX_SIGMA = 0.5  # cap on the tilt's standard deviation (sine units)

    def __init__(self, tilt: np.ndarray, sigma: float, accel: float) -> None:
        self.kf = _KalmanFilter(dim_x=4, dim_z=2)
        self.kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
        self.accel = accel
        self.blind_s = 0.0  # how long the choice has been unclear
        self._dt: float | None = None
        self.reset(tilt, sigma)

    def reset(self, tilt: np.ndarray, sigma: float) -> None:
        """Start again at ``tilt`` at rest (after a long gap the old rate means nothing)."""
        self.kf.x = np.concatenate([tilt, np.zeros(2)]).reshape(4, 1)
        self.kf.P = np.diag([sigma**2, sigma**2, 1.0, 1.0])
        self.blind_s = 0.0

    @property
    def tilt(self) -> np.ndarray:
        return self.kf.x[:2, 0].copy()

    def predict(self, dt: float) -> None:
        if dt != self._dt:  # state [tilt_x, tilt_y, rate_x, rate_y]
            self._dt = dt
            self._f = np.eye(4)
            self._f[0, 2] = self._f[1, 3] = dt
            self._q = np.kron(self.accel**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), np.eye(2))
        self.kf.predict(F=self._f, Q=self._q)
        self._bound()

    def _bound(self) -> None:
        rate = self.kf.x[2:, 0]
        speed = float(np.linalg.norm(rate))
        if speed > self._MAX_RATE:
            self.kf.x[2:, 0] = rate * (self._MAX_RATE / speed)
        block = self.kf.P[:2, :2]
        largest = float(np.max(np.linalg.eigvalsh(block)))
        if largest > self._MAX_SIGMA**2:
            self.kf.P[:2, :] *= math.sqrt(self._MAX_SIGMA**2 / largest)
            self.kf.P[:, :2] *= math.sqrt(self._MAX_SIGMA**2 / largest)

    def choose(self, first: np.ndarray, second: np.ndarray | None, sigma: float, dt: float) -> tuple[bool, bool]:
        """Is ``first`` (rather than ``second``, by default its mirror) branch 0's tilt, and is that clear?

        The pair is matched as a whole: branch 0 near the prediction and branch 1 near its mirror. Always
        updates (an unclear choice with its noise inflated by the unclarity)."""
        predicted = self.tilt
        second = -first if second is None else second
        straight = float(np.linalg.norm(first - predicted) + np.linalg.norm(second + predicted))
        swapped = float(np.linalg.norm(second - predicted) + np.linalg.norm(first + predicted))
        spread = math.sqrt(float(np.trace(self.kf.P[:2, :2])) + 2 * sigma**2)
        is_branch0 = straight <= swapped
        clear = 0.5 * abs(straight - swapped) > spread
        self.blind_s = 0.0 if clear else self.blind_s + dt
        noise = sigma**2 if clear else sigma**2 + spread**2
        self.kf.update((first if is_branch0 else second).reshape(2, 1), R=np.eye(2) * noise)
        self._bound()
        return is_branch0, clear


@dataclass
class _Branch:
    """One IPPE solution's history: its smoother and its last measurement."""

    smoother: RotationFilter
    last: np.ndarray  # rotation of the last measurement assigned to this branch


class TargetTrack:
    """The filter state of one target (see the module doc)."""

    _RECENT_S = 0.3  # the best guess of an undecided target leans on this much recent evidence
    _STILL_CHI2 = 16.0  # still: each difference within this squared Mahalanobis distance (chi2, 3 dof: 99.9 %)
    _OUTLIER_RATIO = 2.5  # a frame with this many times the usual residual is not vouched for ...
    _OUTLIER_MIN_PX = 0.15  # ... if that residual is above this (below it, a fit is good by any standard)

    def __init__(self, config: FilterConfig, points_in_target: np.ndarray) -> None:
        self.config = config
        self.points = np.asarray(points_in_target, dtype=np.float64)
        self.branches: list[_Branch | None] | None = None  # None: no track
        self.tilts: _TiltTracker | None = None
        self.output_branch = 0
        self.committed: int | None = None
        self.evidence: collections.deque[tuple[int, float]] = collections.deque()  # (timestamp_ns, px)
        self.translation_filter: TranslationFilter | None = None
        self.last_ns: int | None = None  # the last frame seen (measured or not)
        self._period_s: float | None = None  # the frame interval (the shortest recent one, smoothed)
        self.measured_ns: int | None = None  # the last frame measured
        self.sigma_px = config.corner_noise_px
        self._frame_sigma = config.corner_noise_px
        self.against = 0.0  # contradicting frames in a row (a decisive one counts 1, a leaning one 1/3)
        self.run = 0  # ... and how many frames that run has: from its second, the output is the frame's pick
        self.doubtful = False  # this frame's assignment of solutions to branches is in doubt
        self.unclear = False  # ... or the tilt could not tell the (far apart) solutions apart this frame
        self._separation_deg = math.inf  # this frame's angle between its two solutions
        self.unconfirmed = False  # re-acquired after a gap, no frame has confirmed the commitment yet
        self.outlier = False  # this frame's residual is far above the track's usual one
        self._leaning = False  # an undecided target's frame or recent evidence chose its output branch
        self._held_spike = False  # the last frame's output jump was held back (see _spike)
        self._was_tracked = False  # the last measured frame's state was tracked
        self._usual_px: float | None = None
        self.frames = 0
        self._output: Pose | None = None  # the last published measured output
        self._velocity: tuple[np.ndarray, np.ndarray] = (np.zeros(3), np.zeros(3))  # omega (body), v (camera)
        self._was_still = False  # the output branch's measurements stayed put for still_s (see _still)
        self._settled_deg = math.inf  # ... turning this much over it
        self._rates: collections.deque[tuple[int, float]] = collections.deque()  # (ns, rad/s) over still_s
        self._rate = math.inf  # last measured rate of change (turn + shift / distance), rad/s
        self._history: collections.deque[tuple[int, int, Pose]] = collections.deque()  # (branch, ns, measured)
        self._covariances: dict[int, tuple[Pose, tuple[np.ndarray, np.ndarray]]] = {}  # this frame's, by pose

    def _covariance(self, pose: Pose, camera: CameraModel, sigma_px: float | None = None) -> tuple[np.ndarray, ...]:
        """:func:`pose_covariance` of one of this frame's poses (each is asked for several times)."""
        cached = self._covariances.get(id(pose))
        if cached is None or cached[0] is not pose:
            sigma = self._frame_sigma if sigma_px is None else sigma_px
            cached = self._covariances[id(pose)] = (pose, pose_covariance(pose, self.points, camera, sigma))
        return cached[1]

    @property
    def alive(self) -> bool:
        return self.branches is not None

    # ------------------------------------------------------------------ evidence
    def _window(self, since_ns: int) -> np.ndarray:
        return np.fromiter((v for t, v in self.evidence if t >= since_ns), dtype=np.float64)

    def _evidence_bound(self, margin: float, z: float) -> float:
        """Lower confidence bound of |mean difference| above ``margin``, signed (+ favours branch 0)."""
        if not self.evidence:
            return 0.0
        values = np.fromiter((v for _, v in self.evidence), dtype=np.float64)
        mean = float(values.mean())
        # per-frame spread, shrunk toward the configured floor as if it were a few frames of prior data:
        # one or two frames cannot claim to be precise, thirty consistent ones can
        prior = 5.0
        squares = float(np.sum((values - mean) ** 2)) + prior * self.config.evidence_noise_px**2
        spread = math.sqrt(squares / (values.size - 1 + prior))
        stderr = spread / math.sqrt(values.size)
        bound = abs(mean) - z * stderr - margin
        return math.copysign(bound, mean) if bound > 0 else 0.0

    def _margin_scale(self) -> float:
        return margin_scale(len(self.points))

    def _decide(self, events: list[TrackEvent]) -> None:
        cfg = self.config
        if self.committed is None:
            bound = self._evidence_bound(cfg.decide_margin_px * self._margin_scale(), cfg.decide_z)
            if bound != 0.0:
                self.committed = 0 if bound > 0 else 1
                events.append(
                    TrackEvent(
                        "commit",
                        f"committed to branch {self.committed} after {self.frames} "
                        f"frame(s) (evidence {bound:+.3f} px beyond the margin)",
                    )
                )
        else:
            bound = self._evidence_bound(cfg.switch_margin_px * self._margin_scale(), cfg.switch_z)
            favoured = None if bound == 0.0 else (0 if bound > 0 else 1)
            if favoured is not None and favoured != self.committed:
                self._switch(favoured, f"on sustained evidence ({bound:+.3f} px)", events)

    def _switch(self, branch: int, why: str, events: list[TrackEvent]) -> None:
        events.append(TrackEvent("switch", f"switched from branch {self.committed} to {branch} {why}"))
        self.committed = branch
        latest = self.evidence[-1] if self.evidence else None
        self.evidence.clear()
        if latest is not None:
            self.evidence.append(latest)
        self.against = 0
        self.run = 0

    def _verdict(self, assigned: list[PoseHypothesis | None]) -> tuple[int | None, int | None]:
        """What this frame alone says: the branch it vouches for (the only solution, or the one the other
        reprojects ``decisive_ratio`` times and ``decisive_sigmas`` corner-noise standard deviations, at
        least ``decisive_px``, worse), and the branch it leans to (the other reprojects twice as badly and
        worse by more than the decision margin). Either is None when the frame says nothing."""
        cfg = self.config
        if assigned[0] is None or assigned[1] is None:
            only = None if assigned[0] is None and assigned[1] is None else (0 if assigned[0] is not None else 1)
            return only, only
        low, high = sorted((0, 1), key=lambda i: assigned[i].reproj_px)  # type: ignore[union-attr]
        better, worse = assigned[low].reproj_px, assigned[high].reproj_px  # type: ignore[union-attr]
        strong = low if decisive(better, worse, cfg, self._frame_sigma, self._margin_scale()) else None
        lean = low if worse - better > cfg.decide_margin_px * self._margin_scale() and worse >= 2.0 * better else None
        return strong, lean

    def _best_guess(self, decisive: int | None) -> int:
        """While undecided: this frame's decisive solution if there is one, else the branch the recent
        evidence leans to (by more than half the decision margin), else the branch the whole window's
        evidence favours however slightly (on far, undecidable markers the per-frame pick is right more
        often than not, and the window's mean more often still), else the current output branch."""
        self._leaning = True
        if decisive is not None:
            return decisive
        assert self.last_ns is not None
        recent = self._window(self.last_ns - int(self._RECENT_S * 1e9))
        if recent.size:
            mean = float(recent.mean())
            if abs(mean) > 0.5 * self.config.decide_margin_px * self._margin_scale():
                return 0 if mean > 0 else 1
        self._leaning = False
        if self.evidence:  # too little to decide on is still more than one frame's pick
            mean = float(np.mean([v for _, v in self.evidence]))
            if mean != 0.0:
                return 0 if mean > 0 else 1
        return self.output_branch

    # ------------------------------------------------------------------ per frame
    def update(
        self,
        measurement: MarkerPose | BoardPose | None,
        timestamp_ns: int,
        camera: CameraModel,
        *,
        blurred: bool = False,
    ) -> TrackUpdate | None:
        """Advance to ``timestamp_ns`` with this frame's measurement (None: not seen). ``blurred``: the
        whole frame is much less sharp than usual (the camera moved fast): a measurement in it is not
        vouched for, and a target lost in it is not predicted (its motion is unknown).

        Returns None when there is nothing to publish: no track, a gap too long to predict through
        (the track stays :attr:`alive`, keeping its flip memory, until ``memory_s``), or a reset.
        """
        if self.last_ns is not None and timestamp_ns <= self.last_ns:
            timestamp_ns = self.last_ns + 1  # a repeated or backward timestamp: no time has passed
        elif self.last_ns is not None:  # the frame interval (a slow frame rate is not a gap)
            step = (timestamp_ns - self.last_ns) * 1e-9
            self._period_s = step if self._period_s is None else min(step, 0.8 * self._period_s + 0.2 * step)
        self.last_ns = timestamp_ns
        events: list[TrackEvent] = []
        self._covariances.clear()
        if measurement is None:
            return self._coast(timestamp_ns, events, blurred)
        self.points = np.asarray(measurement.points_in_target, dtype=np.float64)
        self._update_noise(measurement)
        gap_s = math.inf if self.measured_ns is None else (timestamp_ns - self.measured_ns) * 1e-9
        self.measured_ns = timestamp_ns
        self.frames += 1
        self.doubtful = self.unclear = False
        hypotheses = measurement.hypotheses  # how far apart the two solutions are, asked for several times
        self._separation_deg = (
            angle_between_deg(hypotheses[0].pose.rotation, hypotheses[1].pose.rotation)
            if len(hypotheses) == 2
            else math.inf
        )
        restart_frame = self.branches is None or self._is_gap(gap_s)
        if self.branches is None:
            assigned = self._start(measurement, camera)
            events.append(TrackEvent("start", "track started"))
        else:
            restart = self._is_gap(gap_s)
            if restart:
                events.append(TrackEvent("reacquired", f"seen again after {gap_s:.2f} s"))
                self.unconfirmed = True  # which solution is which was carried over the gap: the frame's
                # own pick is shown, and nothing vouched for, until a frame leans the committed way
            assigned = self._associate(measurement, camera, gap_s, restart, events)
            self._update_branches(assigned, camera, gap_s, restart)
            self._update_translation(measurement, camera, gap_s, restart)
        if not self.doubtful:
            self._add_evidence(assigned, timestamp_ns)
        self._decide(events)
        decided, lean = self._verdict(assigned)
        if self.committed is not None:
            # Self-correcting: a run of frames that contradict the commitment moves it after
            # ``decisive_frames`` (a decisive frame counts one, a leaning one a third). The output is the
            # frame's lower-error solution from a decisive frame or the run's second frame on (on hand-held
            # clips with truth such frames are right far more often than the commitment), and nothing is
            # vouched for while the run is open.
            favoured = decided if decided is not None else lean
            if favoured == self.committed:
                self.against = 0
                self.run = 0
                self.unconfirmed = False
            elif favoured is not None:
                self.against += 1.0 if decided is not None else 1.0 / 3.0  # a leaning frame counts a third
                self.run += 1
                if self.against >= self.config.decisive_frames - 1e-9:
                    self._switch(favoured, "on contradicting frames", events)
        if self.committed is None:
            target = self._best_guess(decided)
        elif (self.run >= 2 or (self.run and decided is not None) or self.doubtful or self.unconfirmed) and (
            None not in assigned
        ):
            target = 0 if assigned[0].reproj_px <= assigned[1].reproj_px else 1
        else:
            target = self.committed
        if assigned[target] is None and assigned[1 - target] is not None:
            target = 1 - target  # the only solution this frame (the other failed validation) is shown
        moved_branch = False
        if target != self.output_branch and self.branches is not None and self.branches[target] is not None:
            moved_branch = True
            events.append(
                TrackEvent(
                    "branch",
                    f"output moves to branch {target}" + ("" if self.committed is not None else " (best guess)"),
                )
            )
            self.output_branch = target
        pose, covariance = self._measured_output(assigned, camera)
        spike = not moved_branch and not restart_frame and self._spike(pose)
        if spike:
            events.append(TrackEvent("spike", "orientation jump in place held for one frame"))
            assert self._output is not None
            pose = Pose.from_matrix(self._output.rotation, pose.tvec)
        vouched = (
            not spike
            and self.committed is not None
            and self.committed == self.output_branch
            and assigned[self.output_branch] is not None
            and decided in (None, self.output_branch)
            and self.against == 0
            and not self.doubtful
            and not (self.unclear and decided is None)
            and not self._close_call(assigned)
            and not self.unconfirmed
            and not self.outlier
            and not blurred
            and self._raw_pick(assigned) in (None, self.output_branch)
            and not self._too_uncertain(covariance)
        )
        hypotheses = (
            assigned[0].pose if assigned[0] is not None else None,
            assigned[1].pose if assigned[1] is not None else None,
        )
        self._was_tracked = vouched
        update = self._result("tracked" if vouched else "ambiguous", pose, hypotheses, events)
        self._output = pose
        return update

    def _is_gap(self, gap_s: float) -> bool:
        """Were frames missed for longer than ``restart_gap_s``? (At 5 fps every frame is 0.2 s after the
        last one: that is the frame rate, not a gap; a gap is more than one and a half frame intervals.)"""
        period = self._period_s or 0.0
        return gap_s > self.config.restart_gap_s and gap_s > 1.5 * period

    def _start(self, measurement: MarkerPose | BoardPose, camera: CameraModel) -> list[PoseHypothesis | None]:
        cfg = self.config
        hypotheses = measurement.hypotheses
        self.branches = [self._new_branch(h.pose, camera) for h in hypotheses]
        if len(self.branches) == 1:
            self.branches.append(None)  # the other solution failed validation: unknown until it shows up
        self.tilts = _TiltTracker(
            tilt_of(hypotheses[0].pose), self._tilt_sigma(hypotheses[0].pose, camera), cfg.tilt_accel_rad_s2
        )
        self.output_branch = 0
        self.committed = None
        self.evidence.clear()
        self.against = 0
        self.run = 0
        best = hypotheses[0].pose
        _, cov_t = self._covariance(best, camera)
        self.translation_filter = TranslationFilter(
            best.tvec, cov_t, cfg.still_translation_m_sqrt_s, cfg.linear_accel_moving_m_s2
        )
        return [hypotheses[0], hypotheses[1] if len(hypotheses) > 1 else None]

    def _new_branch(self, pose: Pose, camera: CameraModel) -> _Branch:
        cov_rot, _ = self._covariance(pose, camera)
        smoother = RotationFilter(
            pose.rotation, cov_rot, self.config.still_rotation_rad_sqrt_s, self.config.angular_accel_moving_rad_s2
        )
        return _Branch(smoother, pose.rotation)

    def _tilt_sigma(self, pose: Pose, camera: CameraModel) -> float:
        cov_rot, _ = self._covariance(pose, camera)
        return math.sqrt(float(np.max(np.linalg.eigvalsh(cov_rot))))

    def _associate(
        self,
        measurement: MarkerPose | BoardPose,
        camera: CameraModel,
        gap_s: float,
        restart: bool,
        events: list[TrackEvent],
    ) -> list[PoseHypothesis | None]:
        """Assign this frame's solutions to the branches: branch 0 is the one whose tilt continues the
        tilt tracker's prediction (see :class:`_TiltTracker`); after a long gap, the one nearer branch 0's
        last tilt (the tracker restarts at rest)."""
        assert self.branches is not None and self.tilts is not None
        hypotheses = measurement.hypotheses
        first = hypotheses[0]
        sigma = self._tilt_sigma(first.pose, camera)
        if restart:  # branch 0's last measured orientation, seen from where the target is now
            assert self.branches[0] is not None  # (a track starts with its lower-error solution on branch 0)
            self.tilts.reset(tilt_of(Pose.from_matrix(self.branches[0].last, first.pose.tvec)), sigma)
        else:
            self.tilts.predict(gap_s)
        second = tilt_of(hypotheses[1].pose) if len(hypotheses) > 1 else None
        is_branch0, clear = self.tilts.choose(tilt_of(first.pose), second, sigma, 0.0 if restart else gap_s)
        apart = len(hypotheses) == 2 and self._separation_deg > self.config.flip_angle_deg
        self.unclear = not clear and apart
        assigned: list[PoseHypothesis | None] = [None, None]
        if len(hypotheses) == 1:
            assigned[0 if is_branch0 else 1] = first
        else:
            assigned = [hypotheses[0], hypotheses[1]] if is_branch0 else [hypotheses[1], hypotheses[0]]
        self.doubtful = len(hypotheses) == 2 and not restart and self._motion_disagrees(assigned, gap_s)
        for index, hypothesis in enumerate(assigned):  # a solution shows up for the first time: its branch starts
            if self.branches[index] is None and hypothesis is not None:
                self.branches[index] = self._new_branch(hypothesis.pose, camera)
        # Unclear for long while the solutions are far apart: which is which may have been lost. (While they
        # are within flip_angle_deg of each other either one is close enough, so unclarity costs nothing.)
        if apart and self.tilts.blind_s > self.config.crossing_blind_s and self.committed is not None:
            events.append(
                TrackEvent(
                    "uncommit",
                    f"the two solutions stayed indistinguishable for {self.tilts.blind_s:.2f} s: "
                    "which is which is undecided again",
                )
            )
            self.committed = None
            self.evidence.clear()
            self.against = 0
            self.run = 0
        return assigned

    @staticmethod
    def _raw_pick(assigned: list[PoseHypothesis | None]) -> int | None:
        """The branch of this frame's lower-error solution (None with fewer than two)."""
        if assigned[0] is None or assigned[1] is None:
            return None
        return 0 if assigned[0].reproj_px <= assigned[1].reproj_px else 1

    def _motion_disagrees(self, assigned: list[PoseHypothesis | None], gap_s: float) -> bool:
        """A second opinion on the assignment: each branch's smoother, turned on at its angular velocity,
        should be nearer its own solution than the other's. Where the tilt's continuity and the
        rotation's disagree (fast motion through a crossing), which is which is not known this frame."""
        assert self.branches is not None
        if any(b is None for b in self.branches) or any(h is None for h in assigned):
            return False
        predicted = [b.smoother.rotation @ so3_exp(b.smoother.omega * gap_s) for b in self.branches]  # type: ignore[union-attr]
        rotations = [h.pose.rotation for h in assigned]  # type: ignore[union-attr]
        straight = angle_between_deg(predicted[0], rotations[0]) + angle_between_deg(predicted[1], rotations[1])
        swapped = angle_between_deg(predicted[0], rotations[1]) + angle_between_deg(predicted[1], rotations[0])
        return swapped + self.config.flip_angle_deg < straight

    def _add_evidence(self, assigned: list[PoseHypothesis | None], timestamp_ns: int) -> None:
        cfg = self.config
        if assigned[0] is None or assigned[1] is None:
            value = cfg.single_solution_evidence_px * (1 if assigned[0] is not None else -1)
        else:
            difference = assigned[1].reproj_px - assigned[0].reproj_px
            value = float(np.clip(difference, -cfg.evidence_cap_px, cfg.evidence_cap_px))
        self.evidence.append((timestamp_ns, value))
        oldest = timestamp_ns - int(cfg.evidence_window_s * 1e9)
        while self.evidence and self.evidence[0][0] < oldest:
            self.evidence.popleft()

    def _update_noise(self, measurement: MarkerPose | BoardPose) -> None:
        """The corner noise: a slow estimate from the residuals, and this frame's own (a blurred frame's
        residuals are larger): its measurement is trusted by the larger of the two. A frame whose residual
        is ``_OUTLIER_RATIO`` times the track's usual one and above ``_OUTLIER_MIN_PX`` (motion blur,
        rolling shutter, a partly hidden marker) may be off by more than its noise says: it is not
        vouched for."""
        estimate = measurement.best.reproj_px * _RESIDUAL_TO_SIGMA
        usual = self._usual_px
        self.outlier = (
            usual is not None
            and estimate > self._OUTLIER_RATIO * max(usual, self.config.corner_noise_px)
            and measurement.best.reproj_px > self._OUTLIER_MIN_PX
        )
        if not self.outlier:  # the usual residual, slowly, from the frames that are not outliers
            self._usual_px = estimate if usual is None else 0.95 * usual + 0.05 * estimate
        self.sigma_px = max(self.config.corner_noise_px, 0.9 * self.sigma_px + 0.1 * estimate)
        self._frame_sigma = max(self.sigma_px, estimate)

    def _update_branches(
        self, assigned: list[PoseHypothesis | None], camera: CameraModel, gap_s: float, restart: bool
    ) -> None:
        """Each branch's smoother takes its measurement. A measurement is never rejected: a smoother
        that finds it implausibly far (``reset_angle_deg``), or that has not seen its branch for longer
        than ``restart_gap_s``, restarts from it."""
        cfg = self.config
        assert self.branches is not None
        limit = math.radians(cfg.max_angular_rate_deg_s)
        for branch, hypothesis in zip(self.branches, assigned):
            if branch is None or hypothesis is None:
                continue
            pose = hypothesis.pose
            cov_rot, _ = self._covariance(pose, camera)
            smoother = branch.smoother
            if not restart:
                smoother.predict(gap_s)
            jump = float(np.degrees(np.linalg.norm(smoother.innovation(pose.rotation))))
            if restart or jump > cfg.reset_angle_deg:
                smoother.reset(pose.rotation, cov_rot)
            else:
                smoother.update(pose.rotation, cov_rot)
                omega = smoother.cv.xs[:, 3:]
                speed = np.linalg.norm(omega, axis=1)
                if np.any(speed > limit):  # bounded angular velocity, per motion model
                    smoother.cv.xs[:, 3:] = omega * np.minimum(1.0, limit / np.maximum(speed, 1e-12))[:, None]
                    smoother.cv._combine()
            branch.last = pose.rotation

    def _update_translation(
        self, measurement: MarkerPose | BoardPose, camera: CameraModel, gap_s: float, restart: bool
    ) -> None:
        assert self.translation_filter is not None
        pose = measurement.best.pose
        _, cov_t = self._covariance(pose, camera)
        if restart:
            self.translation_filter = TranslationFilter(
                pose.tvec, cov_t, self.config.still_translation_m_sqrt_s, self.config.linear_accel_moving_m_s2
            )
            return
        self.translation_filter.predict(gap_s)
        self.translation_filter.update(pose.tvec, cov_t)

    def _measured_output(
        self, assigned: list[PoseHypothesis | None], camera: CameraModel
    ) -> tuple[Pose, np.ndarray | None]:
        """The output pose of a measured frame: the output branch's smoothed pose, held within
        ``output_sigmas`` standard deviations (the measurement's own covariance) of this frame's
        measurement on that branch, so smoothing can lower jitter but never lag behind real motion
        by more than the noise. Returns the pose and the measurement's rotation covariance."""
        assert self.branches is not None and self.translation_filter is not None
        branch = self.branches[self.output_branch]
        assert branch is not None
        rotation, translation = branch.smoother.rotation, self.translation_filter.translation
        hypothesis = assigned[self.output_branch]
        covariance = None
        if hypothesis is not None:
            measured = hypothesis.pose
            cov_rot, cov_t = self._covariance(measured, camera)
            # a still target is averaged over many frames; a moving one follows its measurements closely
            still = self._was_still = self._still(measured, cov_rot, cov_t)
            k = self.config.output_sigmas if still and not self.outlier else self.config.output_sigmas_moving
            error = so3_log(measured.rotation.T @ rotation)  # body-frame error, as the covariance's
            rotation = measured.rotation @ so3_exp(_within(error, cov_rot, k))
            translation = measured.tvec + _within(translation - measured.tvec, cov_t, k)
            covariance = cov_rot
            other = self._undecided_other(assigned)
            if other is not None:
                rotation = _halfway(rotation, self._held(other, assigned, camera, k))
        omega = branch.smoother.omega
        velocity = self.translation_filter.cv.x[3:].copy()
        self._velocity = (omega, velocity)
        return Pose.from_matrix(rotation, translation), covariance

    def _spike(self, pose: Pose) -> bool:
        """Is this output an orientation jump in place: more than ``flip_angle_deg`` from the last
        frame's output on the same branch while the position moved less than ``spike_translation_m``
        (no hand turns a marker that fast about its own centre: a measurement that jumped, from blur or
        a bad corner)? Such an output is held back for one frame, never two: if the next frame keeps
        the new orientation, it is taken."""
        previous, held = self._output, self._held_spike
        self._held_spike = False
        if previous is None or held:
            return False
        jumped = angle_between_deg(previous.rotation, pose.rotation) > self.config.flip_angle_deg
        in_place = float(np.linalg.norm(previous.tvec - pose.tvec)) < self.config.spike_translation_m
        self._held_spike = jumped and in_place
        return self._held_spike

    def _close_call(self, assigned: list[PoseHypothesis | None]) -> bool:
        """Are the two solutions within twice ``flip_angle_deg`` of each other while this frame barely
        tells them apart (their errors differ by less than the decision margin)? Then noise alone can
        carry the pose past a flip's worth: not vouched for, however sure the commitment."""
        if None in assigned:
            return False
        a, b = assigned  # type: ignore[misc]
        margin = self.config.decide_margin_px * self._margin_scale()
        return abs(a.reproj_px - b.reproj_px) < margin and self._separation_deg <= 2.0 * self.config.flip_angle_deg

    def _undecided_other(self, assigned: list[PoseHypothesis | None]) -> int | None:
        """The other branch, when this uncommitted frame's output should be halfway between the two:
        nothing in this frame or the recent evidence chooses (no decisive or leaning frame), and the two
        solutions are within twice ``flip_angle_deg`` of each other, so halfway is within a flip's
        worth of the truth whichever is right (a fronto-parallel marker: the steady, unbiased answer)."""
        if self.committed is not None or None in assigned or self.branches is None or None in self.branches:
            return None
        if self._leaning:
            return None
        if self._separation_deg > 2.0 * self.config.flip_angle_deg:
            return None
        return 1 - self.output_branch

    def _held(self, index: int, assigned: list[PoseHypothesis | None], camera: CameraModel, k: float) -> np.ndarray:
        """Branch ``index``'s smoothed rotation held within ``k`` sigma of its measurement this frame."""
        branch, hypothesis = self.branches[index], assigned[index]  # type: ignore[index]
        assert branch is not None and hypothesis is not None
        cov_rot, _ = self._covariance(hypothesis.pose, camera)
        error = so3_log(hypothesis.pose.rotation.T @ branch.smoother.rotation)
        return hypothesis.pose.rotation @ so3_exp(_within(error, cov_rot, k))

    def _still(self, measured: Pose, cov_rot: np.ndarray, cov_t: np.ndarray) -> bool:
        """Has the output branch's measurement stayed put, within its noise, for ``still_s``? (The
        difference of two measurements has twice a measurement's covariance; ``_STILL_CHI2``.)"""
        assert self.measured_ns is not None
        history = self._history
        if history and history[0][0] != self.output_branch:
            history.clear()
        if history:  # how fast it moved since the last measurement (what a prediction may miss), rad/s
            _, last_ns, last = history[-1]
            dt = max((self.measured_ns - last_ns) * 1e-9, 1e-3)
            turn = float(np.linalg.norm(so3_log(last.rotation.T @ measured.rotation)))
            shift = float(np.linalg.norm(measured.tvec - last.tvec)) / max(float(np.linalg.norm(measured.tvec)), 1e-6)
            self._rates.append((self.measured_ns, (turn + shift) / dt))
        horizon = self.measured_ns - int(self.config.still_s * 1e9)
        while self._rates and self._rates[0][0] < horizon:
            self._rates.popleft()
        # the fastest over the last still_s: one slow step (a repeated frame) says little
        self._rate = max((rate for _, rate in self._rates), default=math.inf)
        history.append((self.output_branch, self.measured_ns, measured))
        while len(history) > 1 and history[1][1] <= horizon:
            history.popleft()
        _, then_ns, then = history[0]
        if then_ns > horizon:
            return False  # not seen long enough to tell
        turned = so3_log(then.rotation.T @ measured.rotation)
        moved = measured.tvec - then.tvec
        shift = float(np.linalg.norm(moved)) / max(float(np.linalg.norm(measured.tvec)), 1e-6)
        self._settled_deg = math.degrees(float(np.linalg.norm(turned)) + shift)  # turn + shift seen from the camera
        return bool(
            turned @ np.linalg.solve(2.0 * cov_rot, turned) < self._STILL_CHI2
            and moved @ np.linalg.solve(2.0 * cov_t, moved) < self._STILL_CHI2
        )

    def _coast(self, timestamp_ns: int, events: list[TrackEvent], blurred: bool = False) -> TrackUpdate | None:
        """A frame without a measurement: a short prediction (velocity decaying with
        ``predict_damping_s``) for up to ``predict_s``; then nothing is published, but the track keeps
        its branches and evidence until ``memory_s``, so a target that returns is not a new track."""
        if self.branches is None or self.measured_ns is None:
            return None
        cfg = self.config
        gap_s = (timestamp_ns - self.measured_ns) * 1e-9
        if gap_s > cfg.memory_s:
            self.branches = None
            events.append(TrackEvent("reset", f"lost for more than {cfg.memory_s:g} s: reset"))
            return None
        if gap_s > cfg.predict_s or self._output is None or blurred or not self._was_tracked:
            return None  # (an undecided target is not predicted: which pose to continue is not known)
        tau = cfg.predict_damping_s
        reach = tau * (1.0 - math.exp(-gap_s / tau))  # integral of exp(-t / tau) over the gap
        omega, velocity = self._velocity
        settled = self._was_still and self._settled_deg <= cfg.predict_max_deg
        if not settled and math.degrees(self._prediction_doubt(omega, gap_s, reach)) > cfg.predict_max_deg:
            return None  # not trustworthy: publish nothing rather than a guess
        rotation = self._output.rotation @ so3_exp(omega * reach)
        pose = Pose.from_matrix(rotation, self._output.tvec + velocity * reach)
        return self._result("predicted", pose, (None, None), events)

    def _prediction_doubt(self, omega: np.ndarray, gap_s: float, reach_s: float) -> float:
        """How much more a prediction over ``gap_s`` may be off than the last measured output (radians):
        the turn the damping leaves out if the motion went on or, if larger, the turn plus the shift (as an
        angle seen from the camera) at the rate last measured."""
        return max(float(np.linalg.norm(omega)) * (gap_s - reach_s), self._rate * gap_s)

    def _too_uncertain(self, covariance: np.ndarray | None) -> bool:
        """3 sigma of the measured orientation beyond flip_angle_deg: even the right branch may be off
        by a flip's worth."""
        if covariance is None:
            return True
        sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(covariance))), 0.0))
        return math.degrees(3.0 * sigma) > self.config.flip_angle_deg

    def _result(
        self, state: str, pose: Pose, hypotheses: tuple[Pose | None, Pose | None], events: list[TrackEvent]
    ) -> TrackUpdate:
        return TrackUpdate(
            state,
            pose,
            self.output_branch,
            self.committed is not None,
            self._evidence_bound(0.0, 0.0),
            hypotheses,
            tuple(events),
        )


def margin_scale(points: int) -> float:
    """The decision margins are set for one marker's four corners. A board's error difference is an RMS
    over more points, whose detector biases (independent from marker to marker) partly cancel: its
    margin shrinks with the square root of the number of points (four per marker)."""
    return min(1.0, math.sqrt(4.0 / max(points, 4)))


def decisive(better_px: float, worse_px: float, config: FilterConfig, sigma_px: float, scale: float = 1.0) -> bool:
    """Does one frame alone decide between two solutions with these RMS reprojection errors: the worse
    one ``decisive_ratio`` times the better's and worse by ``decisive_sigmas`` corner-noise standard
    deviations ``sigma_px``, and at least by ``decisive_px`` (times ``scale``: a board's margin shrinks
    with its number of points)?"""
    floor = max(config.decisive_px * scale, config.decisive_sigmas * sigma_px)
    return worse_px - better_px >= floor and worse_px >= config.decisive_ratio * better_px


def _halfway(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation halfway between ``a`` and ``b`` on the geodesic."""
    return a @ so3_exp(0.5 * so3_log(a.T @ b))


def _within(error: np.ndarray, covariance: np.ndarray, sigmas: float) -> np.ndarray:
    """``error`` shrunk (along itself) to at most ``sigmas`` Mahalanobis distance under ``covariance``."""
    try:
        distance = math.sqrt(max(float(error @ np.linalg.solve(covariance, error)), 0.0))
    except np.linalg.LinAlgError:
        return np.zeros_like(error)
    if distance <= sigmas or distance == 0.0:
        return error
    return error * (sigmas / distance)
