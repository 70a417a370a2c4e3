"""The smoothers: Kalman filters on a rotation (an error state on SO(3)) and on a translation, each an
IMM of a *still* and a *moving* constant-velocity model (see the package doc)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ...geometry import matrix_from_rvec, rvec_from_matrix
from .linear import LinearKF, predict_linear, update_linear

__all__ = [
    "KalmanBatch",
    "RotationFilter",
    "TranslationFilter",
    "TwoModeCV",
    "cv_process_noise",
    "cv_transition",
    "predict_all",
    "so3_exp",
    "so3_log",
    "update_all",
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
        x, p = _combined(self.mu[None], self.xs[None], self.Ps[None])
        self._x, self._P = x[0], p[0]

    def models(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Transition, its transpose and process noise of both models for a step of ``dt`` (the still model:
        position kept, velocity zeroed, a random walk; the moving one: :func:`cv_transition`,
        :func:`cv_process_noise`). Shared by every filter of the same settings (read only): a video's steps
        take few distinct values."""
        if dt == self._dt:
            return self._F, self._FT, self._Q
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
        return models

    def predict(self, dt: float) -> None:
        """IMM predict over ``dt`` seconds: mix the two models, then propagate each."""
        predict_all([self], [dt])

    def update(self, z: np.ndarray, cov: np.ndarray) -> None:
        """IMM update with measurement ``z`` (3,) of covariance ``cov`` (3, 3): update each model, reweigh the modes."""
        update_all([self], [z], [cov])

    def shift(self, delta: np.ndarray) -> None:
        """Subtract ``delta`` from the first three state entries (after folding them into a nominal state)."""
        self.xs[:, :3] -= delta
        self._x = self._x.copy()
        self._x[:3] -= delta


# ---------------------------------------------------------------------------- the IMM steps, over many filters
# Each function takes B filters' arrays stacked on a first axis: xs (B, 2, 6), Ps (B, 2, 6, 6), mu (B, 2),
# M (B, 2, 2); one numpy call per operation whatever B (a frame's targets run three filters each).


