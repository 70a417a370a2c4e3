"""Tracker configuration: TOML read into validated, frozen dataclasses, each key declared once.

- :mod:`.keys`: how a key is declared (a dataclass field with its default, check and doc) and the
  error a bad one raises (:class:`ConfigValueError`: one line naming file, table and key; the key and
  value as attributes);
- :mod:`.model`: the tables (``[detector]``, ``[markers]``, ``[pose]``, ``[filter]``, ``[recording]``,
  ``[[overlays]]``) and :class:`TrackerConfig`; :mod:`.board`: ``[[boards]]``;
- :mod:`.read`: one generic reader plus the special cases (boards, overlays, per-id lengths);
- :mod:`.document`: writes ``configs/default.toml`` and ``configs/demo.toml`` from the declarations
  (``python -m ar_anchor.config.document configs``; a test keeps the files equal to it);
- :mod:`.dictionaries`: OpenCV's dictionary and corner-refinement names.

``TrackerConfig()`` (what runs without ``--config``) is exactly ``configs/default.toml``. In a config
file every scalar key is optional and takes that default, but the lists are what the file says: a
file without ``[[boards]]`` has no boards, one without ``[markers.lengths_m]`` has no per-id sizes.
"""

from __future__ import annotations

from . import model
from .board import BOARD_KINDS, BoardConfig
from .dictionaries import CORNER_REFINEMENTS, canonical_dictionary, dictionary_id, dictionary_names, dictionary_size
from .keys import ConfigValueError
from .model import *  # noqa: F403 - model.__all__, exported as this package's own (below)
from .read import load_config, parse_config

__all__ = [
    "BOARD_KINDS",
    "CORNER_REFINEMENTS",
    "BoardConfig",
    "ConfigValueError",
    "canonical_dictionary",
    "dictionary_id",
    "dictionary_names",
    "dictionary_size",
    "load_config",
    "parse_config",
]
__all__ += model.__all__  # the tables, TrackerConfig, the demo's config
