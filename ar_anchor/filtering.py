"""Temporal filtering: resolve the planar flip with evidence over time, and smooth the pose.

Per target, a :class:`TargetTrack` carries

* **two branches**, one per IPPE solution. The two solutions of a square are mirror images through
  the line of sight (their normals' tilts away from it are opposite), so a small Kalman filter on
  branch 0's tilt (:class:`_TiltTracker`) tells which solution continues which branch, through
  crossings too (a view through fronto-parallel): where the noise hides which is which it coasts
  on its velocity instead of guessing.
* **evidence** for branch 0 against branch 1 over a window of frames: per frame, the difference of
  their RMS reprojection errors. A branch is *committed* (state ``tracked``) only when the window's
  mean difference exceeds ``decide_margin_px`` with ``decide_z`` standard errors of confidence. The
  margin is there because a corner detector's own bias (a few hundredths of a pixel) differs
  systematically between the branches too: evidence below it never decides, however long one
  waits. Such a target stays ``ambiguous``, and its output holds a steady best guess. Once
  committed, a switch needs stronger, sustained evidence (``switch_margin_px``, ``switch_z``).
* a **smoother** per branch: an error-state Kalman filter on SO(3) (rotation error as a body-frame
  rotation vector, so no Euler angles and no trouble near 180 degrees) and, shared, one on
  translation, each an IMM (``filterpy``) of a *still* model that averages a static marker over many
  frames and a *moving* constant-velocity model that follows real motion without lag. Measurement
  noise is the pose covariance implied by the corner noise through the projection Jacobian: it grows
  with distance and shrinks with marker size in pixels; the corner noise is estimated online.
* **dropouts**: missed frames are predicted (state ``predicted``) for up to ``max_missed_frames``;
  a target that returns is associated to its branches by prediction, so it re-acquires without a flip.

A measured frame whose orientation jumps by more than ``flip_angle_deg`` while the position moves
less than ``flip_translation_m`` (plus its noise) is treated as a flip, not as motion, unless it
persists. While the position stays put the output turns at most ``max_output_step_deg`` per frame,
so even a correction slews instead of snapping. ``tracked`` is only said of the committed branch,
settled (not slewing), and with an orientation whose 3-sigma uncertainty is below a flip.
"""

from __future__ import annotations

import collections
import logging
import math
import sys
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from .camera import CameraModel
from .config import FilterConfig
from .geometry import Pose, angle_between_deg, matrix_from_rvec, rvec_from_matrix
from .pose import BoardPose, MarkerPose, PoseHypothesis

