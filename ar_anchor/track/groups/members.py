"""The learned groups' members, frame by frame: the layouts they may follow (:class:`GroupLayout`), each
member given its group's pose where that fits its corners (:func:`members_from_groups`), and a group whose
frame contradicts its layout kept from ``tracked`` (:func:`disagrees_with_layout`, :func:`doubt_layouts`,
:data:`LAYOUT_DOUBT`). The live tracker and the offline replay both apply them to their results. Step 4 of
:mod:`ar_anchor.track.groups`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

from ...camera import CameraModel
from ...geometry import Pose, angle_between_deg, marker_corners_in_marker
from ...targets import TargetId, TrackState
from ..pose import BoardPose, reprojection_rms

__all__ = ["LAYOUT_DOUBT", "GroupLayout", "disagrees_with_layout", "doubt_layouts", "members_from_groups"]

_MEMBER_SLACK_PX = 0.3  # a member takes its group's pose only if that fits its corners within this of its own


@dataclass(frozen=True)
class GroupLayout:
    """A group's layout as its members may follow it this frame (:meth:`~.learner.GroupLearner.layouts`):
    ``group_from_marker`` by member, and whether it has settled."""

    members: dict[int, Pose]
    settled: bool = True
    agree: frozenset[int] | None = None  # members whose own orientation agrees with it (LearnedGroup.agrees; None: all)


def members_from_groups(
    targets: dict,
    layouts: dict[TargetId, GroupLayout],
    camera: CameraModel | None,
    replace: Callable,
) -> dict:
    """``targets`` (a frame's :class:`~ar_anchor.track.results.TargetResult` by name) with each member that its
    group's joint pose used this frame given the group's output composed with its layout (``replace(target, pose,
    reproj_px, state)`` makes the new result), when that pose reprojects the member's own corners within
    :data:`_MEMBER_SLACK_PX` of the member's own solution (a layout still off by a millimetre moves the
    member off its corners: its own pose is then better). ``layouts``: :meth:`~.learner.GroupLearner.layouts`; a
    member whose own track vouches for its pose (``tracked``) follows only a settled one that its
    orientation agrees with (:attr:`GroupLayout.agree`): on the real chessboard.avi, the pair evidence
    learns the slightly curled sheet as flat, and following such layouts made well-tracked members'
    relative rotations up to 30 % less steady.

    Whether or not the group's filter has decided its planar flip: undecided, its output is a best guess
    from 8 or more corners where each member's is one from four (at 2-3 m, a 6-marker sheet's guess is
    right where its members' flip). The member's state says which: ``tracked`` when its group is, or when
    the member's own track vouches for the solution the group's pose lies on (nearer its own output than
    its other solution); ``ambiguous`` otherwise. Others are unchanged."""
    out = dict(targets)
    for name, layout in layouts.items():
        group = targets.get(name)
        if group is None or not group.state.measured:
            continue
        for marker_id in group.markers_used:
            member = TargetId.marker(marker_id)
            own = targets.get(member)
            if own is None or not own.measured or marker_id not in layout.members:
                continue
            if camera is None or own.corners_in_image is None or not own.hypotheses:
                continue
            if own.state is TrackState.TRACKED and not (
                layout.settled and (layout.agree is None or marker_id in layout.agree)
            ):
                continue  # a member sure of its own pose: only a settled layout its orientation agrees with
            pose = group.pose.compose(layout.members[marker_id])
            reproj = reprojection_rms(
                pose, marker_corners_in_marker(own.length_m), own.corners_in_image.reshape(-1, 2), camera
            )
            if not reproj <= own.hypotheses[0].reproj_px + _MEMBER_SLACK_PX:
                continue  # the group's pose does not fit this member's corners as its own does: a layout error
            sure = group.state is TrackState.TRACKED or (own.state is TrackState.TRACKED and _on_own_branch(pose, own))
            out[member] = replace(own, pose, reproj, TrackState.TRACKED if sure else TrackState.AMBIGUOUS)
    return out


LAYOUT_DOUBT = "layout_disagrees"  # a learned group's joint pose agrees with fewer than two of the members seen


def disagrees_with_layout(solved: BoardPose) -> bool:
    """Did a group's joint solve see two members or more but find fewer than two that agree with its layout
    (``markers_used`` and ``outlier_ids``: seen, rejected)? Then this frame contradicts the layout, and its
    pose rests on one member's place in it, whichever RANSAC happened to pick."""
    used = len(solved.markers_used)
    return used < 2 <= used + len(solved.outlier_ids)


def doubt_layouts(targets: dict, names: set[TargetId] | frozenset[TargetId]) -> dict:
    """``targets`` (a frame's results by name) with each measured one of ``names`` (groups whose frame
    :func:`disagrees_with_layout`) not ``tracked``: ``ambiguous``, with the doubt :data:`LAYOUT_DOUBT` (which
    the offline replay keeps: see :mod:`ar_anchor.track.offline`). Poses are left as they are."""
    if not names:
        return targets
    out = dict(targets)
    for name in names:
        target = out.get(name)
        if target is None or not target.state.measured:
            continue
        doubts = target.doubts if LAYOUT_DOUBT in target.doubts else (*target.doubts, LAYOUT_DOUBT)
        out[name] = dataclasses.replace(target, state=TrackState.AMBIGUOUS, doubts=doubts)
    return out


def _on_own_branch(pose: Pose, own) -> bool:
    """Is ``pose`` nearer the member's own output than the member's other solution (the one farther from
    that output)? With one solution: yes."""
    if len(own.hypotheses) < 2:
        return True
    other = max(own.hypotheses, key=lambda h: angle_between_deg(h.pose.rotation, own.pose.rotation))
    return angle_between_deg(pose.rotation, own.pose.rotation) < angle_between_deg(pose.rotation, other.pose.rotation)
