"""A learned group's layout (:class:`LearnedGroup`): its members' poses in the group's frame, turned as its
anchor and centred on its members, made exactly planar when they nearly share one plane, and the board
solver built from them; and the samples that refine a layout from the group's own joint poses
(:func:`on_plane`, :func:`add_sample`). A group's board is named ``group-N`` (:data:`GROUP_PREFIX`,
:func:`is_learned_group`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...camera import CameraModel
from ...config import BoardConfig
from ...geometry import Pose, marker_corners_in_marker, mean_rotation
from ...targets import TargetId
from ..pose import BoardSolver

__all__ = ["GROUP_PREFIX", "LearnedGroup", "add_sample", "is_learned_group", "on_plane"]

GROUP_PREFIX = "group-"
_PLANAR_SHARE = 0.005  # out-of-plane spread (RMS) below this share of the layout's extent: a planar group
_PLANAR_TILT_DEG = 3.0  # ... and no marker's normal farther than this from the plane's (a curled sheet is not flat)
_AGREE_TURN_DEG = 1.0  # ... and a member sure of its pose follows a layout only while it is below this


def is_learned_group(target: TargetId) -> bool:
    """Is ``target`` a learned group's board (``board:group-N``, :attr:`LearnedGroup.target`)?"""
    return target.is_board and target.name.startswith(GROUP_PREFIX)


@dataclass
class LearnedGroup:
    """A group of markers found rigid together: its layout (``group_from_marker`` per member, in a frame
    turned as its anchor and centred on its members, :meth:`recentre`) and the board solver built from it."""

    number: int
    anchor: int
    layout: dict[int, Pose]
    lengths: dict[int, float]
    dictionary: str
    inlier_px: float = 3.0  # [pose] board_inlier_px: a member farther than this from the joint pose is an outlier
    solver: BoardSolver = field(init=False)
    rejected: dict[int, int] = field(default_factory=dict)  # member -> measured frames in a row rejected
    disagreeing: int = 0  # frames in a row the joint pose agreed with fewer than two seen members
    samples: dict[int, list[np.ndarray]] = field(default_factory=dict)  # member -> [rotation sum, t sum, n]
    since_refined: int = 0
    refinements: int = 0  # layout refinements from the group's own joint poses (see GroupLearner._sample)
    turn: dict[int, list] = field(default_factory=dict)  # member -> own-vs-layout turn statistics (_compare_turns)
    settled: bool = False  # its last refinement moved no corner more than _SETTLED_M (its members may follow it)

    def __post_init__(self) -> None:
        self.rebuild()

    @property
    def name(self) -> str:
        return f"{GROUP_PREFIX}{self.number}"

    @property
    def target(self) -> TargetId:
        return TargetId.board(self.name)

    def rebuild(self) -> None:
        """Flatten a planar layout and build its board solver (after a join, a leave or a refinement)."""
        self.layout = _flattened(self.layout, self.lengths)
        corners = []
        for marker_id, pose in sorted(self.layout.items()):
            points = pose.apply(marker_corners_in_marker(self.lengths[marker_id]))
            corners.append((marker_id, tuple(tuple(float(v) for v in p) for p in points)))
        board = BoardConfig(name=self.name, kind="custom", layout=tuple(corners), dictionary=self.dictionary)
        self.solver = BoardSolver(board, self.inlier_px)

    def recentre(self) -> None:
        """Move the group's frame to its members' centroid (turned as it was), after a join or a merge: a
        joint pose's position is surest there, uncoupled from its rotation, so the filter smooths the two
        apart, as it does a board's (a frame at one corner marker would carry the rotation's noise, times
        the lever, into every member's position). The tracker then restarts the group's track."""
        centre = np.concatenate(list(self.corners().values())).mean(axis=0)
        shift = Pose(np.zeros(3), -centre)
        self.layout = {i: shift.compose(pose) for i, pose in self.layout.items()}
        self.samples.clear()  # (measured in the frame before)
        self.rebuild()

    def take_means(self, sums: dict[int, list]) -> bool:
        """The layout becomes the members' mean poses in the group's frame (``sums``: member -> [rotation
        sum, translation sum, count]; those with five samples or more), the anchor's included, then
        re-expressed so that the anchor stays where the layout had it (the group's frame does not move
        with its anchor's sampling noise, and the others are not left to absorb the anchor's own error).
        Returns whether anything changed (the solver is rebuilt then)."""
        means = {
            i: Pose.from_matrix(mean_rotation([rotation_sum]), translation_sum / count)
            for i, (rotation_sum, translation_sum, count) in sums.items()
            if count >= 5 and i in self.layout
        }
        if not means:
            return False
        fix = Pose.identity()
        if self.anchor in means:  # (group_from_marker of the anchor kept as it was)
            fix = self.layout[self.anchor].compose(means[self.anchor].inverse())
        for marker_id, pose in means.items():
            self.layout[marker_id] = fix.compose(pose)
        for marker_id in set(self.layout) - set(means):
            self.layout[marker_id] = fix.compose(self.layout[marker_id])
        self.rebuild()
        return True

    def agrees(self, marker_id: int) -> bool:
        """Does the layout's orientation for this member agree with the member's own solutions (recent
        frames, :meth:`~.learner.GroupLearner._compare_turns`): their mean turn below :data:`_AGREE_TURN_DEG`, or
        below three standard errors of that mean (a far, noisy member cannot tell a degree apart)?"""
        stats = self.turn.get(marker_id)
        if stats is None or stats[2] < 3.0:
            return False
        mean, square, weight = stats
        spread = max(square - float(mean @ mean), 0.0)
        standard_error = math.sqrt(spread / weight)
        return float(np.linalg.norm(mean)) <= max(math.radians(_AGREE_TURN_DEG), 3.0 * standard_error)

    def corners(self) -> dict[int, np.ndarray]:
        """Each member's corners (4, 3) in the group's frame."""
        return {i: pose.apply(marker_corners_in_marker(self.lengths[i])) for i, pose in self.layout.items()}

    def describe(self) -> str:
        return ", ".join(str(i) for i in sorted(self.layout))


