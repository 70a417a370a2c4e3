"""OpenCV's names the config speaks: predefined ArUco dictionaries and corner refinements.

A dictionary is named in one place, :func:`canonical_dictionary`, for the command line and the config
alike. It reads OpenCV's names in any case (``dict_4x4_50``), without the ``DICT_`` prefix (``4x4_50``),
AprilTag families as the AprilTag library names them (``tag36h11``, ``36h11``, ``apriltag_36h11``) and
``original`` for ``DICT_ARUCO_ORIGINAL``; everything is stored and written in OpenCV's canonical
spelling, one per dictionary (OpenCV exposes both ``DICT_APRILTAG_16h5`` and ``DICT_APRILTAG_16H5``).
"""

from __future__ import annotations

import cv2

from .keys import ConfigValueError

__all__ = ["CORNER_REFINEMENTS", "canonical_dictionary", "dictionary_id", "dictionary_names", "dictionary_size"]

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


# short names: the AprilTag library's family names (tag36h11), and the ArUco library's original dictionary
_ALIASES = {"ORIGINAL": "ARUCO_ORIGINAL", "MIP_36H12": "ARUCO_MIP_36H12"}
_ALIASES |= {f"TAG{family}": f"APRILTAG_{family}" for family in ("16H5", "25H9", "36H10", "36H11")}
_ALIASES |= {family: f"APRILTAG_{family}" for family in ("16H5", "25H9", "36H10", "36H11")}

ACCEPTED_FORMS = (
    "DICT_4X4_50 or 4x4_50 (4x4 to 7x7, 50/100/250/1000 markers), tag16h5, tag25h9, tag36h10, tag36h11 "
    "(or 36h11, apriltag_36h11), original (DICT_ARUCO_ORIGINAL), mip_36h12; any case"
)


def canonical_dictionary(name: str) -> str:
    """OpenCV's canonical name (``DICT_APRILTAG_36H11``) of any spelling the config reads: ``DICT_4X4_50``,
    ``dict_4x4_50``, ``4x4_50``, ``tag36h11``, ``36h11``, ``apriltag_36h11``, ``original``. An unknown name is
    a :class:`~ar_anchor.config.keys.ConfigValueError` with ``key="dictionary"``, listing the accepted forms
    and suggesting the closest name."""
    by_upper = {n.upper(): n for n in dictionary_names()}
    key = name.strip().upper().replace("-", "_") if isinstance(name, str) else ""
    key = key.removeprefix("DICT_")
    key = _ALIASES.get(key, key)
    if f"DICT_{key}" in by_upper:
        return by_upper[f"DICT_{key}"]
    raise ConfigValueError(_unknown(name), problem=_unknown(name), key="dictionary", value=name)


def _unknown(name: object) -> str:
    import difflib

    known = dictionary_names()
    spelled = [n.removeprefix("DICT_").lower() for n in known] + [a.lower() for a in _ALIASES]
    typed = str(name).strip().lower().removeprefix("dict_")
    close = difflib.get_close_matches(typed, spelled, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown dictionary {name!r} (known: {ACCEPTED_FORMS}){hint}"


def dictionary_id(name: str) -> int:
    """cv2.aruco constant for a predefined dictionary, any spelling :func:`canonical_dictionary` reads; an
    unknown name is a :class:`~ar_anchor.config.keys.ConfigValueError` with ``key="dictionary"``."""
    return int(getattr(cv2.aruco, canonical_dictionary(name)))


def dictionary_size(name: str) -> int:
    """Number of markers in a predefined dictionary."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary_id(name)).bytesList.shape[0])