def _combined(mu: np.ndarray, xs: np.ndarray, ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The IMM's outputs (B, 6), (B, 6, 6): the models weighed by the mode probabilities."""
    x = (mu[:, None, :] @ xs)[:, 0]
    spread = xs - x[:, None, :]
    p = (mu[:, None, :] @ ps.reshape(len(ps), 2, 36)).reshape(-1, 6, 6)
    return x, p + (mu[:, :, None] * spread).transpose(0, 2, 1) @ spread


def predict_all(filters: Sequence[TwoModeCV], dts: Sequence[float]) -> None:
    """:meth:`TwoModeCV.predict` of each filter over its own ``dt``, all at once."""
    models = [f.models(dt) for f, dt in zip(filters, dts)]
    transition, transposed, noise = (np.stack([m[k] for m in models]) for k in range(3))
    xs, ps, mu, markov = _gather(filters)
    # mixing: model j starts from the mixture of both models, weighed by P(was i | is j)
    cbar = (mu[:, None, :] @ markov)[:, 0]
    omega_t = (markov * mu[:, :, None] / cbar[:, None, :]).transpose(0, 2, 1)  # [b, j, i]
    mixed_x = omega_t @ xs
    spread = xs[:, None, :, :] - mixed_x[:, :, None, :]  # [b, j, i, :]
    weighted = omega_t[..., None] * spread
    mixed_p = (omega_t @ ps.reshape(-1, 2, 36)).reshape(-1, 2, 6, 6) + weighted.transpose(0, 1, 3, 2) @ spread
    xs = (transition @ mixed_x[..., None])[..., 0]
    ps = transition @ mixed_p @ transposed + noise
    _scatter(filters, xs, ps, mu)


def update_all(filters: Sequence[TwoModeCV], zs: Sequence[np.ndarray], covs: Sequence[np.ndarray]) -> None:
    """:meth:`TwoModeCV.update` of each filter with its own measurement and covariance, all at once."""
    xs, ps, mu, markov = _gather(filters)
    z = np.asarray(zs, np.float64).reshape(-1, 3)
    cov = np.asarray(covs, np.float64).reshape(-1, 1, 3, 3)
    innovation = z[:, None, :] - xs[:, :, :3]  # (B, 2, 3)
    s = ps[:, :, :3, :3] + cov
    s_inv = np.linalg.inv(s)
    gain = ps[:, :, :, :3] @ s_inv  # P H^T S^-1, (B, 2, 6, 3)
    xs = xs + (gain @ innovation[..., None])[..., 0]
    i_kh = np.broadcast_to(_IDENTITY2, ps.shape).copy()
    i_kh[..., :3] -= gain
    ps = i_kh @ ps @ i_kh.transpose(0, 1, 3, 2) + gain @ cov @ gain.transpose(0, 1, 3, 2)
    mu = (mu[:, None, :] @ markov)[:, 0] * _likelihoods(innovation, s, s_inv)
    total = mu.sum(axis=1)
    fine = (total > 0) & np.isfinite(total)
    mu = np.where(fine[:, None], mu / np.where(fine, total, 1.0)[:, None], 0.5)
    _scatter(filters, xs, ps, mu)


def _gather(filters: Sequence[TwoModeCV]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if len(filters) == 1:
        f = filters[0]
        return f.xs[None], f.Ps[None], f.mu[None], f.M[None]
    return (
        np.stack([f.xs for f in filters]),
        np.stack([f.Ps for f in filters]),
        np.stack([f.mu for f in filters]),
        np.stack([f.M for f in filters]),
    )


def _scatter(filters: Sequence[TwoModeCV], xs: np.ndarray, ps: np.ndarray, mu: np.ndarray) -> None:
    x, p = _combined(mu, xs, ps)
    for k, f in enumerate(filters):
        f.xs, f.Ps, f.mu, f._x, f._P = xs[k], ps[k], mu[k], x[k], p[k]


def _likelihoods(innovations: np.ndarray, covariances: np.ndarray, inverses: np.ndarray) -> np.ndarray:
    """Gaussian likelihood of each model's innovation (B, 2, 3) under its covariance (B, 2, 3, 3) (with its
    inverse), relative to the filter's largest: the IMM normalises them anyway, and relative values cannot
    all underflow to zero. A model whose covariance is not positive definite gets likelihood zero (both: one)."""
    sign, log_det = np.linalg.slogdet(covariances)
    mahalanobis = (innovations[..., None, :] @ inverses @ innovations[..., None])[..., 0, 0]
    log_l = np.where((sign > 0) & (mahalanobis >= 0), -0.5 * mahalanobis - 0.5 * log_det, -np.inf)
    finite = np.isfinite(log_l)
    best = np.where(finite, log_l, -np.inf).max(axis=1)
    any_finite = finite.any(axis=1)
    relative = np.exp(log_l - np.where(any_finite, best, 0.0)[:, None])
    return np.where(any_finite[:, None], relative, 1.0)


class KalmanBatch:
    """The Kalman steps of a frame's tracks, gathered and taken at once: the IMM smoothers'
    (:func:`predict_all`, :func:`update_all`) and the linear filters' (the tilt trackers:
    :func:`~.linear.predict_linear`, :func:`~.linear.update_linear`). Each step is queued with what must
    follow it (``after``: a rotation filter folds its error into its rotation), and :meth:`run` takes the
    queued predictions, then the queued updates, each followed by its ``after`` in the order queued."""

    def __init__(self) -> None:
        self._predicts: list[tuple[TwoModeCV, float, Callable[[], None] | None]] = []
        self._updates: list[tuple[TwoModeCV, np.ndarray, np.ndarray, Callable[[], None] | None]] = []
        self._linear_predicts: list[tuple[LinearKF, np.ndarray, np.ndarray, Callable[[], None] | None]] = []
        self._linear_updates: list[tuple[LinearKF, np.ndarray, np.ndarray, Callable[[], None] | None]] = []

    def predict(self, cv: TwoModeCV, dt: float, after: Callable[[], None] | None = None) -> None:
        self._predicts.append((cv, dt, after))

    def update(self, cv: TwoModeCV, z: np.ndarray, cov: np.ndarray, after: Callable[[], None] | None = None) -> None:
        self._updates.append((cv, z, cov, after))

    def predict_linear(
        self, kf: LinearKF, transition: np.ndarray, noise: np.ndarray, after: Callable[[], None] | None = None
    ) -> None:
        self._linear_predicts.append((kf, transition, noise, after))

    def update_linear(
        self, kf: LinearKF, z: np.ndarray, noise: np.ndarray, after: Callable[[], None] | None = None
    ) -> None:
        self._linear_updates.append((kf, z, noise, after))

    def run(self) -> None:
        """Take every queued prediction, then every queued update (each kind in one call), then empty the queues."""
        predicts, updates = self._predicts, self._updates
        linear_predicts, linear_updates = self._linear_predicts, self._linear_updates
        self._predicts, self._updates, self._linear_predicts, self._linear_updates = [], [], [], []
        if predicts:
            predict_all([p[0] for p in predicts], [p[1] for p in predicts])
        if linear_predicts:
            predict_linear(*zip(*[step[:3] for step in linear_predicts]))
        _call_afters(predicts, linear_predicts)
        if updates:
            update_all([u[0] for u in updates], [u[1] for u in updates], [u[2] for u in updates])
        if linear_updates:
            update_linear(*zip(*[step[:3] for step in linear_updates]))
        _call_afters(updates, linear_updates)


def _call_afters(*queues: Sequence[tuple]) -> None:
    for queue in queues:
        for *_, after in queue:
            if after is not None:
                after()


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

    def predict(self, dt: float, batch: KalmanBatch | None = None) -> None:
        """Predict over ``dt`` seconds (``batch``: queued there, taken with the frame's other filters)."""
        if batch is not None:
            batch.predict(self.cv, dt, after=self._fold)
            return
        self.cv.predict(dt)
        self._fold()

    def innovation(self, measured: np.ndarray) -> np.ndarray:
        """Body-frame rotation vector from the current estimate to a measurement."""
        return so3_log(self.rotation.T @ measured)

    def update(
        self,
        measured: np.ndarray,
        cov: np.ndarray,
        batch: KalmanBatch | None = None,
        after: Callable[[], None] | None = None,
    ) -> None:
        """Take the measured rotation (covariance ``cov``), then call ``after`` (``batch``: queued there)."""

        def fold() -> None:
            self._fold()
            if after is not None:
                after()

        if batch is not None:
            batch.update(self.cv, self.innovation(measured), cov, after=fold)
            return
        self.cv.update(self.innovation(measured), cov)
        fold()

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

    def predict(self, dt: float, batch: KalmanBatch | None = None) -> None:
        """Predict over ``dt`` seconds (``batch``: queued there, taken with the frame's other filters)."""
        if batch is not None:
            batch.predict(self.cv, dt)
        else:
            self.cv.predict(dt)

    def update(self, measured: np.ndarray, cov: np.ndarray, batch: KalmanBatch | None = None) -> None:
        """Take the measured translation (covariance ``cov``; ``batch``: queued there)."""
        if batch is not None:
            batch.update(self.cv, measured, cov)
        else:
            self.cv.update(measured, cov)
