"""How a config key is declared: once, as a dataclass field that carries its default, check and doc.

A TOML key is a field made by :func:`key`::

    length_m: float = key(0.05, "side of the black square, metres", positive)

The field's :class:`Key` (in ``field.metadata["key"]``) is all the rest of the package needs: the reader
(:mod:`.read`) reads the TOML key of the same name with its type, shape and check; the file writer
(:mod:`.document`) writes ``configs/default.toml`` from its default and doc. A field without a Key
(``TrackerConfig.source``, ``OverlayConfig.colour_set``) is not a TOML key, so a file cannot set it.

A :class:`Check` is a small named rule: ``problem(value, limit)`` says what is wrong with a value (None:
nothing), ``limit`` being the dictionary's marker count, which only the marker-id checks need. The reader
appends ``, got <value>`` to the problem unless the check's own message already shows the value.

:class:`ConfigValueError` is the error the reader raises: its message is the one line a user reads
(``file: [table] key: problem, got value``); its attributes carry the table, key, value and bare problem,
so that a caller that took the value from somewhere else (the CLI: a flag) can name it its own way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError

__all__ = [
    "REQUIRED",
    "Check",
    "ConfigValueError",
    "Key",
    "in_range",
    "key",
    "valid_marker_id",
    "non_negative",
    "one_of",
    "positive",
    "printable",
    "declared",
    "default_of",
    "table_keys",
]

REQUIRED: Any = dataclasses.MISSING  # key(REQUIRED, ...): no default, the reader insists on the key


class ConfigValueError(ConfigError):
    """A config key or value that cannot be used; ``str()`` is the whole one-line message.

    ``table`` (``"[markers]"``, ``"[[boards]] 'desk'"``; empty for a value from elsewhere), ``key``
    (None for problems of a whole table), ``value`` (the offending value, when there is one) and
    ``problem`` (the message without its location) are there for callers that say where it came from
    in their own words, e.g. the CLI's ``--dictionary: <problem>``.
    """

    def __init__(
        self, message: str, *, problem: str, key: str | None = None, table: str = "", value: Any = None
    ) -> None:
        super().__init__(message)
        self.problem = problem
        self.key = key
        self.table = table
        self.value = value


@dataclass(frozen=True)
class Check:
    """A rule a value must meet: ``text`` for people ("must be > 0"), ``problem`` for the reader."""

    text: str
    test: Callable[[Any, int], str | None]
    shows_value: bool = False  # the message names the value itself: no ", got ..." appended

    def problem(self, value: Any, limit: int = 0) -> str | None:
        return self.test(value, limit)


def _rule(text: str, ok: Callable[[Any], bool]) -> Check:
    return Check(text, lambda value, _limit: None if ok(value) else text)


positive = _rule("must be > 0", lambda v: v > 0)
non_negative = _rule("must be >= 0", lambda v: v >= 0)
printable = _rule("must not contain line breaks or control characters", lambda v: v.isprintable())


def in_range(lo: float, hi: float) -> Check:
    """A :class:`Check`: the value is in ``[lo, hi]``."""
    return _rule(f"must be in [{lo:g}, {hi:g}]", lambda v: lo <= v <= hi)


def one_of(names: tuple[str, ...] | dict[str, Any]) -> Check:
    """A :class:`Check`: the value is one of ``names``."""
    return _rule(f"must be one of {', '.join(names)}", lambda v: v in names)


def _marker_id(value: int, limit: int) -> str | None:
    return None if 0 <= value <= limit - 1 else f"must be in [0, {limit - 1}]"


valid_marker_id = Check("must be a marker id of the dictionary", _marker_id)


@dataclass(frozen=True)
class Key:
    """One TOML key: what it means (``doc``), its Python type and shape, and what a value must be.

    ``shape``: ``value`` (a scalar of ``kind``), ``ids`` (a list of marker ids), ``vector`` (``size``
    numbers, each in ``check``'s range), ``id_values`` (a sub-table: marker id -> ``kind``),
    ``table`` (a sub-table read into the dataclass ``kind``), ``tables`` (an array of tables, read by a
    special reader), ``inline`` (free-form, read by a special reader).
    """

    doc: str
    kind: type
    shape: str = "value"
    check: Check | None = None
    required: str = ""  # the problem when the key is missing ("": optional, it takes the default)
    example: Any = None  # what the written file shows (commented out) for a key whose default is empty
    size: int = 0  # vector: number of values


def key(
    default: Any,
    doc: str,
    check: Check | None = None,
    *,
    kind: type | None = None,
    shape: str = "value",
    required: str = "",
    example: Any = None,
    size: int = 0,
    factory: Callable[[], Any] | None = None,
) -> Any:
    """A dataclass field that is a TOML key (see the module doc); ``kind`` defaults to the default's type."""
    if kind is None:
        kind = type(default if factory is None else factory())
    spec = Key(doc, kind, shape, check, required, example, size)
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata={"key": spec})
    return dataclasses.field(default=default, metadata={"key": spec})


def table_keys(cls: type) -> Iterator[tuple[dataclasses.Field, Key]]:
    """The TOML keys of a dataclass (its fields with a :class:`Key`), in declaration order."""
    for item in dataclasses.fields(cls):
        spec = item.metadata.get("key")
        if spec is not None:
            yield item, spec


def declared(cls: type, name: str) -> tuple[dataclasses.Field, Key]:
    """The field and Key of TOML key ``name`` of dataclass ``cls``."""
    for item, spec in table_keys(cls):
        if item.name == name:
            return item, spec
    raise KeyError(f"{cls.__name__} declares no key {name!r}")


def default_of(item: dataclasses.Field) -> Any:
    """A field's default value (built by its factory if it has one)."""
    if item.default_factory is not dataclasses.MISSING:
        return item.default_factory()
    return item.default
