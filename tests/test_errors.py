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


def test_printable_escapes_bidirectional_controls():
    # given a name that a right-to-left override shows as "clip4pm.jpg", and every other bidi control
    bidi = [0x061C, 0x200E, 0x200F, *range(0x202A, 0x202F), *range(0x2066, 0x206A)]
    raw = "clip\u202egpj.mp4" + "".join(chr(code) for code in bidi)
    # when
    shown = printable(raw)
    # then: each is spelled out, nothing reorders the line
    assert shown == "clip\\u202egpj.mp4" + "".join(f"\\u{code:04x}" for code in bidi)
    assert not any(ord(ch) in bidi for ch in shown)
    # and letters of right-to-left scripts are left alone
    assert printable("שלום.mp4") == "שלום.mp4"
