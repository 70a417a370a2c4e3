"""Lengths as the user types them: ``50mm``, ``5cm``, ``0.05m`` or a bare number in the option's own unit.

Every length option of the command line reads its value through :func:`parse_length` (its argparse
type is :func:`length_option`, ``length`` in :mod:`ar_anchor.cli.options`), so a marker side can be
given in whichever unit is at hand, and a bare number keeps the unit the option always had (metres
for ``--marker-length``, millimetres for ``markers --size-mm``). The unit follows the number, with or
without a space, in any case; nothing but ``mm``, ``cm`` and ``m`` is read (an inch is not a guess
worth making).
"""

from __future__ import annotations

import argparse
import math
import re

__all__ = ["LENGTH_FORMS", "UNITS_M", "LengthError", "length_option", "parse_length"]

# metres per unit
UNITS_M = {"mm": 0.001, "cm": 0.01, "m": 1.0}

LENGTH_FORMS = "50mm, 5cm or 0.05m"  # the accepted forms, as errors list them

_LENGTH = re.compile(r"\s*(?P<number>[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>[^\d\s.+-][^\s]*)?\s*")


class LengthError(ValueError):
    """A length that cannot be read; the message says why and lists the accepted forms."""


def parse_length(text: str, bare_unit: str = "m", *, to: str | None = None) -> float:
    """The length ``text`` in ``to`` (default: ``bare_unit``): ``"50mm"``, ``"5 cm"``, ``"0.05M"``, or a bare
    number read in ``bare_unit`` (``"mm"``, ``"cm"`` or ``"m"``). The value must be finite; its sign is
    the caller's to check. :class:`LengthError` for anything else (``"5 inches"``, ``"abc"``, ``"nan"``)."""
    for unit in (bare_unit, to):
        if unit is not None and unit not in UNITS_M:
            raise ValueError(f"unit must be one of {', '.join(UNITS_M)}, got {unit!r}")
    bare_name = _UNIT_NAMES[bare_unit]
    forms = f"expected a length such as {LENGTH_FORMS} (a bare number is in {bare_name})"
    match = _LENGTH.fullmatch(str(text))
    if match is None:
        raise LengthError(f"{forms}, got {text!r}")
    unit = (match["unit"] or bare_unit).lower()
    if unit not in UNITS_M:
        raise LengthError(f"unknown unit {match['unit']!r}: {forms}, got {text!r}")
    value = float(match["number"]) * UNITS_M[unit] / UNITS_M[to or bare_unit]
    if not math.isfinite(value):
        raise LengthError(f"{forms}, got {text!r}")
    return value


def length_option(
    bare: str = "m", *, to: str | None = None, low: float = 0.0, high: float | None = None, inclusive: bool = False
):
    """An argparse type: a length ``> low`` (``>=`` when ``inclusive``; and ``<= high``), typed as ``50mm``,
    ``5cm``, ``0.05m`` or a bare number in ``bare`` (the option's own unit, ``"m"`` or ``"mm"``), returned in
    ``to`` (default ``bare``); :mod:`ar_anchor.units` reads it. The bounds are in ``to``."""
    unit = to or bare

    def parse(text: str) -> float:
        try:
            value = parse_length(text, bare, to=unit)
        except LengthError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
        if not (value >= low if inclusive else value > low) or (high is not None and value > high):
            bounds = f"{'>=' if inclusive else '>'} {low:g} {unit}" + (f" and <= {high:g} {unit}" if high else "")
            raise argparse.ArgumentTypeError(f"must be a length {bounds}, got {text!r}")
        return value

    return parse


_UNIT_NAMES = {"mm": "millimetres", "cm": "centimetres", "m": "metres"}
