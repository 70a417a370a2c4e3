"""Which solution is which: the two branches (one per IPPE solution), the tilt tracker that assigns each
frame's solutions to them, and their smoothers (see the package doc)."""

from __future__ import annotations

import functools
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np

from ...camera import CameraModel
from ...config import FilterConfig
from ...geometry import Pose, angle_between_deg, vector_norm
from ..pose import BoardPose, MarkerPose, PoseHypothesis
from .linear import LinearKF, predict_linear, update_linear
from .noise import CornerNoise
from .smoothing import KalmanBatch, RotationFilter, TranslationFilter, so3_exp

__all__ = ["BranchPair", "tilt_of"]


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
        self.accel = accel
        self.blind_s = 0.0  # how long the choice has been unclear
        self._dt: float | None = None
        self.reset(tilt, sigma)

    def reset(self, tilt: np.ndarray, sigma: float) -> None:
        """Start again at ``tilt`` at rest (after a long gap the old rate means nothing)."""
        self.kf = LinearKF(np.concatenate([tilt, np.zeros(2)]), np.diag([sigma**2, sigma**2, 1.0, 1.0]), measured=2)
        self.blind_s = 0.0

    @property
    def tilt(self) -> np.ndarray:
        return self.kf.x[:2].copy()

    def predict(self, dt: float, batch: KalmanBatch | None = None) -> None:
        """Predict over ``dt`` seconds (``batch``: queued there, taken with the frame's other filters)."""
        if dt != self._dt:  # state [tilt_x, tilt_y, rate_x, rate_y]
            self._dt = dt
            self._f = np.eye(4)
            self._f[0, 2] = self._f[1, 3] = dt
            self._q = np.kron(self.accel**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), np.eye(2))
        if batch is not None:
            batch.predict_linear(self.kf, self._f, self._q, after=self._bound)
            return
        predict_linear([self.kf], [self._f], [self._q])
        self._bound()

    def _bound(self) -> None:
        rate = self.kf.x[2:]
        speed = vector_norm(rate)
        if speed > self._MAX_RATE:
            self.kf.x[2:] = rate * (self._MAX_RATE / speed)
        (a, _), (c, d) = self.kf.P[:2, :2].tolist()
        largest = 0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + c * c)  # of the 2x2 block (its lower triangle)
        if largest > self._MAX_SIGMA**2:
            self.kf.P[:2, :] *= math.sqrt(self._MAX_SIGMA**2 / largest)
            self.kf.P[:, :2] *= math.sqrt(self._MAX_SIGMA**2 / largest)

    def choose(
        self,
        first: np.ndarray,
        second: np.ndarray | None,
        sigma: float,
        dt: float,
        batch: KalmanBatch | None = None,
    ) -> tuple[bool, bool]:
        """Is ``first`` (rather than ``second``, by default its mirror) branch 0's tilt, and is that clear?

        The pair is matched as a whole: branch 0 near the prediction and branch 1 near its mirror. Always
        updates (an unclear choice with its noise inflated by the unclarity; ``batch``: queued there)."""
        predicted = self.tilt
        second = -first if second is None else second
        straight = vector_norm(first - predicted) + vector_norm(second + predicted)
        swapped = vector_norm(second - predicted) + vector_norm(first + predicted)
        spread = math.sqrt(float(np.trace(self.kf.P[:2, :2])) + 2 * sigma**2)
        is_branch0 = straight <= swapped
        clear = 0.5 * abs(straight - swapped) > spread
        self.blind_s = 0.0 if clear else self.blind_s + dt
        noise = np.eye(2) * (sigma**2 if clear else sigma**2 + spread**2)
        measured = first if is_branch0 else second
        if batch is not None:
            batch.update_linear(self.kf, measured, noise, after=self._bound)
        else:
            update_linear([self.kf], [measured], [noise])
            self._bound()
        return is_branch0, clear


@dataclass
class _Branch:
    """One IPPE solution's history: its smoother and its last measurement."""

    smoother: RotationFilter
    last: np.ndarray  # rotation of the last measurement assigned to this branch


