"""Lengths as typed on the command line (:mod:`ar_anchor.units`): a unit or the option's own, and the
errors that list the accepted forms."""

from __future__ import annotations

import argparse
import math

import pytest

from ar_anchor.units import LengthError, length_option, parse_length


@pytest.mark.parametrize(
    ("text", "bare", "to", "expected"),
    [
        ("50mm", "m", None, 0.05),
        ("5cm", "m", None, 0.05),
        ("0.05m", "m", None, 0.05),
        ("0.05", "m", None, 0.05),  # a bare number keeps the option's unit: metres ...
        ("50", "mm", None, 50.0),  # ... or millimetres
        ("5cm", "mm", None, 50.0),
        ("0.05m", "mm", None, 50.0),
        ("50 MM", "m", None, 0.05),  # a space and any case
        (" 2.5Cm ", "mm", None, 25.0),
        ("1e-2m", "mm", None, 10.0),
        (".5m", "m", None, 0.5),
        ("50", "m", "mm", 50000.0),  # read in metres, returned in millimetres
        ("22mm", "m", "mm", 22.0),
        ("-3cm", "m", None, -0.03),  # the sign is the caller's to check
    ],
)
def test_a_length_with_or_without_its_unit(text: str, bare: str, to: str | None, expected: float) -> None:
    assert math.isclose(parse_length(text, bare, to=to), expected, rel_tol=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("5 inches", r"unknown unit 'inches': expected a length such as 50mm, 5cm or 0.05m"),
        ("5in", r"unknown unit 'in'"),
        ("5 km", r"unknown unit 'km'"),
        ("abc", r"expected a length such as 50mm, 5cm or 0.05m \(a bare number is in metres\), got 'abc'"),
        ("", r"got ''"),
        ("mm", r"got 'mm'"),
        ("5 m m", r"got '5 m m'"),
        ("nan", r"got 'nan'"),
        ("inf", r"got 'inf'"),
        ("1e999m", r"got '1e999m'"),
        ("5,0mm", r"got '5,0mm'"),
    ],
)
def test_anything_else_is_refused_with_the_accepted_forms(text: str, message: str) -> None:
    with pytest.raises(LengthError, match=message):
        parse_length(text, "m")


def test_the_bare_unit_is_named_in_the_error() -> None:
    with pytest.raises(LengthError, match=r"a bare number is in millimetres"):
        parse_length("x", "mm")


def test_an_unknown_option_unit_is_a_programming_error() -> None:
    with pytest.raises(ValueError, match="unit must be one of"):
        parse_length("5", "in")


def test_the_argparse_type_checks_the_bounds_in_the_returned_unit() -> None:
    positive = length_option("m")
    assert positive("5cm") == pytest.approx(0.05)
    for bad in ("0", "0mm", "-1cm"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"must be a length > 0 m"):
            positive(bad)
    near = length_option("m", low=0.02, high=100.0, inclusive=True)
    assert near("2cm") == pytest.approx(0.02) and near("100m") == 100.0
    with pytest.raises(argparse.ArgumentTypeError, match=r"must be a length >= 0.02 m and <= 100 m, got '1cm'"):
        near("1cm")
    with pytest.raises(argparse.ArgumentTypeError, match=r"<= 100 m, got '101'"):
        near("101")
    millimetres = length_option("m", to="mm")
    assert millimetres("0.05") == pytest.approx(50.0) and millimetres("5cm") == pytest.approx(50.0)
    with pytest.raises(argparse.ArgumentTypeError, match=r"unknown unit 'inches'"):
        millimetres("2 inches")
