"""Checks of single values: numbers, booleans, strings, choices, lists, null.

A check says what it allows (``describe()``) and validates a value when called, returning it
(typed: a list becomes a tuple) or raising :class:`~femcal.settings._messages.Invalid` with
what was allowed and what was given.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from femcal.settings._messages import BAD, Context, Index, Invalid, closest, dotted, got, yaml_repr


class Check:
    """A check of one value: ``describe()`` says what is allowed, calling it validates."""

    def describe(self) -> str:
        raise NotImplementedError

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        raise NotImplementedError

    def fail(self, value: Any, extra: str = "") -> Invalid:
        return Invalid(f"expected {self.describe()}, got {got(value)}{extra}")

    def mapping(self, value: Any) -> Mapping:
        """``value`` as an open mapping (null is empty); anything else fails this check."""
        if value is None:
            return {}
        if not isinstance(value, Mapping):
            raise self.fail(value)
        return value


def _interval(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return ""


class Int(Check):
    """An integer (not a bool) in ``[lo, hi]``."""

    def __init__(self, lo: int | None = None, hi: int | None = None) -> None:
        self.lo, self.hi = lo, hi

    def describe(self) -> str:
        bounds = _interval(self.lo, self.hi, False, False)
        return f"an integer {bounds}".rstrip()

    def __call__(self, value: Any, path: tuple, ctx: Context) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(value)
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise self.fail(value)
        return int(value)


class Float(Check):
    """A finite number (a YAML int or float, not a bool) in the given interval."""

    def __init__(
        self,
        lo: float | None = None,
        hi: float | None = None,
        *,
        lo_open: bool = False,
        hi_open: bool = False,
    ) -> None:
        self.lo, self.hi, self.lo_open, self.hi_open = lo, hi, lo_open, hi_open

    def describe(self) -> str:
        bounds = _interval(self.lo, self.hi, self.lo_open, self.hi_open)
        return f"a number {bounds}".rstrip()

    def __call__(self, value: Any, path: tuple, ctx: Context) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(value)
        if not math.isfinite(value):
            raise self.fail(value)
        x = float(value)
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            raise self.fail(value)
        if self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi):
            raise self.fail(value)
        return x


class Bool(Check):
    """``true`` or ``false``."""

    def describe(self) -> str:
        return "true or false"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> bool:
        if not isinstance(value, bool):
            raise self.fail(value)
        return value


class Str(Check):
    """A non-empty string; ``what`` names it in messages (e.g. "a path")."""

    def __init__(self, what: str = "a non-empty string") -> None:
        self.what = what

    def describe(self) -> str:
        return self.what

    def __call__(self, value: Any, path: tuple, ctx: Context) -> str:
        if not isinstance(value, str) or not value.strip():
            raise self.fail(value)
        return value


class Choice(Check):
    """One of a fixed set of values; a close miss is named."""

    def __init__(self, choices: Iterable[Any]) -> None:
        self.choices = tuple(choices)

    def describe(self) -> str:
        return "one of " + ", ".join(yaml_repr(c) for c in self.choices)

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        if isinstance(value, bool) or value not in self.choices:
            extra = ""
            if isinstance(value, str):
                close = closest(value, [str(c) for c in self.choices])
                if close is not None:
                    extra = f"; did you mean {close!r}?"
            raise self.fail(value, extra)
        return value


class KeyChoice(Check):
    """A key of an open mapping that must be one of ``choices`` (a close miss is named)."""

    def __init__(self, choices: Iterable[str], what: str) -> None:
        self.choices, self.what = tuple(choices), what

    def describe(self) -> str:
        return f"{self.what} ({', '.join(self.choices)})"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        if value in self.choices:
            return value
        close = closest(str(value), self.choices)
        if close is not None:
            raise Invalid(f"unknown {self.what}; did you mean {dotted((*path[:-1], close))}?")
        raise Invalid(f"unknown {self.what}; valid here: {', '.join(self.choices)}")


class Nullable(Check):
    """``null`` or what ``inner`` accepts."""

    def __init__(self, inner: Check) -> None:
        self.inner = inner

    def describe(self) -> str:
        return f"{self.inner.describe()} or null"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        if value is None:
            return None
        try:
            return self.inner(value, path, ctx)
        except Invalid as exc:
            prefix = f"expected {self.inner.describe()},"
            text = str(exc)
            if text.startswith(prefix):
                text = f"expected {self.describe()}," + text[len(prefix) :]
            raise Invalid(text) from None


class ListOf(Check):
    """A YAML list whose items each pass ``item``; returned as a tuple."""

    def __init__(self, item: Check, *, min_len: int = 0, unique: bool = False) -> None:
        self.item, self.min_len, self.unique = item, min_len, unique

    def describe(self) -> str:
        size = "a non-empty list" if self.min_len == 1 else "a list"
        if self.min_len > 1:
            size = f"a list of at least {self.min_len} items"
        unique = ", no repeats" if self.unique else ""
        return f"{size} (each item {self.item.describe()}{unique})"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        if not isinstance(value, list | tuple) or len(value) < self.min_len:
            raise self.fail(value)
        out = [ctx.check(self.item, v, (*path, Index(i))) for i, v in enumerate(value)]
        if self.unique:
            seen: list[Any] = []
            for v in value:
                if v in seen:
                    raise Invalid(
                        f"{yaml_repr(v)} is listed twice in {yaml_repr(value)}; list each once"
                    )
                seen.append(v)
        return BAD if any(v is BAD for v in out) else tuple(out)


class FnCheck(Check):
    """A check by a function ``fn(value, path, ctx)``; ``describe`` says what it allows."""

    def __init__(self, describe: str, fn: Callable[[Any, tuple, Context], Any]) -> None:
        self._describe, self.fn = describe, fn

    def describe(self) -> str:
        return self._describe

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        return self.fn(value, path, ctx)