class BranchPair:
    """A track's two branches, the tilt tracker that tells them apart, and the translation smoother they
    share. Started from a track's first frame (its lower-error solution on branch 0)."""

    def __init__(
        self, config: FilterConfig, hypotheses: Sequence[PoseHypothesis], noise: CornerNoise, camera: CameraModel
    ) -> None:
        self.config = config
        self.noise = noise
        self.branches: list[_Branch | None] = [self._new_branch(h.pose, camera) for h in hypotheses]
        if len(self.branches) == 1:
            self.branches.append(None)  # the other solution failed validation: unknown until it shows up
        self.tilts = _TiltTracker(
            tilt_of(hypotheses[0].pose), self._tilt_sigma(hypotheses[0].pose, camera), config.tilt_accel_rad_s2
        )
        best = hypotheses[0].pose
        _, cov_t = noise.covariance(best, camera)
        self.translation_filter = TranslationFilter(
            best.tvec, cov_t, config.still_translation_m_sqrt_s, config.linear_accel_moving_m_s2
        )
        self.doubtful = False  # this frame's assignment of solutions to branches is in doubt
        self.unclear = False  # ... or the tilt could not tell the (far apart) solutions apart this frame
        self.apart = False  # this frame's two solutions are more than flip_angle_deg apart

    def has(self, index: int) -> bool:
        return self.branches[index] is not None

    @property
    def complete(self) -> bool:
        """Have both branches started?"""
        return None not in self.branches

    def smoother(self, index: int) -> RotationFilter:
        branch = self.branches[index]
        assert branch is not None
        return branch.smoother

    @property
    def blind_s(self) -> float:
        """How long the tilt tracker has not told the solutions apart."""
        return self.tilts.blind_s

    def _new_branch(self, pose: Pose, camera: CameraModel) -> _Branch:
        cov_rot, _ = self.noise.covariance(pose, camera)
        smoother = RotationFilter(
            pose.rotation, cov_rot, self.config.still_rotation_rad_sqrt_s, self.config.angular_accel_moving_rad_s2
        )
        return _Branch(smoother, pose.rotation)

    def _tilt_sigma(self, pose: Pose, camera: CameraModel) -> float:
        cov_rot, _ = self.noise.covariance(pose, camera)
        return math.sqrt(float(np.max(np.linalg.eigvalsh(cov_rot))))

    def associate_steps(
        self,
        measurement: MarkerPose | BoardPose,
        camera: CameraModel,
        gap_s: float,
        restart: bool,
        separation_deg: float,
        batch: KalmanBatch | None = None,
    ) -> Generator[None, None, list[PoseHypothesis | None]]:
        """Assign this frame's solutions (``separation_deg`` apart) to the branches: branch 0 is the one
        whose tilt continues the tilt tracker's prediction (see :class:`_TiltTracker`); after a long gap,
        the one nearer branch 0's last tilt (the tracker restarts at rest). A branch whose solution shows
        up for the first time starts. Sets :attr:`unclear`, :attr:`doubtful` and :attr:`apart`; returns
        the assignment.

        In steps (:func:`~.linear.run_alone` runs it on its own): it pauses (yields) after queueing the tilt
        tracker's prediction in ``batch`` (None: taken at once), which the choice of branches needs."""
        hypotheses = measurement.hypotheses
        first = hypotheses[0]
        sigma = self._tilt_sigma(first.pose, camera)
        if restart:  # branch 0's last measured orientation, seen from where the target is now
            assert self.branches[0] is not None  # (a track starts with its lower-error solution on branch 0)
            self.tilts.reset(tilt_of(Pose.from_matrix(self.branches[0].last, first.pose.tvec)), sigma)
        else:
            self.tilts.predict(gap_s, batch)
        yield
        second = tilt_of(hypotheses[1].pose) if len(hypotheses) > 1 else None
        is_branch0, clear = self.tilts.choose(tilt_of(first.pose), second, sigma, 0.0 if restart else gap_s, batch)
        self.apart = len(hypotheses) == 2 and separation_deg > self.config.flip_angle_deg
        self.unclear = not clear and self.apart
        assigned: list[PoseHypothesis | None] = [None, None]
        if len(hypotheses) == 1:
            assigned[0 if is_branch0 else 1] = first
        else:
            assigned = [hypotheses[0], hypotheses[1]] if is_branch0 else [hypotheses[1], hypotheses[0]]
        self.doubtful = len(hypotheses) == 2 and not restart and self._motion_disagrees(assigned, gap_s)
        for index, hypothesis in enumerate(assigned):  # a solution shows up for the first time: its branch starts
            if self.branches[index] is None and hypothesis is not None:
                self.branches[index] = self._new_branch(hypothesis.pose, camera)
        return assigned

    def _motion_disagrees(self, assigned: list[PoseHypothesis | None], gap_s: float) -> bool:
        """A second opinion on the assignment: each branch's smoother, turned on at its angular velocity,
        should be nearer its own solution than the other's. Where the tilt's continuity and the
        rotation's disagree (fast motion through a crossing), which is which is not known this frame."""
        if any(b is None for b in self.branches) or any(h is None for h in assigned):
            return False
        predicted = [b.smoother.rotation @ so3_exp(b.smoother.omega * gap_s) for b in self.branches]  # type: ignore[union-attr]
        rotations = [h.pose.rotation for h in assigned]  # type: ignore[union-attr]
        straight = angle_between_deg(predicted[0], rotations[0]) + angle_between_deg(predicted[1], rotations[1])
        swapped = angle_between_deg(predicted[0], rotations[1]) + angle_between_deg(predicted[1], rotations[0])
        return swapped + self.config.flip_angle_deg < straight

    def update_steps(
        self,
        assigned: list[PoseHypothesis | None],
        measurement: MarkerPose | BoardPose,
        camera: CameraModel,
        gap_s: float,
        restart: bool,
        batch: KalmanBatch | None = None,
    ) -> Generator[None, None, None]:
        """The smoothers take this frame's measurements (``restart``: after a gap, from them), in steps: their
        Kalman steps are queued in ``batch`` (None: taken at once), and it pauses (yields) after queueing the
        predictions and after queueing the updates, for the caller to take the batch's steps
        (:meth:`KalmanBatch.run`) with other tracks' before going on.

        Each branch's smoother takes its measurement. A measurement is never rejected: a smoother that
        finds it implausibly far (``reset_angle_deg``), or that has not seen its branch for longer than
        ``restart_gap_s``, restarts from it. The translation smoother takes the better solution's."""
        cfg = self.config
        measured = [
            (branch.smoother, hypothesis)
            for branch, hypothesis in zip(self.branches, assigned)
            if branch is not None and hypothesis is not None
        ]
        for branch, hypothesis in zip(self.branches, assigned):
            if branch is not None and hypothesis is not None:
                branch.last = hypothesis.pose.rotation
        if not restart:
            for smoother, _ in measured:
                smoother.predict(gap_s, batch)
            self.translation_filter.predict(gap_s, batch)
        yield
        limit = math.radians(cfg.max_angular_rate_deg_s)
        for smoother, hypothesis in measured:
            pose = hypothesis.pose
            cov_rot, _ = self.noise.covariance(pose, camera)
            jump = math.degrees(vector_norm(smoother.innovation(pose.rotation)))
            if restart or jump > cfg.reset_angle_deg:
                smoother.reset(pose.rotation, cov_rot)
            else:  # then a bounded angular velocity, per motion model
                smoother.update(pose.rotation, cov_rot, batch, after=functools.partial(smoother.limit_rate, limit))
        pose = measurement.best.pose
        _, cov_t = self.noise.covariance(pose, camera)
        if restart:
            self.translation_filter = TranslationFilter(
                pose.tvec, cov_t, cfg.still_translation_m_sqrt_s, cfg.linear_accel_moving_m_s2
            )
        else:
            self.translation_filter.update(pose.tvec, cov_t, batch)
        yield
