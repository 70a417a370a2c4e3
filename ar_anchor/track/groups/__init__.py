"""Rigid groups learned while tracking: lone markers that move together are solved together.

Users stick several markers on one sheet, wall or object and rarely write a board layout for them. Each
lone marker then flips and jitters alone, though its neighbours, seen in the same frame, settle its pose.
With ``[groups] learn = true`` (``--learn-groups``) the tracker learns such groups as it goes:

1. **Pairs** (:class:`~.evidence.Pair`). For two lone markers measured in one frame, every combination of their
   validated IPPE solutions gives a candidate relative pose ``i_from_j`` (up to four: the planar flip of
   each). The true one recurs frame after frame; a flipped one moves with the viewpoint. A pair keeps a
   few *modes* (running means of candidates). A frame supports a mode when the two markers' eight
   corners fit it jointly: one camera pose, refined by Levenberg-Marquardt from either of the first
   marker's solutions, reprojects them within ``[groups] agree_px`` RMS. A joint fit, not a comparison
   of the two lone poses: a lone marker's rotation is often degrees off, the pair's corners are not.
   When no mode fits, the frame's candidates start new ones. Each marker is paired with its
   :data:`~.learner._NEIGHBOURS` nearest in the image (the cost stays linear in the markers seen). Markers of a
   configured board are solved with it and never learned.
2. **Rigid** when a mode has held ``min_frames`` frames, in at least ``agreement`` of the frames that saw
   both since it first appeared, and its frames' candidates agree on one relative rotation
   (:meth:`~.evidence.Mode._consensus`: a vote, decided only when no other rotation comes near its support). That
   vote is where viewpoints count: the flipped candidates move with the viewpoint and the true one stays,
   so markers in different planes seen from one viewpoint only keep two rotations level and never join;
   markers in one plane have the flip-free planar candidate, which needs no second viewpoint. Two objects
   moving independently keep changing their relative pose, so no mode of theirs lasts. Two objects that
   only stand still together look exactly like one rigid object (nothing in the images tells them apart
   while nothing moves): they are grouped, the event says the evidence is a constant pose across
   viewpoints, and the first one to move leaves (4).
3. **Groups**: rigid pairs link markers into groups (a rigid pair with a member adds a marker; one
   between two groups merges them). A group's layout is its members' poses in the group's frame: turned
   as its anchor (its first marker), centred on its members' corners
   (:meth:`~.layout.LearnedGroup.recentre`); a layout whose markers lie in one plane (within
   :data:`~.layout._PLANAR_SHARE` of its extent, normals within :data:`~.layout._PLANAR_TILT_DEG`) is made
   exactly planar, so the group is solved as a planar board (both IPPE solutions kept). Each group is a
   target of its own, ``board:group-N``, solved like a board (:class:`~ar_anchor.track.pose.BoardSolver`:
   RANSAC over its members' corners, then LM on the inliers) and passed through the same flip filter. When
   a group forms or grows, the tracker does not start it from nothing: a planar group's layout is refined
   at once from the frames kept (:meth:`~.learner.GroupLearner.remember`, the last ``[filter]
   evidence_window_s``; :meth:`~.learner.GroupLearner.refine_from_past`) and its flip filter is replayed
   over its joint pose in each (:meth:`~.learner.GroupLearner.past_solves`). Its layout is then refined
   every :data:`~.learner._REFINE_EVERY` frames from the frames where three members or more fix the
   group's pose (each member's pose in the group's frame, averaged: a planar group's from any such frame,
   a non-planar group's only while it is ``tracked``; see :meth:`~.learner.GroupLearner._sample`), until a
   refinement moves no corner more than :data:`~.learner._SETTLED_M`: it has *settled*.
4. **Members** (:func:`~.members.members_from_groups`): a member measured this frame and used by its
   group's joint pose outputs the group's output composed with its layout (``tracked`` when the group or
   its own track vouches for it, else ``ambiguous``) if that fits its corners, and if the layout is one to
   follow (:meth:`~.learner.GroupLearner.layouts`): a member unsure of its own pose follows a settled or a
   planar (flat) layout; one whose own track vouches for it only a settled layout whose orientation for it
   agrees with its own solutions over recent frames (:meth:`~.layout.LearnedGroup.agrees`: the pair
   evidence sees a curled sheet as flat). Otherwise its own lone track's output stands (its lone track
   keeps running, so a member that leaves goes on as before). A member the joint pose rejects
   ``leave_frames`` measured frames in a row leaves (its pair evidence with the group is forgotten); a
   group left with one marker, or whose joint pose agrees with fewer than two of the members it sees for
   ``leave_frames`` frames, dissolves.

Joins, leaves, merges and dissolutions are :class:`~ar_anchor.track.filtering.TrackEvent` (kind ``group``)
on the group's and the members' results, so they reach the log and rerun's ``events``.

The package, by step: :mod:`.evidence` (pairs, their modes, when a pair is rigid), :mod:`.layout` (a group's
layout and board solver, and the samples that refine it), :mod:`.learner` (:class:`GroupLearner`: groups formed,
grown, merged, solved, left and dissolved, layouts refined), :mod:`.members` (members given their group's pose,
groups whose frame contradicts their layout).
"""

from .layout import GROUP_PREFIX, LearnedGroup, is_learned_group
from .learner import GroupLearner
from .members import LAYOUT_DOUBT, GroupLayout, disagrees_with_layout, doubt_layouts, members_from_groups

__all__ = [
    "GROUP_PREFIX",
    "LAYOUT_DOUBT",
    "GroupLayout",
    "GroupLearner",
    "LearnedGroup",
    "disagrees_with_layout",
    "doubt_layouts",
    "is_learned_group",
    "members_from_groups",
]
