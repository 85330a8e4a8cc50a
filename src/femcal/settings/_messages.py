"""Problems and their messages: what was given, where, and the closest valid key.

:class:`Invalid` is raised by a check, :data:`BAD` stands for a value whose problem is
recorded, and a :class:`Context` collects the problems of one validation run so that every
problem is reported at once. The helpers write the parts every message shares: the dotted
path of a key, what was given (``'ten' (str)``) and the "did you mean" of an unknown key.

The ``_``-prefixed modules are private to :mod:`femcal.settings`; their names carry no
underscore for that reason.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from femcal.settings._checks import Check


class Invalid(Exception):
    """A value failed its check; the message says what is allowed and what was given."""


BAD = object()  # a value that failed its check (the problem is already recorded)


class Index(int):
    """A list position in a path (shown as ``[i]``, unlike an integer mapping key)."""


def yaml_repr(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_name(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, Mapping):
        return "mapping"
    return type(value).__name__


def got(value: Any) -> str:
    """``'ten' (str)``: what was given, as the message shows it."""
    return f"{yaml_repr(value)} ({_type_name(value)})"


def dotted(path: tuple) -> str:
    out = ""
    for key in path:
        if isinstance(key, Index):
            out += f"[{int(key)}]"
        else:
            out += ("." if out else "") + str(key)
    return out


def _similarity(a: str, b: str) -> float:
    """difflib's ratio of two keys, also with their words sorted (``plot_max``/``max_plots``)."""
    a, b = a.lower(), b.lower()
    plain = difflib.SequenceMatcher(None, a, b).ratio()
    words = difflib.SequenceMatcher(
        None, "_".join(sorted(re.split(r"[_\-.]", a))), "_".join(sorted(re.split(r"[_\-.]", b)))
    ).ratio()
    return max(plain, words)


def closest(word: str, candidates: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The candidate closest to ``word`` (difflib, case-insensitive), or None."""
    scored = [(_similarity(str(word), str(c)), str(c)) for c in candidates]
    scored = [sc for sc in scored if sc[0] >= cutoff]
    return max(scored, key=lambda sc: sc[0])[1] if scored else None


def unknown_message(
    key: Any,
    path: tuple,
    known: Iterable[str],
    retired: Mapping[str, str],
    missing: Iterable[str],
    what: str = "unknown setting",
    extra: str = "",
) -> str:
    """``calibrate.plot_max: unknown setting; did you mean calibrate.max_plots?`` and kin."""
    here = dotted((*path, key))
    if key in retired:
        return f"{here}: retired setting; {retired[key]}"
    known = list(known)
    close = closest(str(key), [*known, *retired])
    if close is None:
        listing = ", ".join(str(k) for k in known) if known else "none"
        return f"{here}: {what}{extra}; valid here: {listing}"
    there = dotted((*path, close))
    if close in retired:
        return f"{here}: {what}; it looks like {there}, a retired setting: {retired[close]}"
    message = f"{here}: {what}; did you mean {there}?{extra}"
    if close in missing:
        message += f" {there} is required and missing: {key} is probably it, misspelt."
    return message


@dataclass
class Context:
    """Collects the problems of one validation run."""

    complete: bool
    problems: list[tuple[tuple, str]] = field(default_factory=list)
    hints: dict[tuple, str] = field(default_factory=dict)

    def report(self, path: tuple, message: str) -> None:
        self.problems.append((path, message))

    def report_at(self, path: tuple, message: str) -> None:
        """Record ``message`` about the key at ``path``, prefixed with its dotted path."""
        self.report(path, f"{dotted(path)}: {message}")

    def check(self, check: Check, value: Any, path: tuple, doc: str | None = None) -> Any:
        """Run ``check``; record its problem (with the setting's doc) and return ``BAD``."""
        try:
            return check(value, path, self)
        except Invalid as exc:
            message = f"{dotted(path)}: {exc}"
            if doc:
                message += f"{' ' if message.endswith('?') else '; '}{dotted(path[-1:])}: {doc}"
            self.report(path, message)
            return BAD