def _flattened(layout: dict[int, Pose], lengths: dict[int, float]) -> dict[int, Pose]:
    """``layout`` made exactly planar when its markers nearly share one plane (see the module doc): each
    marker's centre projected onto the best-fit plane and its normal turned onto the plane's."""
    if len(layout) < 2:
        return layout
    normals = np.stack([pose.rotation[:, 2] for pose in layout.values()])
    mean_normal = normals.sum(axis=0)
    mean_normal /= max(float(np.linalg.norm(mean_normal)), 1e-12)
    corners = np.concatenate([pose.apply(marker_corners_in_marker(lengths[i])) for i, pose in layout.items()])
    centroid = corners.mean(axis=0)
    _, singular, vt = np.linalg.svd(corners - centroid, full_matrices=False)
    normal = vt[2] if float(vt[2] @ mean_normal) >= 0 else -vt[2]
    extent = float(np.ptp(corners @ vt[0]))
    out_of_plane = singular[2] / math.sqrt(len(corners))
    tilt = max(math.degrees(math.acos(float(np.clip(n @ normal, -1.0, 1.0)))) for n in normals)
    if out_of_plane > _PLANAR_SHARE * extent or tilt > _PLANAR_TILT_DEG:
        return layout
    flat = {}
    for marker_id, pose in layout.items():
        rotation = pose.rotation
        axis = np.cross(rotation[:, 2], normal)
        sine, cosine = float(np.linalg.norm(axis)), float(rotation[:, 2] @ normal)
        turn = np.eye(3)
        if sine > 1e-12:
            k = axis / sine
            skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            turn = np.eye(3) + sine * skew + (1 - cosine) * skew @ skew
        centre = pose.tvec - float((pose.tvec - centroid) @ normal) * normal
        flat[marker_id] = Pose.from_matrix(turn @ rotation, centre)
    return flat


def add_sample(sums: dict[int, list], marker_id: int, sample: Pose) -> None:
    """Add a member's pose in the group's frame to ``sums`` (member -> [rotation sum, translation sum, count],
    as :meth:`LearnedGroup.take_means` reads them)."""
    total = sums.setdefault(marker_id, [np.zeros((3, 3)), np.zeros(3), 0])
    total[0] = total[0] + sample.rotation
    total[1] = total[1] + sample.tvec
    total[2] += 1


def on_plane(
    corners: np.ndarray, length_m: float, camera_from_group: Pose, group_from_anchor: Pose, camera: CameraModel
) -> Pose | None:
    """``group_from_marker`` of a marker of a planar group from its ``corners`` (in the image) and side:
    their rays (undistorted) met with the group's plane (the anchor's x-y plane), and a square of its side
    fitted there."""
    pixels = np.asarray(corners, dtype=np.float64).reshape(4, 1, 2)
    rays = cv2.undistortPoints(pixels, camera.camera_matrix, camera.dist_or_none).reshape(4, 2)
    rays = np.column_stack([rays, np.ones(4)])
    camera_from_anchor = camera_from_group.compose(group_from_anchor)
    normal, origin = camera_from_anchor.rotation[:, 2], camera_from_anchor.tvec
    along = rays @ normal
    if np.any(np.abs(along) < 1e-9):
        return None
    points = rays * ((origin @ normal) / along)[:, None]  # in the camera frame
    if np.any(points[:, 2] <= 0):
        return None
    in_plane = (points - origin) @ camera_from_anchor.rotation[:, :2]  # the anchor's x, y
    square = marker_corners_in_marker(length_m)[:, :2]
    centre = in_plane.mean(axis=0)
    u, _, vt = np.linalg.svd(square.T @ (in_plane - centre))
    turn = (u @ vt).T
    if np.linalg.det(turn) < 0:
        return None
    rotation = np.eye(3)
    rotation[:2, :2] = turn
    anchor_from_marker = Pose.from_matrix(rotation, np.array([centre[0], centre[1], 0.0]))
    return group_from_anchor.compose(anchor_from_marker)
