"""Who a pose is about, and what the tracker says of it: :class:`TargetId` and :class:`TrackState`.

A target is a single marker (``marker:<id>``) or a rigid board (``board:<name>``). Its name is the
key of :attr:`FrameResult.targets <ar_anchor.track.results.FrameResult.targets>`, the ``target``
column of ``poses.csv`` and the entity path in rerun, so it is a string; :class:`TargetId` is that
string with its parts and one ordering attached, and the only place a name is built or parsed.
Patterns (``marker:*``, ``board:*``, ``*``) select targets for overlays.

Ordering, everywhere (poses.csv rows, filter updates, with and without ``--no-filter``): boards
before markers, markers by numeric id, boards by name.
"""

from __future__ import annotations

import enum
from typing import Literal

__all__ = ["KINDS", "TargetId", "TrackState", "target_pattern_problem"]

KINDS = ("marker", "board")
Kind = Literal["marker", "board"]


class TargetId(str):
    """A target's name, ``marker:<id>`` or ``board:<name>``; compares and hashes as that string.

    >>> TargetId.marker(3), TargetId.board("desk").kind
    ('marker:3', 'board')
    >>> TargetId.ordered([TargetId.marker(10), "marker:2", TargetId.board("desk")])
    ['board:desk', 'marker:2', 'marker:10']
    """

    __slots__ = ()

    def __new__(cls, kind: Kind, name: str | int) -> TargetId:
        name = str(name)
        if kind not in KINDS:
            raise ValueError(f"a target kind is 'marker' or 'board', got {kind!r}")
        if kind == "marker" and not (name.isdigit() and name.isascii()):
            raise ValueError(f"a marker id is a non-negative integer, got {name!r}")
        if kind == "board" and (not name or ":" in name or "*" in name):
            raise ValueError(f"a board name is non-empty without ':' or '*', got {name!r}")
        if kind == "marker" and len(name) > 18:  # (Python refuses int() of 4300 digits and more)
            raise ValueError(f"a marker id has at most 18 digits, got one of {len(name)}")
        if kind == "marker" and name != str(int(name)):
            raise ValueError(f"write marker:{int(name)}, not marker:{name}")
        return super().__new__(cls, f"{kind}:{name}")

    def __reduce__(self) -> tuple[object, tuple[str, str]]:  # pickled as its parts (results spooled to disk)
        return (TargetId, (self.kind, self.name))

    @classmethod
    def marker(cls, marker_id: int) -> TargetId:
        return cls("marker", int(marker_id))

    @classmethod
    def board(cls, name: str) -> TargetId:
        return cls("board", name)

    @classmethod
    def parse(cls, text: str) -> TargetId:
        """``marker:<id>`` or ``board:<name>``; ValueError naming what is wrong otherwise."""
        if isinstance(text, TargetId):
            return text
        kind, sep, name = str(text).partition(":")
        if not sep or kind not in KINDS:
            raise ValueError(f'a target is "marker:<id>" or "board:<name>", got {text!r}')
        return cls(kind, name)  # type: ignore[arg-type]

    @property
    def kind(self) -> Kind:
        return self.partition(":")[0]  # type: ignore[return-value]

    @property
    def name(self) -> str:
        return self.partition(":")[2]

    @property
    def marker_id(self) -> int | None:
        """The marker's id, None for a board."""
        return int(self.name) if self.kind == "marker" else None

    @property
    def path_part(self) -> str:
        """``marker_3``: the name as one part of an entity path (rerun) or a file name."""
        return f"{self.kind}_{self.name}"

    @property
    def is_board(self) -> bool:
        return self.kind == "board"

    def sort_key(self) -> tuple[str, int, str]:
        """Boards first (by name), then markers by numeric id."""
        return (self.kind, self.marker_id if self.marker_id is not None else -1, self.name)

    def matches(self, pattern: str) -> bool:
        """Does ``pattern`` (``*``, ``marker:*``, ``board:*`` or a target name) select this target?"""
        return pattern == "*" or pattern == f"{self.kind}:*" or pattern == self

    @staticmethod
    def ordered(names) -> list[TargetId]:
        """Names (strings or TargetIds) as TargetIds, in the one order."""
        return sorted((TargetId.parse(n) for n in names), key=TargetId.sort_key)


def target_pattern_problem(pattern: object) -> str | None:
    """Why ``pattern`` selects no target (None when it is valid): ``marker:<id>``, ``board:<name>``,
    ``marker:*``, ``board:*`` or ``*``."""
    if pattern in ("*", "marker:*", "board:*"):
        return None
    try:
        TargetId.parse(str(pattern))
    except ValueError as exc:
        return f'must be "marker:<id>", "board:<name>", "marker:*", "board:*" or "*" ({exc})'
    return None


class TrackState(str, enum.Enum):
    """What the tracker says of a target's pose in one frame (the ``state`` column of poses.csv).

    - ``tracked``: measured this frame and the planar flip is resolved: the pose is vouched for.
    - ``ambiguous``: measured, but the flip is not (yet) decided, or this frame is not trusted
      (blur, outlier, close call): the pose is the best available, not a promise.
    - ``predicted``: not measured this frame; a short, damped prediction through a gap.
    - ``interpolated``: not measured this frame; offline replay only (:mod:`ar_anchor.track.offline`):
      a gap bridged between the measured poses on either side of it.
    """

    TRACKED = "tracked"
    AMBIGUOUS = "ambiguous"
    PREDICTED = "predicted"
    INTERPOLATED = "interpolated"

    __str__ = str.__str__
    __format__ = str.__format__
    __hash__ = str.__hash__  # a TrackState and its text are the same dict key

    @property
    def measured(self) -> bool:
        return self is not TrackState.PREDICTED and self is not TrackState.INTERPOLATED
