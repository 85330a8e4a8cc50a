"""Settings in dataclasses, and the checks of mappings: sections, open maps, keyword tables.

A section is a frozen dataclass whose fields are settings (:func:`setting`: a check, a
one-line doc, a default); :class:`Section` validates a mapping against it and reports every
unknown, retired, missing or invalid key. :class:`MapOf` and :class:`Keywords` check open
maps: any keys, or the keyword arguments of a function or class.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping
from dataclasses import field
from typing import Any

from femcal.settings._checks import Check, Nullable
from femcal.settings._messages import BAD, Context, Invalid, closest, dotted, unknown_message

MISSING = dataclasses.MISSING


def setting(check: Check, doc: str, default: Any = MISSING, *, key: str | None = None) -> Any:
    """A dataclass field that is a setting: its check, its one-line doc, its default.

    Without a default the setting is required. ``key`` is the YAML key when it differs from
    the attribute name (e.g. ``pgd-study``).
    """
    metadata = {"check": check, "doc": doc, "key": key}
    if default is MISSING:
        return field(metadata=metadata)
    if isinstance(default, dict | list):
        return field(default_factory=lambda: type(default)(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def optional(check: Check, doc: str) -> Any:
    """A setting that may be null, and is null by default."""
    return setting(Nullable(check), doc, None)


def settings_of(cls: type) -> dict[str, dataclasses.Field]:
    """YAML key -> dataclass field, for the fields that are settings."""
    return {
        (f.metadata.get("key") or f.name): f
        for f in dataclasses.fields(cls)
        if "check" in f.metadata
    }


def _required(f: dataclasses.Field) -> bool:
    return f.default is MISSING and f.default_factory is MISSING


def _default(f: dataclasses.Field) -> Any:
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    return None


class Section(Check):
    """A mapping validated against a settings dataclass; returns an instance of it.

    Class attributes of the dataclass tune it: ``_hint`` (appended to every problem inside),
    ``_retired`` (key -> what replaced it), ``_open`` (attribute, check, what: the other keys
    are entries of an open map when their value is a mapping, e.g. the splits of ``train``),
    ``_complete`` (missing required keys are reported even when the file is checked
    partially) and ``_cross`` (a function of the validated values yielding (key, message)).
    """

    def __init__(self, cls: type) -> None:
        self.cls = cls

    def describe(self) -> str:
        keys = ", ".join(settings_of(self.cls))
        return f"a mapping of settings ({keys})"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        hint = getattr(self.cls, "_hint", None)
        if hint:
            ctx.hints[path] = hint
        if not isinstance(value, Mapping):
            raise self.fail(value)
        return _validate_mapping(self.cls, value, path, ctx)


def _validate_mapping(cls: type, value: Mapping, path: tuple, ctx: Context) -> Any:
    specs = settings_of(cls)
    retired: Mapping[str, str] = getattr(cls, "_retired", {})
    open_map = getattr(cls, "_open", None)
    complete = ctx.complete or getattr(cls, "_complete", False)
    missing = [k for k, f in specs.items() if _required(f) and k not in value]
    paired: set[str] = set()
    values: dict[str, Any] = {}
    entries: dict[Any, Any] = {}
    invalid = False
    for key, item in value.items():
        if key in specs:
            continue
        if open_map is not None and key not in retired and isinstance(item, Mapping):
            entries[key] = ctx.check(open_map[1], item, (*path, key))
            invalid |= entries[key] is BAD
            continue
        extra = f" (the other keys of {dotted(path)} are {open_map[2]})" if open_map else ""
        ctx.report((*path, key), unknown_message(key, path, specs, retired, missing, extra=extra))
        close = closest(str(key), specs)
        if close in missing:
            paired.add(close)
        invalid = True
    if complete:
        for key in missing:
            if key not in paired:
                f = specs[key]
                ctx.report_at(
                    (*path, key),
                    f"missing setting; add it ({key}: "
                    f"{f.metadata['doc']}; expected {f.metadata['check'].describe()})",
                )
            invalid = True
    for key, f in specs.items():
        if key in value:
            check, doc = f.metadata["check"], f.metadata["doc"]
            values[f.name] = ctx.check(check, value[key], (*path, key), doc)
            invalid |= values[f.name] is BAD
    if open_map is not None:
        values[open_map[0]] = entries
    cross = getattr(cls, "_cross", None)
    if cross is not None and not invalid:
        full = {f.name: values.get(f.name, _default(f)) for f in dataclasses.fields(cls)}
        for key, message in cross(full):
            ctx.report_at((*path, *key) if isinstance(key, tuple) else (*path, key), message)
            invalid = True
    if invalid or missing:
        return BAD  # invalid (reported) or incomplete (a command reports it when it reads it)
    return cls(**values)


# ---------------------------------------------------------------------------- open maps
class MapOf(Check):
    """An open mapping: every key passes ``key``, every value ``value``; returns a dict."""

    def __init__(self, value: Check, key: Check | None = None, *, what: str = "entries") -> None:
        self.value, self.key, self.what = value, key, what

    def describe(self) -> str:
        return f"a mapping of {self.what}"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        out, bad = {}, False
        for k, v in self.mapping(value).items():
            if self.key is not None:
                try:
                    self.key(k, (*path, k), ctx)
                except Invalid as exc:
                    ctx.report_at((*path, k), str(exc))
                    bad = True
                    continue
            out[k] = ctx.check(self.value, v, (*path, k))
            bad |= out[k] is BAD
        return BAD if bad else out


class Keywords(Check):
    """Keyword arguments of a function or class (a closed table of checks), as a dict.

    ``table`` maps each keyword to ``(check, doc)``; ``refused`` maps keywords that must not
    be set here to the reason and the fix; ``owner`` names the function in messages.
    """

    def __init__(
        self,
        table: Mapping[str, tuple[Check, str]],
        owner: str,
        *,
        refused: Mapping[str, str] | None = None,
        cross: Callable[[dict], Iterable[tuple[str, str]]] | None = None,
    ) -> None:
        self.table, self.owner = dict(table), owner
        self.refused = dict(refused or {})
        self.cross = cross

    def describe(self) -> str:
        return f"a mapping of {self.owner} keywords ({', '.join(self.table)})"

    def reject(self, key: Any, path: tuple, ctx: Context) -> bool:
        """Report ``key`` (under ``path``) if it is refused or unknown; True if it was."""
        where = (*path, key)
        if key in self.refused:
            ctx.report_at(where, f"not settable here; {self.refused[key]}")
        elif key not in self.table:
            what = f"unknown {self.owner} keyword"
            ctx.report(where, unknown_message(key, path, self.table, {}, (), what))
        else:
            return False
        return True

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        out, bad = {}, False
        for k, v in self.mapping(value).items():
            if self.reject(k, path, ctx):
                bad = True
                continue
            check, doc = self.table[k]
            out[k] = ctx.check(check, v, (*path, k), doc)
            bad |= out[k] is BAD
        if not bad and self.cross is not None:
            for k, message in self.cross(out):
                ctx.report_at((*path, k), message)
                bad = True
        return BAD if bad else out
