"""Typed, validated settings: ``params.yaml``, ``fe/params.yaml`` and femcal's environment.

Every key of both params files is described here once: its type, its allowed range or
choices and a one-line doc (the metadata of the frozen dataclasses below). A small generic
validator walks a loaded YAML mapping against them and reports every problem at once, each
with the file, the line, the dotted path of the key, what was given and what is allowed:

* an unknown key names the closest valid key (``calibrate.plot_max: unknown setting; did you
  mean calibrate.max_plots?``); a retired key names what replaced it, and so does a
  misspelling of a retired key;
* a missing required key is named, and so is an unknown key beside it that is probably the
  misspelt one;
* a wrong type or a value out of range says what was given and what is allowed (YAML
  integers are accepted for numbers; booleans are not integers).

Open maps are validated too: the model hyper-parameters of ``train.<split>.fixed`` and
``inverse.fixed`` against the keyword arguments of :class:`femcal.surrogates.nn.
NeuralSurrogate` and :class:`femcal.calibration.inverse.InverseModel`, the options of
``calibrate.options.<method>`` against the calibrator's keyword arguments, the FE adapter's
``fe.settings`` against :class:`femcal.fe.calculix.CalculixDisc`, and ``search_space``
entries against their ``{type: float|int|categorical, low, high, log, choices}`` form. The
tables are static so that validating needs no heavy import (no torch, Lightning, scikit-learn
or MLflow); ``tests/test_settings.py`` checks them against the real signatures.

:func:`check_environment` does the same for the environment variables femcal reads.

Two modes: :func:`femcal.config.load_params` (every ``femcal`` command) checks what a file
holds, and leaves missing sections and keys to the command that reads them (through
:func:`femcal.config.section`, which names them); :func:`load_settings` requires a complete
file and returns the typed :class:`Settings`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import urllib.parse
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

__all__ = [
    "CALIBRATOR_OPTIONS",
    "ENVIRONMENT",
    "INVERSE_HYPERPARAMETERS",
    "SURROGATE_HYPERPARAMETERS",
    "Settings",
    "check_environment",
    "describe_setting",
    "detect_schema",
    "load_settings",
    "validate_params",
]

#: The file kinds: the root pipeline's params.yaml and the FE pipeline's fe/params.yaml.
SCHEMAS: tuple[str, ...] = ("root", "fe")


# ===================================================================== checks (the validator)
class _Invalid(Exception):
    """A value failed its check; the message says what is allowed and what was given."""


_BAD = object()  # a value that failed its check (the problem is already recorded)
_MISSING = dataclasses.MISSING


class _Index(int):
    """A list position in a path (shown as ``[i]``, unlike an integer mapping key)."""


def _yaml_repr(value: Any) -> str:
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


def _got(value: Any) -> str:
    """``'ten' (str)``: what was given, as the message shows it."""
    return f"{_yaml_repr(value)} ({_type_name(value)})"


def _dotted(path: tuple) -> str:
    out = ""
    for key in path:
        if isinstance(key, _Index):
            out += f"[{int(key)}]"
        else:
            out += ("." if out else "") + str(key)
    return out


@dataclass
class _Context:
    """Collects the problems of one validation run."""

    complete: bool
    problems: list[tuple[tuple, str]] = field(default_factory=list)
    hints: dict[tuple, str] = field(default_factory=dict)

    def report(self, path: tuple, message: str) -> None:
        self.problems.append((path, message))

    def check(self, check: _Check, value: Any, path: tuple, doc: str | None = None) -> Any:
        """Run ``check``; record its problem (with the setting's doc) and return ``_BAD``."""
        try:
            return check(value, path, self)
        except _Invalid as exc:
            message = f"{_dotted(path)}: {exc}"
            if doc:
                message += f"{' ' if message.endswith('?') else '; '}{_dotted(path[-1:])}: {doc}"
            self.report(path, message)
            return _BAD


class _Check:
    """A check of one value: ``describe()`` says what is allowed, calling it validates."""

    def describe(self) -> str:
        raise NotImplementedError

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        raise NotImplementedError

    def fail(self, value: Any, extra: str = "") -> _Invalid:
        return _Invalid(f"expected {self.describe()}, got {_got(value)}{extra}")


def _interval(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return ""


class Int(_Check):
    """An integer (not a bool) in ``[lo, hi]``."""

    def __init__(self, lo: int | None = None, hi: int | None = None) -> None:
        self.lo, self.hi = lo, hi

    def describe(self) -> str:
        bounds = _interval(self.lo, self.hi, False, False)
        return f"an integer {bounds}".rstrip()

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(value)
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            raise self.fail(value)
        return int(value)


class Float(_Check):
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

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> float:
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


class Bool(_Check):
    """``true`` or ``false``."""

    def describe(self) -> str:
        return "true or false"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> bool:
        if not isinstance(value, bool):
            raise self.fail(value)
        return value


class Str(_Check):
    """A non-empty string; ``what`` names it in messages (e.g. "a path")."""

    def __init__(self, what: str = "a non-empty string") -> None:
        self.what = what

    def describe(self) -> str:
        return self.what

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> str:
        if not isinstance(value, str) or not value.strip():
            raise self.fail(value)
        return value


class Choice(_Check):
    """One of a fixed set of values; a close miss is named."""

    def __init__(self, choices: Iterable[Any]) -> None:
        self.choices = tuple(choices)

    def describe(self) -> str:
        return "one of " + ", ".join(_yaml_repr(c) for c in self.choices)

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if isinstance(value, bool) or value not in self.choices:
            extra = ""
            if isinstance(value, str):
                close = _closest(value, [str(c) for c in self.choices])
                if close is not None:
                    extra = f"; did you mean {close!r}?"
            raise self.fail(value, extra)
        return value


class Nullable(_Check):
    """``null`` or what ``inner`` accepts."""

    def __init__(self, inner: _Check) -> None:
        self.inner = inner

    def describe(self) -> str:
        return f"{self.inner.describe()} or null"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if value is None:
            return None
        try:
            return self.inner(value, path, ctx)
        except _Invalid as exc:
            prefix = f"expected {self.inner.describe()},"
            text = str(exc)
            if text.startswith(prefix):
                text = f"expected {self.describe()}," + text[len(prefix) :]
            raise _Invalid(text) from None


class ListOf(_Check):
    """A YAML list whose items each pass ``item``; returned as a tuple."""

    def __init__(self, item: _Check, *, min_len: int = 0, unique: bool = False) -> None:
        self.item, self.min_len, self.unique = item, min_len, unique

    def describe(self) -> str:
        size = "a non-empty list" if self.min_len == 1 else "a list"
        if self.min_len > 1:
            size = f"a list of at least {self.min_len} items"
        unique = ", no repeats" if self.unique else ""
        return f"{size} (each item {self.item.describe()}{unique})"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if not isinstance(value, list | tuple) or len(value) < self.min_len:
            raise self.fail(value)
        out = [ctx.check(self.item, v, (*path, _Index(i))) for i, v in enumerate(value)]
        if self.unique:
            seen: list[Any] = []
            for v in value:
                if v in seen:
                    raise _Invalid(
                        f"{_yaml_repr(v)} is listed twice in {_yaml_repr(value)}; list each once"
                    )
                seen.append(v)
        return _BAD if any(v is _BAD for v in out) else tuple(out)


class _Custom(_Check):
    """A check by a function returning the value or raising ``_Invalid``."""

    def __init__(self, describe: str, fn: Callable[[Any], Any]) -> None:
        self._describe, self.fn = describe, fn

    def describe(self) -> str:
        return self._describe

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if not isinstance(value, str):
            raise self.fail(value)
        return self.fn(value)


def _similarity(a: str, b: str) -> float:
    """difflib's ratio of two keys, also with their words sorted (``plot_max``/``max_plots``)."""
    a, b = a.lower(), b.lower()
    plain = difflib.SequenceMatcher(None, a, b).ratio()
    words = difflib.SequenceMatcher(
        None, "_".join(sorted(re.split(r"[_\-.]", a))), "_".join(sorted(re.split(r"[_\-.]", b)))
    ).ratio()
    return max(plain, words)


def _closest(word: str, candidates: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The candidate closest to ``word`` (difflib, case-insensitive), or None."""
    scored = [(_similarity(str(word), str(c)), str(c)) for c in candidates]
    scored = [sc for sc in scored if sc[0] >= cutoff]
    return max(scored, key=lambda sc: sc[0])[1] if scored else None


# --------------------------------------------------------------------- settings in dataclasses
def setting(check: _Check, doc: str, default: Any = _MISSING, *, key: str | None = None) -> Any:
    """A dataclass field that is a setting: its check, its one-line doc, its default.

    Without a default the setting is required. ``key`` is the YAML key when it differs from
    the attribute name (e.g. ``pgd-study``).
    """
    metadata = {"check": check, "doc": doc, "key": key}
    if default is _MISSING:
        return field(metadata=metadata)
    if isinstance(default, dict | list):
        return field(default_factory=lambda: type(default)(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def _settings_of(cls: type) -> dict[str, dataclasses.Field]:
    """YAML key -> dataclass field, for the fields that are settings."""
    return {
        (f.metadata.get("key") or f.name): f
        for f in dataclasses.fields(cls)
        if "check" in f.metadata
    }


def _required(f: dataclasses.Field) -> bool:
    return f.default is _MISSING and f.default_factory is _MISSING


class Section(_Check):
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
        keys = ", ".join(_settings_of(self.cls))
        return f"a mapping of settings ({keys})"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        hint = getattr(self.cls, "_hint", None)
        if hint:
            ctx.hints[path] = hint
        if not isinstance(value, Mapping):
            raise self.fail(value)
        return _validate_mapping(self.cls, value, path, ctx)


def _unknown_message(
    key: Any,
    path: tuple,
    known: Iterable[str],
    retired: Mapping[str, str],
    missing: Iterable[str],
    what: str = "unknown setting",
    extra: str = "",
) -> str:
    """``calibrate.plot_max: unknown setting; did you mean calibrate.max_plots?`` and kin."""
    here = _dotted((*path, key))
    if key in retired:
        return f"{here}: retired setting; {retired[key]}"
    known = list(known)
    close = _closest(str(key), [*known, *retired])
    if close is None:
        listing = ", ".join(str(k) for k in known) if known else "none"
        return f"{here}: {what}{extra}; valid here: {listing}"
    there = _dotted((*path, close))
    if close in retired:
        return f"{here}: {what}; it looks like {there}, a retired setting: {retired[close]}"
    message = f"{here}: {what}; did you mean {there}?{extra}"
    if close in missing:
        message += f" {there} is required and missing: {key} is probably it, misspelt."
    return message


def _validate_mapping(cls: type, value: Mapping, path: tuple, ctx: _Context) -> Any:
    specs = _settings_of(cls)
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
            invalid |= entries[key] is _BAD
            continue
        extra = f" (the other keys of {_dotted(path)} are {open_map[2]})" if open_map else ""
        ctx.report((*path, key), _unknown_message(key, path, specs, retired, missing, extra=extra))
        close = _closest(str(key), specs)
        if close in missing:
            paired.add(close)
        invalid = True
    if complete:
        for key in missing:
            if key not in paired:
                f = specs[key]
                ctx.report(
                    (*path, key),
                    f"{_dotted((*path, key))}: missing setting; add it ({key}: "
                    f"{f.metadata['doc']}; expected {f.metadata['check'].describe()})",
                )
            invalid = True
    for key, f in specs.items():
        if key in value:
            check, doc = f.metadata["check"], f.metadata["doc"]
            values[f.name] = ctx.check(check, value[key], (*path, key), doc)
            invalid |= values[f.name] is _BAD
    if open_map is not None:
        values[open_map[0]] = entries
    cross = getattr(cls, "_cross", None)
    if cross is not None and not invalid:
        full = {f.name: values.get(f.name, _default(f)) for f in dataclasses.fields(cls)}
        for key, message in cross(full):
            where = (*path, *key) if isinstance(key, tuple) else (*path, key)
            ctx.report(where, f"{_dotted(where)}: {message}")
            invalid = True
    if invalid or missing:
        return _BAD  # invalid (reported) or incomplete (a command reports it when it reads it)
    return cls(**values)


def _default(f: dataclasses.Field) -> Any:
    if f.default is not _MISSING:
        return f.default
    if f.default_factory is not _MISSING:
        return f.default_factory()
    return None


class MapOf(_Check):
    """An open mapping: every key passes ``key``, every value ``value``; returns a dict."""

    def __init__(self, value: _Check, key: _Check | None = None, *, what: str = "entries") -> None:
        self.value, self.key, self.what = value, key, what

    def describe(self) -> str:
        return f"a mapping of {self.what}"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if value is None:
            value = {}
        if not isinstance(value, Mapping):
            raise self.fail(value)
        out, bad = {}, False
        for k, v in value.items():
            if self.key is not None:
                try:
                    self.key(k, (*path, k), ctx)
                except _Invalid as exc:
                    ctx.report((*path, k), f"{_dotted((*path, k))}: {exc}")
                    bad = True
                    continue
            out[k] = ctx.check(self.value, v, (*path, k))
            bad |= out[k] is _BAD
        return _BAD if bad else out


class Keywords(_Check):
    """Keyword arguments of a function or class (a closed table of checks), as a dict.

    ``table`` maps each keyword to ``(check, doc)``; ``refused`` maps keywords that must not
    be set here to the reason and the fix; ``owner`` names the function in messages.
    """

    def __init__(
        self,
        table: Mapping[str, tuple[_Check, str]],
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

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if value is None:
            value = {}
        if not isinstance(value, Mapping):
            raise self.fail(value)
        out, bad = {}, False
        for k, v in value.items():
            where = (*path, k)
            if k in self.refused:
                ctx.report(where, f"{_dotted(where)}: not settable here; {self.refused[k]}")
                bad = True
            elif k not in self.table:
                ctx.report(
                    where,
                    _unknown_message(k, path, self.table, {}, (), f"unknown {self.owner} keyword"),
                )
                bad = True
            else:
                check, doc = self.table[k]
                out[k] = ctx.check(check, v, where, doc)
                bad |= out[k] is _BAD
        if not bad and self.cross is not None:
            for k, message in self.cross(out):
                ctx.report((*path, k), f"{_dotted((*path, k))}: {message}")
                bad = True
        return _BAD if bad else out


class SearchSpace(_Check):
    """An Optuna search space over the keywords of ``table`` (see :func:`femcal.train.suggest`).

    Each entry is ``{type: float|int|categorical, low, high, log, choices}``: float and int
    need ``low < high`` (``low > 0`` with ``log``), categorical needs ``choices``; the bounds
    and choices must be valid values of the hyper-parameter itself.
    """

    def __init__(self, keywords: Keywords) -> None:
        self.keywords = keywords

    def describe(self) -> str:
        return "a mapping hyper-parameter -> {type: float|int|categorical, low, high, log, choices}"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if value is None:
            value = {}
        if not isinstance(value, Mapping):
            raise self.fail(value)
        out, bad = {}, False
        for name, spec in value.items():
            where = (*path, name)
            if name in self.keywords.refused or name not in self.keywords.table:
                reason = self.keywords.refused.get(name)
                ctx.report(
                    where,
                    f"{_dotted(where)}: not settable here; {reason}"
                    if reason
                    else _unknown_message(
                        name,
                        path,
                        self.keywords.table,
                        {},
                        (),
                        f"unknown {self.keywords.owner} keyword",
                    ),
                )
                bad = True
                continue
            out[name] = self._entry(name, spec, where, ctx)
            bad |= out[name] is _BAD
        return _BAD if bad else out

    def _entry(self, name: str, spec: Any, path: tuple, ctx: _Context) -> Any:
        entry = ctx.check(Section(SearchEntry), spec, path)
        if entry is _BAD:
            return _BAD
        check, _ = self.keywords.table[name]
        kinds = _search_kinds(check)
        if entry.type not in kinds:
            allowed = " or ".join(kinds) if kinds else "none (it cannot be searched)"
            fix = "; search width and depth instead" if name == "hidden" else ""
            ctx.report(
                (*path, "type"),
                f"{_dotted((*path, 'type'))}: {name} is {check.describe()}, so type "
                f"{entry.type} does not fit; use {allowed}{fix}",
            )
            return _BAD
        bad = False
        if entry.type == "categorical":
            for i, choice in enumerate(entry.choices):
                bad |= ctx.check(check, choice, (*path, "choices", _Index(i))) is _BAD
        else:
            for bound in ("low", "high"):  # as written: 16 for an int, 0.001 for a float
                bad |= ctx.check(check, spec[bound], (*path, bound)) is _BAD
        return _BAD if bad else entry


def _search_kinds(check: _Check) -> tuple[str, ...]:
    if isinstance(check, Int):
        return ("int", "categorical")
    if isinstance(check, Float):
        return ("float", "int", "categorical")
    if isinstance(check, Bool | Choice):
        return ("categorical",)
    return ()


# ============================================================ URLs, addresses, names (strings)
#: SQLAlchemy dialects (their common spellings), for suggestions.
_SQL_DIALECTS = ("sqlite", "postgresql", "mysql", "mariadb", "oracle", "mssql", "cockroachdb")
_SQL_URL = re.compile(r"^(?P<dialect>[A-Za-z][A-Za-z0-9_]*)(?:\+(?P<driver>[A-Za-z0-9_]+))?://")
_SQL_EXAMPLES = "e.g. sqlite:///mlruns/optuna.db or postgresql://user:password@host/optuna"


def sqlalchemy_url_problem(value: str) -> str | None:
    """Why ``value`` is not a usable SQLAlchemy database URL (None when it is)."""
    if value != value.strip():
        return f"it has spaces around it; write {value.strip()!r}"
    m = _SQL_URL.match(value)
    if m is None:
        if "://" not in value and (value.endswith((".db", ".sqlite", ".sqlite3")) or "/" in value):
            return f"not a SQLAlchemy URL; for a SQLite file write sqlite:///{value}"
        return f"not a SQLAlchemy URL (dialect[+driver]://...); {_SQL_EXAMPLES}"
    dialect, rest = m["dialect"].lower(), value[m.end() :]
    if dialect == "postgres":
        return f"SQLAlchemy names this dialect postgresql; write postgresql://{rest}"
    if dialect not in _SQL_DIALECTS:
        close = _closest(dialect, _SQL_DIALECTS)
        if close is not None:
            return f"unknown database dialect {dialect!r}; did you mean {close}://{rest}?"
    if dialect == "sqlite":
        if not rest or rest in ("/", "/:memory:"):
            return (
                "an in-memory SQLite database forgets the study when the process ends; name a "
                "file, e.g. sqlite:///mlruns/optuna.db"
            )
        if not rest.startswith("/"):
            return f"a SQLite URL has three slashes before a relative path: sqlite:///{rest}"
    return None


_DASK_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")
_DASK_ADDRESS = re.compile(
    r"^(?P<scheme>[A-Za-z]+)://(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+)(?::(?P<port>\d+))?/?$"
)


def dask_address_problem(value: str) -> str | None:
    """Why ``value`` is not a Dask scheduler address ``tcp://host:port`` (None when it is)."""
    value = value.strip()
    if value.startswith("inproc://"):
        return None
    m = _DASK_ADDRESS.match(value)
    if m is None:
        if "://" not in value and re.match(r"^[^\s:/]+:\d+$", value):
            return f"no protocol; write tcp://{value}"
        return "not a Dask scheduler address; write tcp://host:port, e.g. tcp://login-node:8786"
    scheme, port = m["scheme"].lower(), m["port"]
    if scheme not in _DASK_SCHEMES:
        return (
            f"unknown protocol {scheme}://; use one of "
            f"{', '.join(s + '://' for s in _DASK_SCHEMES)}, e.g. tcp://{m['host']}:8786"
        )
    if port is None:
        return f"no port; write {scheme}://{m['host']}:8786 (the scheduler's default port)"
    if not 1 <= int(port) <= 65535:
        return f"port {port} is not in 1..65535"
    return None


_MLFLOW_SCHEMES = ("http", "https", "file", "databricks", "databricks-uc", "uc")


def mlflow_tracking_uri_problem(value: str) -> str | None:
    """Why ``value`` is not an MLflow tracking URI MLflow can use (None when it is)."""
    if value != value.strip():
        return f"it has spaces around it; write {value.strip()!r}"
    if value in ("databricks", "databricks-uc", "uc"):
        return None
    if "://" not in value:
        if re.match(r"^[A-Za-z0-9.-]+:\d+(/.*)?$", value):
            return f"no scheme, so MLflow would read it as a folder; write http://{value}"
        return None  # a local folder (a file store)
    scheme = urllib.parse.urlsplit(value).scheme.lower()
    base = scheme.split("+", 1)[0]
    if scheme in ("http", "https"):
        if not urllib.parse.urlsplit(value).netloc:
            return f"no host; write {scheme}://host:5000"
        return None
    if scheme in _MLFLOW_SCHEMES:
        return None
    if base in _SQL_DIALECTS or base == "postgres":
        return sqlalchemy_url_problem(value)
    close = _closest(scheme, [*_MLFLOW_SCHEMES, *_SQL_DIALECTS])
    fix = f"; did you mean {close}://?" if close else ""
    return (
        f"unknown scheme {scheme}://{fix} (a tracking server http(s)://host:port, a database "
        "sqlite:///path/mlflow.db or postgresql://..., or a folder)"
    )


def model_uri_problem(value: str) -> str | None:
    """Why ``value`` is not an MLflow model URI (None when it looks like one)."""
    if value.startswith("models:"):
        if re.match(r"^models:/[^/@\s]+(@[^/@\s]+|/[^/@\s]+)$", value):
            return None
        return (
            "expected models:/NAME@ALIAS or models:/NAME/VERSION, e.g. "
            "models:/ivd-rom-surrogate@champion"
        )
    if value.startswith("runs:"):
        if re.match(r"^runs:/[0-9A-Za-z]+/.+$", value):
            return None
        return "expected runs:/RUN_ID/ARTIFACT_PATH"
    if re.match(r"^(model|modles|modells):/", value):
        return f"did you mean models:/{value.split(':/', 1)[1]}?"
    if "@" in value and "/" not in value and "://" not in value:
        return f"did you mean models:/{value}?"
    return None  # a path or another artifact URI


def _url_check(describe: str, problem: Callable[[str], str | None]) -> _Custom:
    def check(value: str) -> str:
        why = problem(value)
        if why is not None:
            raise _Invalid(f"expected {describe}, got {_yaml_repr(value)}: {why}")
        return value

    return _Custom(describe, check)


SQL_URL = _url_check("a SQLAlchemy database URL", sqlalchemy_url_problem)
DASK_ADDRESS = _url_check("a Dask scheduler address tcp://host:port", dask_address_problem)
MODEL_URI = _url_check("an MLflow model URI (models:/NAME@ALIAS)", model_uri_problem)
PATH = Str("a path (a non-empty string)")
NAME = Str("a non-empty name")
_DATASET_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _dataset_name(value: Any, path: tuple, ctx: _Context) -> str:
    if not isinstance(value, str) or not _DATASET_NAME.match(value):
        raise _Invalid(
            f"dataset name {_yaml_repr(value)} must start with a letter or digit and hold only "
            "letters, digits, '_', '.' and '-' (it names the stage calibrate@<name> and "
            "reports/calibrate-<name>.json)"
        )
    return value


class _KeyChoice(_Check):
    """A key of an open mapping that must be one of ``choices`` (a close miss is named)."""

    def __init__(self, choices: Iterable[str], what: str) -> None:
        self.choices, self.what = tuple(choices), what

    def describe(self) -> str:
        return f"{self.what} ({', '.join(self.choices)})"

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        if value in self.choices:
            return value
        close = _closest(str(value), self.choices)
        if close is not None:
            raise _Invalid(f"unknown {self.what}; did you mean {_dotted((*path[:-1], close))}?")
        raise _Invalid(f"unknown {self.what}; valid here: {', '.join(self.choices)}")


class _FnCheck(_Check):
    def __init__(self, describe: str, fn: Callable[[Any, tuple, _Context], Any]) -> None:
        self._describe, self.fn = describe, fn

    def describe(self) -> str:
        return self._describe

    def __call__(self, value: Any, path: tuple, ctx: _Context) -> Any:
        return self.fn(value, path, ctx)


# ================================================================ keyword tables (static)
#: Hidden activations of the networks (femcal.surrogates.nn.ACTIVATIONS).
ACTIVATIONS: tuple[str, ...] = ("silu", "gelu", "relu", "tanh", "softplus")
#: The study's baseline models (femcal.surrogates registry, without "nn").
BASELINE_MODELS: tuple[str, ...] = (
    "linear",
    "poly2",
    "poly3",
    "poly4",
    "poly5",
    "svr",
    "random_forest",
    "gaussian_process",
    "lightgbm",
)
#: Registered calibrators (femcal.calibration registry).
CALIBRATORS: tuple[str, ...] = ("pgd", "pgd-study", "ga", "inverse")
#: Prepared splits (femcal.prepare.SPLITS) and FE campaign splits (femcal.fe.campaign).
SPLITS: tuple[str, ...] = ("large", "small", "test")
#: Registered FE solver adapters (femcal.fe registry).
SOLVERS: tuple[str, ...] = ("calculix",)
#: Mesh presets of the disc geometry (femcal.fe.geometry.MESH_PRESETS).
MESH_PRESETS: tuple[str, ...] = ("coarse", "default", "fine")

_WIDTHS = (Int(1), "width of every hidden layer (with depth: hidden = [width] * depth)")
_DEPTH = (Int(1), "number of hidden layers (with width)")
_HIDDEN = (ListOf(Int(1), min_len=1), "hidden-layer widths (or give width and depth)")

#: NeuralSurrogate keywords settable in train.<split>.fixed / search_space (plus width, depth).
SURROGATE_HYPERPARAMETERS: dict[str, tuple[_Check, str]] = {
    "hidden": _HIDDEN,
    "width": _WIDTHS,
    "depth": _DEPTH,
    "activation": (Choice(ACTIVATIONS), "hidden activation"),
    "log_target": (Bool(), "model log RoM (RoM must then be > 0)"),
    "loss": (Choice(("l1", "l2")), "training loss on the scaled (log-)RoM"),
    "learning_rate": (Float(0, lo_open=True), "peak learning rate (AdamW, one-cycle)"),
    "weight_decay": (Float(0), "AdamW weight decay"),
    "batch_size": (Int(1), "configurations per optimisation step"),
    "max_epochs": (Int(1), "epochs per ensemble member"),
    "patience": (Int(0), "early stopping: epochs without a better validation MAE"),
    "dropout": (Float(0, 1, hi_open=True), "dropout after each hidden activation"),
    "val_fraction": (
        Float(0, 1, hi_open=True),
        "validation fraction when no validation set is given (train uses train.val_fraction)",
    ),
    "log_params": (Bool(), "parameters with positive bounds enter in log scale"),
    "lr_schedule": (Choice(("onecycle", "cosine", "constant")), "learning-rate schedule"),
}
_SURROGATE_REFUSED = {
    "n_members": "the ensemble size is train.<split>.final_members (trials train one member)",
    "seed": "set train.seed, or train.<split>.seed for one split",
    "space": "the parameter space comes from the prepared data",
}

#: InverseModel keywords settable in inverse.fixed / search_space (plus width, depth).
INVERSE_HYPERPARAMETERS: dict[str, tuple[_Check, str]] = {
    "hidden": _HIDDEN,
    "width": _WIDTHS,
    "depth": _DEPTH,
    "activation": (Choice(ACTIVATIONS), "hidden activation"),
    "learning_rate": (Float(0, lo_open=True), "initial AdamW learning rate"),
    "weight_decay": (Float(0), "AdamW weight decay"),
    "dropout": (Float(0, 1, hi_open=True), "dropout after each hidden activation"),
    "batch_size": (Int(1), "samples per step"),
    "max_epochs": (Int(1), "upper bound on epochs"),
    "patience": (Int(0), "early stopping: epochs without a better validation MAE"),
    "min_delta": (Float(0), "smallest validation-MAE improvement that counts"),
    "scheduler_patience": (Int(0), "ReduceLROnPlateau patience in epochs"),
    "scheduler_factor": (Float(0, 1, lo_open=True, hi_open=True), "ReduceLROnPlateau factor"),
    "log_input": (Bool(), "standardise log RoM rather than RoM"),
    "val_fraction": (Float(0, 1, hi_open=True), "fraction of samples held out for validation"),
}
_INVERSE_REFUSED = {
    "seed": "set inverse.seed",
    "space": "the parameter space comes from the surrogate",
}


def _no_hidden_and_width(kw: dict) -> Iterable[tuple[str, str]]:
    if "hidden" in kw and ("width" in kw or "depth" in kw):
        yield "hidden", "give either hidden or width and depth, not both (width/depth win)"


SURROGATE_FIXED = Keywords(
    SURROGATE_HYPERPARAMETERS,
    "NeuralSurrogate",
    refused=_SURROGATE_REFUSED,
    cross=_no_hidden_and_width,
)
INVERSE_FIXED = Keywords(
    INVERSE_HYPERPARAMETERS, "InverseModel", refused=_INVERSE_REFUSED, cross=_no_hidden_and_width
)


def _pgd_cross(kw: dict) -> Iterable[tuple[str, str]]:
    if kw.get("n_starts", 8) + kw.get("n_random_starts", 0) < 1:
        yield "n_starts", "n_starts + n_random_starts must be >= 1 (starts per specimen)"


_GA_DEFAULTS = {"population": 20, "n_selected": 6, "n_crossover": 4, "n_mutation": 4}


def _ga_cross(kw: dict) -> Iterable[tuple[str, str]]:
    v = {**_GA_DEFAULTS, "n_immigrants": 6, **kw}
    total = v["n_selected"] + v["n_crossover"] + v["n_mutation"] + v["n_immigrants"]
    if total != v["population"]:
        yield (
            "population",
            f"n_selected + n_crossover + n_mutation + n_immigrants = {v['n_selected']} + "
            f"{v['n_crossover']} + {v['n_mutation']} + {v['n_immigrants']} = {total} must equal "
            f"population = {v['population']} (defaults 6 + 4 + 4 + 6 = 20)",
        )
    if v["n_crossover"] > 0 and v["n_selected"] < 2:
        yield "n_selected", "crossover needs n_selected >= 2 (or n_crossover: 0)"


#: Keyword options of each calibrator (calibrate.options.<method>): name -> (check, doc).
CALIBRATOR_OPTIONS: dict[str, Keywords] = {
    "pgd": Keywords(
        {
            "optimizer": (Choice(("gauss-newton", "adam", "lbfgsb")), "the local optimiser"),
            "n_starts": (Int(0), "starts per specimen from the nearest bank entries"),
            "n_random_starts": (Int(0), "additional uniform random starts per specimen"),
            "n_bank_uniform": (Int(0), "uniform draws added to the start bank"),
            "max_iter": (Int(1), "Gauss-Newton iterations (L-BFGS-B's iteration cap)"),
            "keep_after": (Int(0), "successive halving: iterations before keeping the best"),
            "keep": (Int(0), "starts per specimen kept after keep_after (0 = all)"),
            "jacobian_members": (Int(0), "ensemble members of the early Jacobian (0 = exact)"),
            "exact_final": (Int(0), "last iterations with the exact Jacobian"),
            "tol": (Float(0, lo_open=True), "relative loss decrease that counts as converged"),
            "loss": (Choice(("l2", "l1")), "weighted squared or absolute error"),
            "select": (Choice(("mae", "r2")), "how the best start of a specimen is chosen"),
            "steps": (Int(0), "Adam's steps"),
            "lr": (Float(0, lo_open=True), "Adam's learning rate (unit coordinates)"),
            "noise_deg": (
                Float(0, lo_open=True),
                "error scale of one RoM value in degrees (default: the surrogate's error)",
            ),
            "fit_tolerance": (Float(0), "stop a start below fit_tolerance * noise_deg RMS"),
            "range_z": (Float(0, lo_open=True), "half-width of the ranges in sd"),
            "ranges": (Bool(), "compute the identifiability ranges"),
            "effect_levels": (
                ListOf(Float(0, 1), min_len=1),
                "unit-box levels of the start grid over each effect's parameters",
            ),
            "effect_bank_starts": (
                Int(0),
                "effect models: starts from the nearest disc-and-effect combinations",
            ),
            "effect_bank_samples": (Int(1), "disc-and-effect combinations drawn for those"),
        },
        "pgd calibrator",
        refused={
            "start_bank": "set calibrate.start_bank (a prepared table whose configurations "
            "are the starts)",
            "rng": "set calibrate.seed",
        },
        cross=_pgd_cross,
    ),
    "pgd-study": Keywords(
        {
            "n_starts": (Int(1), "random starts per specimen (the study's 500)"),
            "steps": (Int(0), "optimisation steps (the study's 2250)"),
            "lr": (Float(0, lo_open=True), "learning rate in the unit box (the study's 0.0971)"),
            "loss": (Choice(("l1", "l2")), "row loss (the study: l1)"),
            "projection": (Choice(("clip", "average")), "the study's projection or averaging"),
            "bounds_penalty": (Float(0), "weight of the bounds penalty (0 = off)"),
            "optimizer": (Choice(("adam", "lbfgs")), "Adam (the study) or torch's L-BFGS"),
            "select": (Choice(("r2", "mae")), "best start by mean R² or by MAE"),
        },
        "pgd-study calibrator",
        refused={"rng": "set calibrate.seed"},
    ),
    "ga": Keywords(
        {
            "population": (Int(1), "individuals per specimen and generation (study: 20)"),
            "n_selected": (Int(1), "best individuals kept as parents (study: 6)"),
            "n_crossover": (Int(0), "crossover children per generation (study: 4)"),
            "n_mutation": (Int(0), "mutated copies per generation (study: 4)"),
            "n_immigrants": (Int(0), "uniform random individuals per generation (study: 6)"),
            "restart_every": (Int(1), "generations between restarts (study: 10)"),
            "max_generations": (Int(1), "generations at most (study: 120)"),
            "target_r2": (Float(hi=1), "stop a specimen once its best mean R² reaches this"),
            "fitness": (Choice(("r2", "mae")), "ranking of the individuals"),
        },
        "ga calibrator",
        refused={"rng": "set calibrate.seed"},
        cross=_ga_cross,
    ),
    "inverse": Keywords(
        {"model_uri": (MODEL_URI, "the registered inverse model (train-inverse)")},
        "inverse calibrator",
        refused={
            "model": "give model_uri (a registered inverse model)",
            "rng": "set calibrate.seed",
        },
    ),
}

#: Fields of the disc geometry (femcal.fe.geometry.DiscGeometry), plus ``preset``.
GEOMETRY_FIELDS: dict[str, tuple[_Check, str]] = {
    "preset": (Choice(MESH_PRESETS), "mesh density the other fields start from"),
    "width_mm": (Float(0, lo_open=True), "lateral axis of the ellipse, mm"),
    "depth_mm": (Float(0, lo_open=True), "anterior-posterior axis of the ellipse, mm"),
    "height_mm": (Float(0, lo_open=True), "disc height, mm"),
    "nucleus_fraction": (Float(0, 1, lo_open=True, hi_open=True), "nucleus volume fraction"),
    "n_rings": (Int(1), "annulus rings (material layers)"),
    "n_regions": (Int(3), "circumferential annulus regions per side"),
    "elements_per_region": (Int(1), "elements along the circumference per region"),
    "elements_per_ring": (Int(1), "elements across each annulus ring"),
    "elements_core": (Int(1), "elements between the nucleus block and its boundary"),
    "elements_height": (Int(1), "elements through the disc height"),
    "core_size": (Float(0, 1, lo_open=True, hi_open=True), "nucleus block corner radius"),
    "reference_height_mm": (Float(), "load reference point above the disc centre, mm"),
}
_GEOMETRY = Keywords(GEOMETRY_FIELDS, "DiscGeometry")


def _geometry(value: Any, path: tuple, ctx: _Context) -> Any:
    if isinstance(value, str):
        return Choice(MESH_PRESETS)(value, path, ctx)
    if isinstance(value, Mapping):
        return _GEOMETRY(value, path, ctx)
    raise _Invalid(
        f"expected a mesh preset ({', '.join(MESH_PRESETS)}) or a mapping of DiscGeometry "
        f"fields, got {_got(value)}"
    )


#: Keyword arguments of each FE solver adapter (fe.settings).
SOLVER_SETTINGS: dict[str, Keywords] = {
    "calculix": Keywords(
        {
            "geometry": (
                _FnCheck("a mesh preset or a mapping of DiscGeometry fields", _geometry),
                "disc geometry: a mesh preset (coarse, default, fine) or DiscGeometry fields",
            ),
            "kappa": (Choice(("scale", "ignore")), "how the fibre dispersion Kappa enters"),
            "executable": (NAME, "the CalculiX executable"),
            "initial_increment": (Float(0, 1, lo_open=True), "first load increment"),
            "max_attempts": (Int(1), "attempts per job (retries of a fibre-routine abort)"),
            "timeout_s": (Nullable(Float(0, lo_open=True)), "seconds per attempt (null = none)"),
            "max_increments": (Int(1), "load increments at most"),
            "retry_factor": (Float(0, 1, lo_open=True), "increment factor of a retry"),
            "nucleus_d1": (Float(0, lo_open=True), "compressibility of the nucleus"),
            "annulus_d1": (Float(0, lo_open=True), "compressibility of the annulus"),
        },
        "CalculixDisc",
    ),
}


# ====================================================================== the sections
@dataclass(frozen=True)
class DataSettings:
    """``data``: where the study's files and the prepared tables live."""

    raw_dir: str = setting(PATH, "folder of the study's files as fetched (fetch's output)")
    prepared_dir: str = setting(PATH, "folder of the tidy tables and parameter_space.json")
    source_dir: str | None = setting(
        Nullable(PATH), "what prepare reads, in the study's layout (null: raw_dir)", None
    )
    limit_configs: int | None = setting(
        Nullable(Int(1)), "keep only the first N configurations per split (null: all)", None
    )


@dataclass(frozen=True)
class MlflowSettings:
    """``mlflow``: the tracking store, the experiment and the registered model name."""

    store_dir: str = setting(
        PATH,
        "folder of the default store sqlite:///<store_dir>/mlflow.db (MLFLOW_TRACKING_URI "
        "overrides it)",
    )
    experiment: str = setting(NAME, "MLflow experiment of every run")
    model_name: str = setting(NAME, "registered name of the surrogate")


@dataclass(frozen=True)
class SearchEntry:
    """One Optuna search-space entry: ``{type, low, high, log}`` or ``{type, choices}``."""

    _complete: ClassVar[bool] = True

    type: str = setting(Choice(("float", "int", "categorical")), "the Optuna distribution")
    low: float | None = setting(Nullable(Float()), "lower bound (float and int)", None)
    high: float | None = setting(Nullable(Float()), "upper bound (float and int)", None)
    log: bool = setting(Bool(), "sample in log scale (float and int; needs low > 0)", False)
    choices: tuple | None = setting(
        Nullable(
            ListOf(
                _FnCheck("a number, string or boolean", lambda v, p, c: _scalar(v)),
                min_len=1,
                unique=True,
            )
        ),
        "the values to choose from (categorical)",
        None,
    )

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        if v["type"] == "categorical":
            if v["choices"] is None:
                yield "choices", "missing: a categorical entry needs choices: [a, b, ...]"
            for key in ("low", "high"):
                if v[key] is not None:
                    yield key, f"{key} is for type float or int; a categorical has choices only"
            if v["log"]:
                yield "log", "log is for type float or int"
            return
        if v["choices"] is not None:
            yield "choices", f"choices are for type categorical; a {v['type']} has low and high"
        for key in ("low", "high"):
            if v[key] is None:
                yield key, f"missing: a {v['type']} entry needs low and high"
        if v["low"] is None or v["high"] is None:
            return
        if v["type"] == "int":
            for key in ("low", "high"):
                if float(v[key]) != int(v[key]):
                    yield key, f"an int entry needs integer bounds; got {v[key]:g}"
        if not v["low"] < v["high"]:
            yield "high", f"high must be > low; got low {v['low']:g}, high {v['high']:g}"
        if v["log"] and v["low"] <= 0:
            yield "low", f"a log-scale entry needs low > 0; got {v['low']:g}"


def _scalar(value: Any) -> Any:
    if value is None or isinstance(value, list | dict):
        raise _Invalid(f"expected a number, string or boolean, got {_got(value)}")
    return value


@dataclass(frozen=True)
class TrainSplitSettings:
    """``train.<split>``: one surrogate trained on a prepared split (search + ensemble)."""

    n_trials: int = setting(Int(0), "complete Optuna trials (0: train on fixed alone)", 0)
    final_members: int = setting(Int(1), "ensemble members of the final model", 1)
    register: bool = setting(Bool(), "register the final model in MLflow", False)
    fixed: dict = setting(SURROGATE_FIXED, "NeuralSurrogate hyper-parameters", {})
    search_space: dict = setting(
        SearchSpace(SURROGATE_FIXED), "Optuna search space over the hyper-parameters", {}
    )
    seed: int | None = setting(Nullable(Int(0)), "seed of this split (default: train.seed)", None)
    split: str | None = setting(
        Nullable(Choice(SPLITS)), "prepared table trained on (default: the section's name)", None
    )
    model_name: str | None = setting(
        Nullable(NAME), "registered name (default: mlflow.model_name)", None
    )


@dataclass(frozen=True)
class TrainSettings:
    """``train``: Optuna storage and study, and one section per split (``train.<split>``)."""

    _open: ClassVar[tuple] = (
        "splits",
        Section(TrainSplitSettings),
        "splits: mappings such as large: {n_trials: 3, fixed: {...}}",
    )

    storage: str = setting(
        SQL_URL, "Optuna RDB storage, a SQLAlchemy URL (FEMCAL_OPTUNA_STORAGE overrides it)"
    )
    study_name: str = setting(NAME, "base name of the Optuna studies")
    val_fraction: float = setting(
        Float(0, 1, lo_open=True, hi_open=True), "fraction of configurations for validation"
    )
    seed: int = setting(Int(0), "seed of the sampler, the split and the members")
    splits: dict = field(default_factory=dict)

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        for name, split in v["splits"].items():
            if split.split is None and name not in SPLITS:
                yield (
                    (name,),
                    (
                        f"{name} is not a prepared split ({', '.join(SPLITS)}); add split: large "
                        "(the table it trains on)"
                    ),
                )


@dataclass(frozen=True)
class BaselinesSettings:
    """``baselines``: the study's model zoo."""

    seed: int = setting(Int(0), "seed of the stochastic baselines")
    n_jobs: int = setting(
        _FnCheck("an integer >= 1, or -1 (all cores)", lambda v, p, c: _n_jobs(v)),
        "parallel jobs of the baselines that support it",
    )
    models: tuple[str, ...] = setting(
        ListOf(Choice(BASELINE_MODELS), unique=True), "baseline models to fit"
    )


def _n_jobs(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not (value >= 1 or value == -1):
        raise _Invalid(f"expected an integer >= 1, or -1 (all cores), got {_got(value)}")
    return value


_MOMENTS = ListOf(Float(0, lo_open=True), min_len=1, unique=True)


@dataclass(frozen=True)
class InterpolationSettings:
    """``interpolation``: train on some moments, test on the others."""

    train_moments: tuple[float, ...] = setting(_MOMENTS, "moments trained on, Nm")
    test_moments: tuple[float, ...] = setting(_MOMENTS, "moments tested on, Nm")
    final_members: int = setting(Int(1), "ensemble members of the surrogate")
    baselines: tuple[str, ...] = setting(
        ListOf(Choice(BASELINE_MODELS), unique=True), "baselines checked too"
    )

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        both = sorted(set(v["train_moments"] or ()) & set(v["test_moments"] or ()))
        if both:
            yield (
                "test_moments",
                (
                    f"{', '.join(f'{m:g}' for m in both)} Nm also trained on; test on moments "
                    "left out of train_moments"
                ),
            )


@dataclass(frozen=True)
class InverseSettings:
    """``inverse``: the study's inverse network (RoM curves -> parameters)."""

    surrogate_uri: str = setting(MODEL_URI, "surrogate the training samples come from")
    moments: tuple[float, ...] = setting(_MOMENTS, "moment grid of the curves, Nm")
    n_samples: int = setting(Int(2), "surrogate samples to train on", 50_000)
    n_trials: int = setting(Int(0), "complete Optuna trials (0: train on fixed alone)", 0)
    seed: int = setting(Int(0), "seed of the samples, the split and the network", 0)
    study_name: str = setting(NAME, "Optuna study name", "ivd-inverse")
    register_as: str | None = setting(
        Nullable(NAME), "registered name (null: not registered)", None
    )
    fixed: dict = setting(INVERSE_FIXED, "InverseModel hyper-parameters", {})
    search_space: dict = setting(
        SearchSpace(INVERSE_FIXED), "Optuna search space over the hyper-parameters", {}
    )


@dataclass(frozen=True)
class MomentSettings:
    """``moments``: the moment policy every command shares (femcal.moments.MomentPolicy)."""

    error_growth: float = setting(
        Float(0), "growth of the surrogate's error sd per unit log-moment distance beyond range"
    )
    max_log_ratio: float = setting(
        Float(0), "log-moment distance beyond the trained range above which moments are refused"
    )


@dataclass(frozen=True)
class EffectsSettings:
    """``effects``: the user's effect modules, imported before the effect registry is used."""

    _hint: ClassVar[str] = (
        "the effects section must be {modules: [paths]}, each path a .py file or a folder of "
        "them relative to the project root. Write e.g. `effects: {modules: [my_effects.py]}` "
        "(the effects a calibration uses are listed under calibrate.datasets.<name>.effects)"
    )

    modules: tuple[str, ...] = setting(
        ListOf(PATH), ".py files or folders of them, relative to the params file's folder", []
    )


@dataclass(frozen=True)
class DatasetSettings:
    """``calibrate.datasets.<name>``: one measurement file and the effects added to the disc."""

    measurements: str = setting(PATH, "a long/wide CSV, or a folder of ROM_Results_* files")
    effects: tuple[str, ...] = setting(
        ListOf(NAME, unique=True), "effects added to the disc model ([] = the disc alone)", []
    )


def _dataset(value: Any, path: tuple, ctx: _Context) -> Any:
    if isinstance(value, str) and value.strip():
        return DatasetSettings(measurements=value)
    if isinstance(value, Mapping):
        return Section(DatasetSettings)(value, path, ctx)
    raise _Invalid(
        f"expected a path or {{measurements: path, effects: [names]}}, got {_got(value)}"
    )


def _method_options(value: Any, path: tuple, ctx: _Context) -> Any:
    return CALIBRATOR_OPTIONS[path[-1]](value, path, ctx)


@dataclass(frozen=True)
class CalibrateSettings:
    """``calibrate``: the calibration stages, one per dataset, and the calibrator."""

    _retired: ClassVar[dict[str, str]] = {
        "max_extrapolation": "replaced by moments.max_log_ratio (and moments.error_growth), the "
        "moment policy every command shares; delete it and set those in the moments section",
        "measurements": "replaced by calibrate.datasets.<name>.measurements (one stage per "
        "dataset); move it there",
        "metrics_file": "each dataset's figures go to reports/calibrate-<name>.json; delete it",
        "effects": "replaced by calibrate.datasets.<name>.effects (effects per dataset); move "
        "it there",
    }

    out_dir: str = setting(PATH, "outputs go to <out_dir>/<dataset>/")
    method: str = setting(Choice(CALIBRATORS), "calibration method")
    model_uri: str = setting(MODEL_URI, "the registered surrogate")
    datasets: dict = setting(
        MapOf(
            _FnCheck("a path or {measurements, effects}", _dataset),
            _FnCheck("a dataset name", _dataset_name),
            what="datasets",
        ),
        "name -> {measurements: path, effects: [names]}, one calibrate@<name> stage each",
        {},
    )
    holdout_uri: str | None = setting(
        Nullable(MODEL_URI), "held-out surrogate that re-evaluates every calibration", None
    )
    start_bank: str | None = setting(
        Nullable(PATH), "prepared table whose configurations are pgd's starts", None
    )
    seed: int = setting(Int(0), "seed of the calibrator", 0)
    chunk_size: int | None = setting(
        Nullable(Int(1)), "specimens per batch (null: all at once)", None
    )
    plots: bool = setting(Bool(), "write plots", True)
    max_plots: int | None = setting(
        Nullable(Int(0)), "per-specimen PNGs for the first N specimens (null: all)", None
    )
    options: dict = setting(
        MapOf(
            _FnCheck("calibrator options", _method_options),
            _KeyChoice(CALIBRATORS, "calibration method"),
            what="calibrator options per method",
        ),
        "method -> the calibrator's keyword options",
        {},
    )


@dataclass(frozen=True)
class PlantSettings:
    """``plant``: a cohort with hidden effects built from the Test set's FE curves."""

    out_dir: str = setting(PATH, "folder of the planted cohort")
    n_per_class: int = setting(Int(1), "specimens per class (4 classes)")
    moments: tuple[float, ...] = setting(_MOMENTS, "moments of the cohort, Nm")
    noise_deg: float = setting(Float(0), "measurement noise sd, degrees")
    seed: int = setting(Int(0), "seed of the cohort", 0)


@dataclass(frozen=True)
class DiagnoseSettings:
    """``diagnose``: where the model fails and which effect is missing."""

    measurements: str = setting(PATH, "measurement file diagnosed")
    out_dir: str = setting(PATH, "output folder")
    metrics_file: str | None = setting(Nullable(PATH), "summary figures (DVC metrics)", None)
    noise_deg: float | None = setting(
        Nullable(Float(0, lo_open=True)), "measurement noise sd, degrees (null: estimated)", None
    )
    candidates: tuple[str, ...] | None = setting(
        Nullable(ListOf(NAME, unique=True)), "effects tried (null: every registered one)", None
    )
    min_delta: float = setting(Float(0), "BIC gain an effect needs", 10.0)
    alpha: float = setting(
        Float(0, 1, lo_open=True, hi_open=True), "level of the adequacy tests", 0.01
    )
    max_effects: int = setting(Int(0), "effects forward selection may add per specimen", 3)
    seed: int = setting(Int(0), "seed of the diagnosis", 0)
    plots: bool = setting(Bool(), "write plots", True)
    max_plots: int | None = setting(
        Nullable(Int(0)), "per-specimen PNGs for the first N specimens (null: all)", None
    )


def _bounds(value: Any, path: tuple, ctx: _Context) -> Any:
    if isinstance(value, str) and value.strip():
        return value
    if not isinstance(value, Mapping) or not value:
        raise _Invalid(
            "expected a ParameterBounds.csv path or a mapping name -> [lower, upper], got "
            f"{_got(value)}"
        )
    out, bad = {}, False
    pair = ListOf(Float(), min_len=2)
    for name, bounds in value.items():
        where = (*path, name)
        if name not in PARAMETER_NAMES:
            ctx.report(
                where, _unknown_message(name, path, PARAMETER_NAMES, {}, (), "unknown parameter")
            )
            bad = True
            continue
        lo_hi = ctx.check(pair, bounds, where, "[lower, upper] in physical units")
        if lo_hi is _BAD:
            bad = True
        elif len(lo_hi) != 2 or not lo_hi[0] < lo_hi[1]:
            ctx.report(
                where,
                f"{_dotted(where)}: expected [lower, upper] with lower < upper, "
                f"got {_yaml_repr(list(bounds))}",
            )
            bad = True
        else:
            out[name] = lo_hi
    return _BAD if bad else out


def _solver_settings(value: Any, path: tuple, ctx: _Context) -> Any:
    # A mapping here; its keys are checked against fe.solver's adapter (SOLVER_SETTINGS).
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise _Invalid(f"expected a mapping of the adapter's keyword arguments, got {_got(value)}")
    return dict(value)


@dataclass(frozen=True)
class FeSettings:
    """``fe``: the FE campaign (fe/params.yaml)."""

    solver: str = setting(Choice(SOLVERS), "FE solver adapter (femcal.fe registry)")
    bounds: Any = setting(
        _FnCheck("a ParameterBounds.csv path or a mapping name -> [lower, upper]", _bounds),
        "the sampling box: name -> [lower, upper], or a ParameterBounds.csv path",
    )
    splits: dict = setting(
        MapOf(Int(0), _KeyChoice(SPLITS, "split"), what="split -> configurations"),
        "configurations per split (large, small, test)",
    )
    seed: int = setting(Int(0), "seed of the designs")
    load_cases: tuple[str, ...] = setting(
        ListOf(Choice(LOAD_CASES), unique=True), "load cases simulated (all four)"
    )
    moments: tuple[float, ...] = setting(_MOMENTS, "moments simulated, Nm")
    out_dir: str = setting(PATH, "dataset folder in the study's layout")
    store: str = setting(PATH, "durable store of finished jobs (JSON lines)")
    settings: dict = setting(
        _FnCheck("a mapping of the adapter's keyword arguments", _solver_settings),
        "the adapter's keyword arguments (part of every job's hash)",
        {},
    )
    scratch_dir: str | None = setting(Nullable(PATH), "per-job scratch (null: temp)", None)
    metrics_file: str | None = setting(Nullable(PATH), "campaign figures (DVC metrics)", None)
    scheduler_address: str | None = setting(
        Nullable(DASK_ADDRESS),
        "Dask scheduler, tcp://host:port (null: a local cluster, or FEMCAL_DASK_ADDRESS)",
        None,
    )
    n_workers: int = setting(Int(1), "workers of the local cluster", 2)

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        if v["load_cases"] is not None and sorted(v["load_cases"]) != sorted(LOAD_CASES):
            yield (
                "load_cases",
                (
                    "a dataset in the study's layout needs all four load cases "
                    f"{list(LOAD_CASES)}; got {list(v['load_cases'])}"
                ),
            )


@dataclass(frozen=True)
class IdpRange:
    """A literature range of the intradiscal pressure at one force, MPa."""

    _complete: ClassVar[bool] = True

    low: float = setting(Float(0), "lowest value, MPa")
    mean: float = setting(Float(0), "mean value, MPa")
    high: float = setting(Float(0), "highest value, MPa")

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        if not v["low"] <= v["mean"] <= v["high"]:
            yield (
                "mean",
                (f"need low <= mean <= high; got {v['low']:g}, {v['mean']:g}, {v['high']:g}"),
            )


@dataclass(frozen=True)
class ValidateSettings:
    """``validate``: FE re-simulation of the calibrated parameters and the IDP check."""

    calibration_dir: str = setting(PATH, "calibration folder validated")
    measurements: str = setting(PATH, "the measurements that were calibrated to")
    out_dir: str = setting(PATH, "output folder")
    store: str = setting(PATH, "campaign store of the FE runs")
    metrics_file: str | None = setting(Nullable(PATH), "figures (DVC metrics)", None)
    forces: tuple[float, ...] = setting(
        ListOf(Float(0, lo_open=True), unique=True), "axial compression forces, N", []
    )
    idp_literature: dict = setting(
        MapOf(Section(IdpRange), Float(0, lo_open=True), what="force in N -> {low, mean, high}"),
        "literature IDP range per force: force in N -> {low, mean, high} in MPa",
        {},
    )


#: Sections of each file kind: section -> (class, required in a complete file).
_SECTIONS: dict[str, tuple[type, dict[str, bool]]] = {
    "data": (DataSettings, {"root": True, "fe": True}),
    "mlflow": (MlflowSettings, {"root": True, "fe": True}),
    "train": (TrainSettings, {"root": True, "fe": True}),
    "baselines": (BaselinesSettings, {"root": True, "fe": False}),
    "interpolation": (InterpolationSettings, {"root": True, "fe": False}),
    "inverse": (InverseSettings, {"root": True, "fe": False}),
    "moments": (MomentSettings, {"root": True, "fe": True}),
    "effects": (EffectsSettings, {"root": False, "fe": False}),
    "calibrate": (CalibrateSettings, {"root": True, "fe": True}),
    "plant": (PlantSettings, {"root": True, "fe": False}),
    "diagnose": (DiagnoseSettings, {"root": True, "fe": False}),
    "fe": (FeSettings, {"fe": True}),
    "validate": (ValidateSettings, {"fe": True}),
}


@dataclass(frozen=True)
class Settings:
    """A validated params file: one typed section each (None when the file lacks it).

    Attributes
    ----------
    path : Path
        The file.
    schema : {"root", "fe"}
        The pipeline it drives: the root ``params.yaml`` or the FE pipeline's
        ``fe/params.yaml`` (which also has ``fe`` and ``validate``).
    """

    path: Path
    schema: str
    data: DataSettings | None = None
    mlflow: MlflowSettings | None = None
    train: TrainSettings | None = None
    baselines: BaselinesSettings | None = None
    interpolation: InterpolationSettings | None = None
    inverse: InverseSettings | None = None
    moments: MomentSettings | None = None
    effects: EffectsSettings | None = None
    calibrate: CalibrateSettings | None = None
    plant: PlantSettings | None = None
    diagnose: DiagnoseSettings | None = None
    fe: FeSettings | None = None
    validate: ValidateSettings | None = None


# ====================================================================== validation entry points
def detect_schema(data: Mapping[str, Any]) -> str:
    """``"fe"`` for a file with an ``fe`` or ``validate`` section (fe/params.yaml), else root."""
    return "fe" if "fe" in data or "validate" in data else "root"


def _validate_top(data: Mapping[str, Any], schema: str, ctx: _Context) -> dict[str, Any]:
    allowed = {name for name, (_, req) in _SECTIONS.items() if schema in req}
    required = [name for name, (_, req) in _SECTIONS.items() if req.get(schema)]
    missing = [name for name in required if name not in data]
    out: dict[str, Any] = {}
    paired: set[str] = set()
    for key, value in data.items():
        if key == "_path":
            continue
        if key in allowed:
            out[key] = ctx.check(Section(_SECTIONS[key][0]), value, (key,))
            continue
        if key in _SECTIONS:  # fe or validate in a root params file
            ctx.report(
                (key,),
                f"{key}: not a section of the root params.yaml; {key} belongs to the FE "
                "pipeline's fe/params.yaml",
            )
            continue
        close = _closest(str(key), allowed)
        if close in missing:
            paired.add(close)
        ctx.report(
            (key,), _unknown_message(key, (), sorted(allowed), {}, missing, "unknown section")
        )
    if ctx.complete:
        for name in missing:
            if name not in paired:
                ctx.report(
                    (name,),
                    f"{name}: missing section; add it (see the project's "
                    f"{'fe/params.yaml' if schema == 'fe' else 'params.yaml'})",
                )
    # The adapter's settings depend on the solver: checked once both are known.
    fe = data.get("fe") if "fe" in allowed else None
    if isinstance(fe, Mapping) and isinstance(fe.get("settings"), Mapping):
        solver = fe.get("solver", SOLVERS[0])
        if solver in SOLVER_SETTINGS:
            checked = ctx.check(SOLVER_SETTINGS[solver], fe["settings"], ("fe", "settings"))
            if isinstance(out.get("fe"), FeSettings) and checked is not _BAD:
                out["fe"] = dataclasses.replace(out["fe"], settings=checked)
    return out


def _line_numbers(text: str) -> Callable[[tuple], int | None]:
    """A function path -> 1-based line of that key in the YAML ``text`` (None if unknown)."""
    import yaml

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:  # pragma: no cover - the text was loaded before
        root = None

    def line(path: tuple) -> int | None:
        node, found = root, None
        for key in path:
            if isinstance(node, yaml.MappingNode):
                for k, v in node.value:
                    if k.value == str(key):
                        found, node = k.start_mark.line + 1, v
                        break
                else:
                    return found
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, _Index):
                if int(key) >= len(node.value):
                    return found
                node = node.value[int(key)]
                found = node.start_mark.line + 1
            else:
                return found
        return found

    return line


def _sentence(message: str) -> str:
    return message if message.endswith((".", "?", "!")) else message + "."


def _raise(ctx: _Context, where: str, text: str | None) -> None:
    """One ConfigError for every recorded problem, each with its line in the file."""
    if not ctx.problems:
        return
    line_of = _line_numbers(text) if text is not None else (lambda path: None)
    lines = []
    for path, message in ctx.problems:
        hint = next((h for p, h in ctx.hints.items() if path[: len(p)] == p), None)
        if hint and hint not in message:
            message = f"{message}; {hint}"
        lines.append((line_of(path), _sentence(message)))
    lines.sort(key=lambda lm: (lm[0] is None, lm[0] or 0))
    if len(lines) == 1:
        line, message = lines[0]
        raise ConfigError(f"{where}{f', line {line}' if line else ''}: {message}")
    body = "\n".join(f"  {f'line {line}: ' if line else ''}{message}" for line, message in lines)
    raise ConfigError(f"{where}: {len(lines)} invalid settings; fix each and rerun:\n{body}")


def validate_params(
    data: Mapping[str, Any],
    *,
    path: str | Path = "params.yaml",
    schema: str | None = None,
    complete: bool = False,
    text: str | None = None,
) -> Settings | None:
    """Validate a loaded params mapping; raise one ConfigError listing every problem.

    Parameters
    ----------
    data : mapping
        The YAML document (sections at the top).
    path : str or Path
        The file, for messages.
    schema : {"root", "fe"}, optional
        Which file it is (default: :func:`detect_schema`).
    complete : bool
        Require every required section and key (``load_settings``). Otherwise only what the
        file holds is checked, and a command reports a missing key when it reads it.
    text : str, optional
        The file's text, for line numbers in messages.

    Returns
    -------
    Settings or None
        The typed settings when ``complete`` (or when nothing is missing), else None.

    Raises
    ------
    ConfigError
        Unknown, retired, missing (``complete``), mistyped or out-of-range settings.
    """
    schema = schema or detect_schema(data)
    if schema not in SCHEMAS:
        raise ConfigError(f"schema must be one of {', '.join(SCHEMAS)}; got {schema!r}.")
    ctx = _Context(complete=complete)
    sections = _validate_top(data, schema, ctx)
    _raise(ctx, str(path), text)
    if any(v is _BAD for v in sections.values()):  # incomplete: partial validation only
        return None
    return Settings(path=Path(path), schema=schema, **sections)


def load_settings(path: str | Path = "params.yaml", *, schema: str | None = None) -> Settings:
    """Read, validate and type a complete params file.

    Parameters
    ----------
    path : str or Path
        ``params.yaml`` or ``fe/params.yaml``.
    schema : {"root", "fe"}, optional
        Which file it is (default: ``"fe"`` when it has an ``fe`` section).

    Returns
    -------
    Settings

    Raises
    ------
    ConfigError
        The file is missing or not YAML, or a setting is unknown, retired, missing, of the
        wrong type or out of range (all of them in one message).
    """
    from femcal.config import read_yaml_mapping

    data, text = read_yaml_mapping(path)
    settings = validate_params(data, path=path, schema=schema, complete=True, text=text)
    assert settings is not None  # complete validation returns the settings or raises
    return settings


def describe_setting(keys: Iterable[str]) -> str | None:
    """The one-line doc of the setting at ``keys`` (e.g. ``("calibrate", "max_plots")``)."""
    keys = list(keys)
    if not keys or keys[0] not in _SECTIONS:
        return None
    cls: Any = _SECTIONS[keys[0]][0]
    doc = re.sub(r"^``[^`]+``: ", "", cls.__doc__.splitlines()[0]).rstrip(".")
    for key in keys[1:]:
        specs = _settings_of(cls) if dataclasses.is_dataclass(cls) else {}
        if key not in specs:
            return None
        doc = specs[key].metadata["doc"]
        check = specs[key].metadata["check"]
        cls = check.cls if isinstance(check, Section) else None
    return doc


# ====================================================================== environment variables
@dataclass(frozen=True)
class EnvVar:
    """An environment variable femcal reads: its doc, its check and the commands reading it."""

    name: str
    doc: str
    problem: Callable[[str], str | None]
    commands: tuple[str, ...]


def _mirror_problem(value: str) -> str | None:
    path = Path(value.strip()).expanduser()
    if not path.exists():
        return f"{path.resolve()} does not exist"
    if not path.is_dir():
        return f"{path.resolve()} is a file, not a folder"
    if not any((path / split).is_dir() for split in ("Large", "Small", "Test")):
        return f"{path.resolve()} holds none of Large/, Small/, Test/"
    return None


def _storage_problem(value: str) -> str | None:
    return sqlalchemy_url_problem(value)


_TRACKING = (
    "train",
    "baselines",
    "interpolate",
    "evaluate",
    "train-inverse",
    "calibrate",
    "diagnose",
    "validate",
)

#: The environment variables femcal reads, by name.
ENVIRONMENT: dict[str, EnvVar] = {
    v.name: v
    for v in (
        EnvVar(
            "FEMCAL_DATA_MIRROR",
            "a local folder holding the study's Large/, Small/ and Test/ (instead of the "
            "download); set it to that folder (the study's datasets/), or unset it to download",
            _mirror_problem,
            ("fetch",),
        ),
        EnvVar(
            "FEMCAL_OPTUNA_STORAGE",
            "the Optuna storage, a SQLAlchemy URL (overrides train.storage); e.g. "
            "postgresql://user:password@host/optuna, or unset it to use train.storage",
            _storage_problem,
            ("train", "train-inverse"),
        ),
        EnvVar(
            "FEMCAL_DASK_ADDRESS",
            "the Dask scheduler of the FE campaign, tcp://host:port (when fe.scheduler_address "
            "is null); e.g. tcp://login-node:8786, or unset it for a local cluster",
            dask_address_problem,
            ("simulate", "validate"),
        ),
        EnvVar(
            "MLFLOW_TRACKING_URI",
            "the MLflow tracking server or database (overrides mlflow.store_dir); e.g. "
            "http://mlflow-server:5000, or unset it to use the project's store",
            mlflow_tracking_uri_problem,
            _TRACKING,
        ),
    )
}


def check_environment(
    command: str | None = None, environ: Mapping[str, str] | None = None
) -> dict[str, str]:
    """Validate the environment variables ``command`` reads (all of femcal's when None).

    An empty or blank variable counts as unset, as where it is read.

    Parameters
    ----------
    command : str, optional
        A ``femcal`` sub-command, e.g. ``"fetch"``.
    environ : mapping, optional
        The environment (default: :data:`os.environ`).

    Returns
    -------
    dict
        The variables that are set, name -> value.

    Raises
    ------
    ConfigError
        Naming every bad variable, its value, what is wrong and the fix.
    """
    environ = os.environ if environ is None else environ
    found, problems = {}, []
    for var in ENVIRONMENT.values():
        if command is not None and command not in var.commands:
            continue
        value = environ.get(var.name, "")
        if not value.strip():
            continue
        why = var.problem(value)
        if why is None:
            found[var.name] = value
        else:
            problems.append(f"{var.name}={value!r}: {why}. {var.name} is {var.doc}.")
    if len(problems) == 1:
        raise ConfigError(f"Environment variable {problems[0]}")
    if problems:
        raise ConfigError(
            "Invalid environment variables:\n" + "\n".join(f"  {p}" for p in problems)
        )
    return found
