"""OpenCV's names the config speaks: predefined ArUco dictionaries and corner refinements.

Dictionary names are case-insensitive on input (``dict_4x4_50`` works) and listed in one canonical
spelling per dictionary (OpenCV exposes both ``DICT_APRILTAG_16h5`` and ``DICT_APRILTAG_16H5``).
"""

from __future__ import annotations

import cv2

from .keys import ConfigValueError

__all__ = ["CORNER_REFINEMENTS", "dictionary_id", "dictionary_names", "dictionary_size"]

# OpenCV's refinement per option; "edges" is ours (ar_anchor.track.corners), run on unrefined corners
CORNER_REFINEMENTS = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


def dictionary_names() -> list[str]:
    """Names of cv2.aruco's predefined dictionaries (``DICT_4X4_50``, ...), canonical spelling."""
    names = [n for n in dir(cv2.aruco) if n.startswith("DICT_")]
    by_value: dict[int, str] = {}
    for name in sorted(names):
        by_value.setdefault(int(getattr(cv2.aruco, name)), name)
    return sorted(by_value.values())


def dictionary_id(name: str) -> int:
    """cv2.aruco constant for a predefined dictionary name (case-insensitive); an unknown name is a
    :class:`~ar_anchor.config.keys.ConfigValueError` with ``key="dictionary"`` and the name as value."""
    lookup = {n.upper(): n for n in dir(cv2.aruco) if n.startswith("DICT_")}
    key = name.upper() if isinstance(name, str) else ""
    if key not in lookup:
        problem = f"unknown dictionary {name!r} (known: {', '.join(dictionary_names())})"
        raise ConfigValueError(problem, problem=problem, key="dictionary", value=name)
    return int(getattr(cv2.aruco, lookup[key]))


def dictionary_size(name: str) -> int:
    """Number of markers in a predefined dictionary."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary_id(name)).bytesList.shape[0])
