"""The error module's helpers."""

from __future__ import annotations

from ar_anchor.errors import printable


def test_printable_escapes_what_would_move_or_colour_the_terminal():
    raw = "a\nb\r\x1b[31mred\x7f" + b"\xff".decode("utf-8", "surrogateescape")
    shown = printable(raw)
    assert shown == "a\\nb\\r\\x1b[31mred\\x7f\\udcff"
    assert all(ch.isprintable() for ch in shown)


def test_printable_leaves_ordinary_names_alone():
    assert printable("clip é ✓ (1).mp4") == "clip é ✓ (1).mp4"
    assert printable(123) == "123"