__all__ = [
    "RotationFilter",
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
    """Something a user may want to see on the timeline: a commit, a switch, a rejected flip, a reset."""

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

    Each frame offers a mirror pair of tilts; branch 0 takes the one nearer the prediction. When the
    two are about equally near (the solutions cross and the noise hides which is which) the filter
    coasts on its velocity instead of guessing, and the branches are re-identified once they part.
    """

    def __init__(self, tilt: np.ndarray, sigma: float, accel: float) -> None:
        self.kf = _KalmanFilter(dim_x=4, dim_z=2)
        self.kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
        self.kf.x = np.concatenate([tilt, np.zeros(2)]).reshape(4, 1)
        self.kf.P = np.diag([sigma**2, sigma**2, 1.0, 1.0])
        self.accel = accel
        self.blind = 0  # consecutive frames without a clear decision
        self._dt: float | None = None

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

    def choose(self, candidate: np.ndarray, sigma: float) -> tuple[bool, bool]:
        """Is ``candidate`` (rather than its mirror) branch 0's tilt, and is that clear? Updates when clear."""
        predicted = self.tilt
        near = float(np.linalg.norm(candidate - predicted))
        mirror = float(np.linalg.norm(-candidate - predicted))
        spread = math.sqrt(float(np.trace(self.kf.P[:2, :2])) + 2 * sigma**2)
        is_branch0 = near <= mirror
        clear = abs(near - mirror) > spread
        if clear:
            self.blind = 0
            self.kf.update((candidate if is_branch0 else -candidate).reshape(2, 1), R=np.eye(2) * sigma**2)
        else:
            self.blind += 1
        return is_branch0, clear


class TargetTrack:
    """The filter state of one target (see the module doc)."""

    def __init__(self, config: FilterConfig, points_in_target: np.ndarray) -> None:
        self.config = config
        self.points = np.asarray(points_in_target, dtype=np.float64)
        self.branches: list[RotationFilter | None] | None = None  # None: no track
        self.tilts: _TiltTracker | None = None
        self._pending_events: list[TrackEvent] = []
        self.doubtful = False
        self.output_branch = 0
        self.committed: int | None = None
        self.evidence: collections.deque[float] = collections.deque(maxlen=config.window)
        self.translation_filter: TranslationFilter | None = None
        self.last_ns: int | None = None
        self.missed = 0
        self.sigma_px = config.corner_noise_px
        self.output_rotation: np.ndarray | None = None
        self.output_translation: np.ndarray | None = None
        self.slewing = False
        self.pending_flip = 0
        self.frames = 0
        self._covariances: dict[int, tuple[Pose, tuple[np.ndarray, np.ndarray]]] = {}  # this frame's, by pose

    def _covariance(self, pose: Pose, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """:func:`pose_covariance` of one of this frame's poses (each is asked for up to three times)."""
        cached = self._covariances.get(id(pose))
        if cached is None or cached[0] is not pose:
            cached = self._covariances[id(pose)] = (pose, pose_covariance(pose, self.points, camera, self.sigma_px))
        return cached[1]

    @property
    def alive(self) -> bool:
        return self.branches is not None

    # ------------------------------------------------------------------ evidence
    def _evidence_bound(self, margin: float, z: float) -> float:
        """Lower confidence bound of |mean difference| above ``margin``, signed (+ favours branch 0)."""
        if not self.evidence:
            return 0.0
        values = np.fromiter(self.evidence, dtype=np.float64)
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
        """The decision margins are set for one marker's four corners. A board's error difference is
        an RMS over more points, whose detector biases (independent from marker to marker) partly
        cancel: its margin shrinks with the square root of the number of points (four per marker)."""
        return min(1.0, math.sqrt(4.0 / max(len(self.points), 4)))

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
                events.append(
                    TrackEvent(
                        "switch",
                        f"switched from branch {self.committed} to {favoured} on sustained evidence ({bound:+.3f} px)",
                    )
                )
                self.committed = favoured
                self.evidence.clear()

    def _best_guess(self) -> int:
        """While ambiguous: keep the current output branch (a steady guess) unless the evidence leans the
        other way by half the decision margin with 2 standard errors: not enough to vouch for, enough to prefer."""
        bound = self._evidence_bound(0.5 * self.config.decide_margin_px * self._margin_scale(), 2.0)
        if bound == 0.0 or self.branches is None or self.branches[0 if bound > 0 else 1] is None:
            return self.output_branch
        return 0 if bound > 0 else 1

    # ------------------------------------------------------------------ per frame
    def update(
        self, measurement: MarkerPose | BoardPose | None, timestamp_ns: int, camera: CameraModel
    ) -> TrackUpdate | None:
        """Advance to ``timestamp_ns`` with this frame's measurement (None: not seen)."""
        dt = (
            1.0 / 30.0 if self.last_ns is None or timestamp_ns <= self.last_ns else (timestamp_ns - self.last_ns) * 1e-9
        )
        self.last_ns = timestamp_ns
        events: list[TrackEvent] = []
        self._pending_events = events
        self.doubtful = False
        self._covariances.clear()
        if measurement is None:
            return self._coast(dt, events)
        # the correspondences of this frame (a board's visible markers change from frame to frame)
        self.points = np.asarray(measurement.points_in_target, dtype=np.float64)
        self._update_noise(measurement)
        if self.branches is None:
            hypotheses = self._start(measurement, camera)
            events.append(TrackEvent("start", "track started"))
        else:
            self.missed = 0
            self.frames += 1
            for branch in self.branches:
                if branch is not None:
                    branch.predict(dt)
            assert self.translation_filter is not None
            self.translation_filter.predict(dt)
            assigned = self._associate(measurement, camera, dt)
            self._add_evidence(assigned)
            self._update_branches(assigned, camera, events)
            self._update_translation(measurement, camera)
            hypotheses = tuple(h.pose if h is not None else None for h in assigned)
        self._decide(events)
        target = self.committed if self.committed is not None else self._best_guess()
        if target != self.output_branch and self.branches is not None and self.branches[target] is not None:
            events.append(
                TrackEvent(
                    "branch",
                    f"output moves to branch {target}" + ("" if self.committed is not None else " (best guess)"),
                )
            )
            self.output_branch = target
            self.slewing = True
        return self._result("tracked" if self.committed == self.output_branch else "ambiguous", hypotheses, events)

    def _start(self, measurement: MarkerPose, camera: CameraModel) -> tuple[Pose | None, Pose | None]:
        cfg = self.config
        hypotheses = measurement.hypotheses
        self.branches = [self._new_branch(h.pose, camera) for h in hypotheses]
        self.tilts = _TiltTracker(
            tilt_of(hypotheses[0].pose), self._tilt_sigma(hypotheses[0].pose, camera), cfg.tilt_accel_rad_s2
        )
        if len(self.branches) == 1:
            self.branches.append(None)  # the other solution failed validation: unknown until it shows up
        self.output_branch = 0
        self.committed = None
        self.evidence.clear()
        self.frames = 1
        self.missed = 0
        if len(hypotheses) == 1:
            self.evidence.append(cfg.single_solution_evidence_px)
        else:
            self.evidence.append(
                float(
                    np.clip(
                        hypotheses[1].reproj_px - hypotheses[0].reproj_px, -cfg.evidence_cap_px, cfg.evidence_cap_px
                    )
                )
            )
        best = hypotheses[0].pose
        _, cov_t = self._covariance(best, camera)
        self.translation_filter = TranslationFilter(
            best.tvec, cov_t, cfg.still_translation_m_sqrt_s, cfg.linear_accel_moving_m_s2
        )
        self.output_rotation = best.rotation
        self.slewing = False
        return (hypotheses[0].pose, hypotheses[1].pose if len(hypotheses) > 1 else None)

    def _new_branch(self, pose: Pose, camera: CameraModel) -> RotationFilter:
        cov_rot, _ = self._covariance(pose, camera)
        return RotationFilter(
            pose.rotation, cov_rot, self.config.still_rotation_rad_sqrt_s, self.config.angular_accel_moving_rad_s2
        )

    def _tilt_sigma(self, pose: Pose, camera: CameraModel) -> float:
        cov_rot, _ = self._covariance(pose, camera)
        return math.sqrt(float(np.max(np.linalg.eigvalsh(cov_rot))))

    def _associate(self, measurement: MarkerPose, camera: CameraModel, dt: float) -> list[PoseHypothesis | None]:
        """Assign this frame's solutions to the branches: branch 0 is the one whose tilt continues
        the tilt tracker's prediction (see :class:`_TiltTracker`)."""
        assert self.branches is not None and self.tilts is not None
        hypotheses = measurement.hypotheses
        self.tilts.predict(dt)
        first = hypotheses[0]
        is_branch0, clear = self.tilts.choose(tilt_of(first.pose), self._tilt_sigma(first.pose, camera))
        assigned: list[PoseHypothesis | None] = [None, None]
        if len(hypotheses) == 1:
            assigned[0 if is_branch0 else 1] = first
        else:
            assigned = [hypotheses[0], hypotheses[1]] if is_branch0 else [hypotheses[1], hypotheses[0]]
            missing = [i for i, b in enumerate(self.branches) if b is None]
            for index in missing:  # a second solution shows up for the first time: it starts its branch
                self.branches[index] = self._new_branch(assigned[index].pose, camera)
        # Blind for long while the solutions are far apart: which is which may have been lost. (While they
        # are within flip_angle_deg of each other either one is close enough, so blindness costs nothing.)
        apart = (
            len(hypotheses) == 2
            and angle_between_deg(hypotheses[0].pose.rotation, hypotheses[1].pose.rotation) > self.config.flip_angle_deg
        )
        if not clear and apart and self.tilts.blind > self.config.crossing_blind_frames and self.committed is not None:
            self._pending_events.append(
                TrackEvent(
                    "uncommit",
                    f"the two solutions stayed indistinguishable for {self.tilts.blind} frames: "
                    "which is which is undecided again",
                )
            )
            self.committed = None
            self.evidence.clear()
        return assigned

    def _add_evidence(self, assigned: list[PoseHypothesis | None]) -> None:
        cfg = self.config
        if assigned[0] is None or assigned[1] is None:
            self.evidence.append(cfg.single_solution_evidence_px * (1 if assigned[0] is not None else -1))
            return
        difference = assigned[1].reproj_px - assigned[0].reproj_px
        if cfg.motion_weight_px_per_deg > 0 and self.branches is not None and None not in self.branches:
            innovation = [
                float(np.degrees(np.linalg.norm(b.innovation(h.pose.rotation))))
                for b, h in zip(self.branches, assigned)
            ]  # type: ignore[union-attr]
            difference += cfg.motion_weight_px_per_deg * (innovation[1] - innovation[0])
        self.evidence.append(float(np.clip(difference, -cfg.evidence_cap_px, cfg.evidence_cap_px)))

    def _update_noise(self, measurement: MarkerPose) -> None:
        estimate = measurement.best.reproj_px * _RESIDUAL_TO_SIGMA
        self.sigma_px = max(self.config.corner_noise_px, 0.9 * self.sigma_px + 0.1 * estimate)

    def _update_branches(
        self, assigned: list[PoseHypothesis | None], camera: CameraModel, events: list[TrackEvent]
    ) -> None:
        cfg = self.config
        assert self.branches is not None
        for index, (branch, hypothesis) in enumerate(zip(self.branches, assigned)):
            if branch is None or hypothesis is None:
                continue  # coasts on its prediction
            pose = hypothesis.pose
            cov_rot, cov_t = self._covariance(pose, camera)
            jump = float(np.degrees(np.linalg.norm(branch.innovation(pose.rotation))))
            if index == self.output_branch and jump > cfg.flip_angle_deg and not self.slewing:
                assert self.translation_filter is not None
                moved = float(np.linalg.norm(pose.tvec - self.translation_filter.translation))
                if moved < cfg.flip_translation_m + 3.0 * math.sqrt(float(np.max(np.linalg.eigvalsh(cov_t)))):
                    self.pending_flip += 1
                    if self.pending_flip <= cfg.flip_persist_frames:
                        events.append(
                            TrackEvent(
                                "rejected_flip",
                                f"orientation jump of {jump:.1f} deg with "
                                f"{100 * moved:.2f} cm of motion: a flip, not motion",
                            )
                        )
                        self.doubtful = True  # this frame's output is a prediction we cannot vouch for
                        continue
                    events.append(
                        TrackEvent(
                            "accepted_jump",
                            f"orientation jump of {jump:.1f} deg persisted "
                            f"{self.pending_flip} frames: accepted as motion",
                        )
                    )
                    branch.reset(pose.rotation, cov_rot)
                    self.slewing = True
            if index == self.output_branch:
                self.pending_flip = 0
            branch.update(pose.rotation, cov_rot)

    def _update_translation(self, measurement: MarkerPose, camera: CameraModel) -> None:
        assert self.translation_filter is not None
        pose = measurement.best.pose
        _, cov_t = self._covariance(pose, camera)
        self.translation_filter.update(pose.tvec, cov_t)

    def _coast(self, dt: float, events: list[TrackEvent]) -> TrackUpdate | None:
        if self.branches is None:
            return None
        self.missed += 1
        if self.missed > self.config.max_missed_frames:
            self.branches = None
            events.append(TrackEvent("reset", f"lost for more than {self.config.max_missed_frames} frames: reset"))
            return None
        assert self.translation_filter is not None
        for branch in self.branches:
            if branch is not None:
                branch.predict(dt)
        if self.tilts is not None:
            self.tilts.predict(dt)
        self.translation_filter.predict(dt)
        return self._result("predicted", (None, None), events)

    def _output(self, filtered: np.ndarray, moved_m: float) -> np.ndarray:
        """The rotation to show: the filter's, but while the position stays put (``moved_m`` below
        ``flip_translation_m``) turning at most max_output_step_deg per frame: a change of branch, or a
        filter that jumped, is slewed over several frames instead of snapping."""
        previous = self.output_rotation
        if previous is None:
            self.output_rotation = filtered
            return filtered
        step = so3_log(previous.T @ filtered)
        angle = float(np.degrees(np.linalg.norm(step)))
        limit = self.config.max_output_step_deg
        if angle <= limit or moved_m >= self.config.flip_translation_m:
            self.slewing = False
            self.output_rotation = filtered
        else:
            self.slewing = True
            self.output_rotation = previous @ so3_exp(step * (limit / angle))
        return self.output_rotation

    def _too_uncertain(self, branch: RotationFilter) -> bool:
        """3 sigma of the filtered orientation beyond flip_angle_deg."""
        sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(branch.cv.P[:3, :3]))), 0.0))
        return math.degrees(3.0 * sigma) > self.config.flip_angle_deg

    def _result(self, state: str, hypotheses: tuple[Pose | None, Pose | None], events: list[TrackEvent]) -> TrackUpdate:
        assert self.branches is not None and self.translation_filter is not None
        branch = self.branches[self.output_branch]
        assert branch is not None
        translation = self.translation_filter.translation
        moved = 0.0 if self.output_translation is None else float(np.linalg.norm(translation - self.output_translation))
        self.output_translation = translation
        rotation = self._output(branch.rotation, moved)
        pose = Pose.from_matrix(rotation, translation)
        if state == "tracked" and (self.slewing or self.doubtful or self._too_uncertain(branch)):
            # turning toward the committed branch, a rejected flip, or an orientation so noisy that even the
            # right branch may be off by a flip's worth: not vouched for
            state = "ambiguous"
        return TrackUpdate(
            state,
            pose,
            self.output_branch,
            self.committed is not None,
            self._evidence_bound(0.0, 0.0),
            hypotheses,
            tuple(events),
        )
