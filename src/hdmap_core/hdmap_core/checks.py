"""One range check shared by every configuration dataclass, and the fixed rules a switch turns on.

Each stage config's ``__post_init__`` names its fields and their allowed interval once, e.g.
``check_range(self, ("step_m", "margin_m"), low=0.0, low_open=True)``; the error says which config,
which field, the interval and the value given, the same way for every config.

A rule that was measured and adopted is a constant, not a field. Where the paper (or a preset)
does without it, one public switch of the stage turns a family of such rules off: each is a
:class:`Rule` of the config class, its value while the switch is on and its "off" value (the
paper's) otherwise; stage code reads it as an attribute like a field (``config.track_search_m``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Generic, TypeVar, overload

from hdmap_core.errors import ConfigError

__all__ = ["Rule", "check_range", "check_choice"]

T = TypeVar("T")


class Rule(Generic[T]):
    """A fixed rule of a config class: ``on`` while the instance's bool field ``switch`` is true,
    ``off`` (the paper: the rule does nothing) otherwise. Not a field: ``--set`` cannot reach it.

    Example: ``track_search_m = Rule("track_links", 60.0, 0.0)`` in ``StitchConfig``.
    """

    def __init__(self, switch: str, on: T, off: T) -> None:
        self.switch, self.on, self.off = switch, on, off
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> Rule[T]: ...
    @overload
    def __get__(self, obj: object, owner: type | None = None) -> T: ...
    def __get__(self, obj: object | None, owner: type | None = None) -> T | Rule[T]:
        if obj is None:
            return self
        return self.on if getattr(obj, self.switch) else self.off

    def __repr__(self) -> str:
        return f"{self.on!r} with {self.switch} (off: {self.off!r})"


def _interval(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    if low is None and high is None:
        return "a number"
    if high is None:
        return f"{'>' if low_open else '>='} {low:g}"
    if low is None:
        return f"{'<' if high_open else '<='} {high:g}"
    return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


def check_range(
    config: object,
    names: Iterable[str],
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    finite: bool = False,
    integer: bool = False,
) -> None:
    """Raise ``ConfigError`` unless every field in ``names`` of ``config`` lies in the interval.

    Args:
        config: a dataclass instance (its class name prefixes the message).
        names: field names to check.
        low, high: bounds (None: unbounded on that side).
        low_open, high_open: exclude the bound itself.
        finite: also refuse inf (NaN is always refused).
        integer: the value must be an ``int`` (not a bool).

    Raises:
        ConfigError: "<Config>.<field> must be <finite and> <interval>, got <value>".
    """
    for name in (names,) if isinstance(names, str) else names:
        value = getattr(config, name)
        if integer:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)
        if ok and finite:
            ok = math.isfinite(value)
        if ok and low is not None:
            ok = value > low if low_open else value >= low
        if ok and high is not None:
            ok = value < high if high_open else value <= high
        if not ok:
            what = ("an integer " if integer else "") + ("finite and " if finite else "")
            interval = _interval(low, high, low_open, high_open)
            raise ConfigError(f"{type(config).__name__}.{name} must be {what}{interval}, got {value!r}")


def check_choice(config: object, name: str, choices: Iterable[str]) -> None:
    """Raise ``ConfigError`` unless the field ``name`` of ``config`` is one of ``choices``."""
    value = getattr(config, name)
    options = tuple(choices)
    if value not in options:
        raise ConfigError(f"{type(config).__name__}.{name} must be one of {options}, got {value!r}")
