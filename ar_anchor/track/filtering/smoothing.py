"""The smoothers: Kalman filters on a rotation (an error state on SO(3)) and on a translation, each an
IMM of a *still* and a *moving* constant-velocity model (see the package doc)."""

from __future__ import annotations

import math

import numpy as np

from ...geometry import matrix_from_rvec, rvec_from_matrix

__all__ = [
    "RotationFilter",
    "TranslationFilter",
    "TwoModeCV",
    "cv_process_noise",
    "cv_transition",
    "so3_exp",
    "so3_log",
]


# ---------------------------------------------------------------------------- SO(3) helpers


def so3_exp(vector: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) -> rotation matrix (3, 3)."""
    return matrix_from_rvec(vector)


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,)."""
    return rvec_from_matrix(rotation)


_POSITION, _VELOCITY = np.arange(3), np.arange(3, 6)  # the blocks of a 3D constant-velocity state [x, v]
_IDENTITY2 = np.repeat(np.eye(6)[None], 2, axis=0)  # one 6x6 identity per motion model
_MODELS: dict[tuple[float, float, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # (dt, ...) -> F, F^T, Q
_MODELS_KEPT = 256  # a variable frame rate makes new steps: the cache starts again beyond this many


def cv_process_noise(dt: float, accel_sigma: float) -> np.ndarray:
    """Discrete white-noise-acceleration covariance for a 3D constant-velocity state [x, v]."""
    q = accel_sigma**2
    noise = np.zeros((6, 6))
    noise[_POSITION, _POSITION] = q * dt**3 / 3.0
    noise[_POSITION, _VELOCITY] = noise[_VELOCITY, _POSITION] = q * dt**2 / 2.0
    noise[_VELOCITY, _VELOCITY] = q * dt
    return noise


def cv_transition(dt: float) -> np.ndarray:
    """Transition matrix (6, 6) of a 3D constant-velocity state [x, v] over ``dt`` seconds."""
    transition = np.eye(6)
    transition[_POSITION, _VELOCITY] = dt
    return transition


# ---------------------------------------------------------------------------- filters


class TwoModeCV:
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
        self._F = self._FT = self._Q = np.zeros((2, 6, 6))  # noqa: N815
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
        self._P = (self.mu @ self.Ps.reshape(2, 36)).reshape(6, 6) + (self.mu[:, None] * spread).T @ spread

    def _models(self, dt: float) -> None:
        """Transition and process noise of both models for a step of ``dt`` (the still model: position
        kept, velocity zeroed, a random walk; the moving one: :func:`cv_transition`, :func:`cv_process_noise`).
        Shared by every filter of the same settings (read only): a video's steps take few distinct values."""
        if dt == self._dt:
            return
        key = (dt, self.still_sigma, self.accel_moving)
        models = _MODELS.get(key)
        if models is None:
            still_f, still_q = np.zeros((6, 6)), np.zeros((6, 6))
            still_f[_POSITION, _POSITION] = 1.0
            still_q[_POSITION, _POSITION] = self.still_sigma**2 * dt
            still_q[_VELOCITY, _VELOCITY] = 1e-12
            transition = np.stack([still_f, cv_transition(dt)])
            models = (
                transition,
                transition.transpose(0, 2, 1).copy(),
                np.stack([still_q, cv_process_noise(dt, self.accel_moving)]),
            )
            if len(_MODELS) >= _MODELS_KEPT:
                _MODELS.clear()
            _MODELS[key] = models
        self._F, self._FT, self._Q = models
        self._dt = dt

    def predict(self, dt: float) -> None:
        """IMM predict over ``dt`` seconds: mix the two models, then propagate each."""
        self._models(dt)
        # mixing: model j starts from the mixture of both models, weighed by P(was i | is j)
        cbar = self.mu @ self.M
        omega = self.M * self.mu[:, None] / cbar[None, :]  # omega[i, j]
        mixed_x = omega.T @ self.xs
        spread = self.xs[None, :, :] - mixed_x[:, None, :]  # [j, i, :]
        weighted = omega.T[:, :, None] * spread  # [j, i, :]
        mixed_p = (omega.T @ self.Ps.reshape(2, 36)).reshape(2, 6, 6) + weighted.transpose(0, 2, 1) @ spread
        self.xs = (self._F @ mixed_x[:, :, None])[:, :, 0]
        self.Ps = self._F @ mixed_p @ self._FT + self._Q
        self._combine()

    def update(self, z: np.ndarray, cov: np.ndarray) -> None:
        """IMM update with measurement ``z`` (3,) of covariance ``cov`` (3, 3): update each model, reweigh the modes."""
        z = np.asarray(z, np.float64).reshape(3)
        cov = np.asarray(cov, np.float64)
        rows = self._H_ROWS
        innovation = z - self.xs[:, rows]  # (2, 3)
        pht = self.Ps[:, :, rows]  # P H^T, (2, 6, 3)
        s = self.Ps[:, rows, rows] + cov  # (2, 3, 3)
        s_inv = np.linalg.inv(s)
        gain = pht @ s_inv  # (2, 6, 3)
        self.xs = self.xs + (gain @ innovation[:, :, None])[:, :, 0]
        i_kh = _IDENTITY2.copy()
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
        """Restart at ``rotation`` (``camera_from_target``), covariance ``rotation_cov``; ``omega`` in rad/s (body)."""
        self.rotation = np.array(rotation, dtype=np.float64)
        x0 = np.zeros(6)
        if omega is not None:
            x0[3:] = omega
        p0 = np.block([[rotation_cov, np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3) * omega_sigma**2]])
        self.cv = TwoModeCV(x0, p0, *self.accels)

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

    def limit_rate(self, limit: float) -> None:
        """Bound each motion model's angular velocity to ``limit`` (rad/s)."""
        omega = self.cv.xs[:, 3:]
        speed = np.linalg.norm(omega, axis=1)
        if np.any(speed > limit):
            self.cv.xs[:, 3:] = omega * np.minimum(1.0, limit / np.maximum(speed, 1e-12))[:, None]
            self.cv._combine()


class TranslationFilter:
    """Constant-velocity filter on the translation (camera frame, metres), two process-noise modes."""

    def __init__(self, translation: np.ndarray, cov: np.ndarray, still_sigma: float, accel_moving: float) -> None:
        x0 = np.concatenate([np.asarray(translation, dtype=np.float64), np.zeros(3)])
        p0 = np.block([[cov, np.zeros((3, 3))], [np.zeros((3, 3)), np.eye(3) * 0.5**2]])
        self.cv = TwoModeCV(x0, p0, still_sigma, accel_moving)

    @property
    def translation(self) -> np.ndarray:
        return self.cv.x[:3].copy()

    @property
    def velocity(self) -> np.ndarray:
        return self.cv.x[3:].copy()

    def predict(self, dt: float) -> None:
        self.cv.predict(dt)

    def update(self, measured: np.ndarray, cov: np.ndarray) -> None:
        self.cv.update(measured, cov)
