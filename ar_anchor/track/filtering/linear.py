"""A linear Kalman filter whose steps are taken for many filters at once (the tilt trackers of a frame's
tracks), and the helper that runs a track's update alone when it is written as steps.

The steps are ``filterpy``'s :class:`~filterpy.kalman.KalmanFilter` ``predict`` and ``update`` (the same
Joseph-form update), on the filters' states stacked in arrays: filterpy steps one filter per Python call,
which, with one tilt tracker per target, was a third of the filter's time with 50 markers in view.
``tests/track/test_filtering.py`` checks them against filterpy step by step.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from typing import TypeVar

import numpy as np

__all__ = ["LinearKF", "predict_linear", "run_alone", "update_linear"]

T = TypeVar("T")


class LinearKF:
    """A linear Kalman filter's state: ``x`` (n,), ``P`` (n, n); its measurement is the first ``m`` entries
    of the state (``H = [I 0]``). Stepped by :func:`predict_linear` and :func:`update_linear`."""

    def __init__(self, x: np.ndarray, p: np.ndarray, measured: int) -> None:
        self.x = np.asarray(x, np.float64).reshape(-1).copy()
        self.P = np.asarray(p, np.float64).copy()  # noqa: N815 - the Kalman filter's name for it
        self.measured = measured


def predict_linear(
    filters: Sequence[LinearKF], transitions: Sequence[np.ndarray], noises: Sequence[np.ndarray]
) -> None:
    """``x = F x``, ``P = F P F^T + Q`` of each filter with its own ``F`` and ``Q``, all at once."""
    f = np.stack(transitions)
    x = (f @ np.stack([kf.x for kf in filters])[..., None])[..., 0]
    p = f @ np.stack([kf.P for kf in filters]) @ f.transpose(0, 2, 1) + np.stack(noises)
    for k, kf in enumerate(filters):
        kf.x, kf.P = x[k], p[k]


def update_linear(filters: Sequence[LinearKF], zs: Sequence[np.ndarray], noises: Sequence[np.ndarray]) -> None:
    """Each filter's update with its measurement ``z`` (m,) of covariance ``R`` (m, m), all at once
    (filters of one size: ``n`` and ``m`` the same for all)."""
    m = filters[0].measured
    x = np.stack([kf.x for kf in filters])
    p = np.stack([kf.P for kf in filters])
    r = np.stack(noises)
    innovation = np.asarray(zs, np.float64).reshape(len(filters), m) - x[:, :m]
    gain = p[:, :, :m] @ np.linalg.inv(p[:, :m, :m] + r)  # P H^T S^-1
    x = x + (gain @ innovation[..., None])[..., 0]
    i_kh = np.broadcast_to(np.eye(x.shape[1]), p.shape).copy()
    i_kh[..., :m] -= gain
    p = i_kh @ p @ i_kh.transpose(0, 2, 1) + gain @ r @ gain.transpose(0, 2, 1)
    for k, kf in enumerate(filters):
        kf.x, kf.P = x[k], p[k]


def run_alone(steps: Generator[None, None, T]) -> T:
    """Run an update written as steps (a generator that pauses while a batch it queued into is taken,
    see :class:`~.smoothing.KalmanBatch`) on its own: its queued steps were taken at once (no batch)."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value
