"""Pydantic's validation errors as femcal's messages: file, line, key, what was given, the fix.

:func:`describe` says in words what a type annotation allows (``an integer >= 0 or null``);
:func:`problems` turns a :class:`pydantic.ValidationError` into ``(path, message)`` pairs: an
unknown key names the closest valid one (or what replaced a retired one), a missing key its
doc, a wrong value what was given and what is allowed. :func:`raise_problems` adds each
problem's line in the YAML file and raises one :class:`~femcal.errors.ConfigError`.

Models tune the messages with class variables: ``_unknown`` (what an unknown key is called),
``_retired`` and ``_refused`` (key -> what to do instead), ``_complete`` (missing keys are
reported even when a file is checked partially), ``_missing`` (the message of a missing key),
``_open`` (a field holding the model's other keys, e.g. the splits of ``train``) and ``_hint``
(appended to every problem inside).
"""

from __future__ import annotations

import difflib
import re
import types
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import annotated_types as at
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo
from pydantic_core import PydanticCustomError

from femcal.errors import ConfigError


@dataclass(frozen=True)
class Doc:
    """What a custom type allows, as messages say it (``a path (a non-empty string)``)."""

    text: str


@dataclass(frozen=True)
class PlainOf:
    """A mapping validated against ``model`` and kept as plain data (keyword arguments)."""

    model: type


class Index(int):
    """A list position in a path (shown as ``[i]``, unlike an integer mapping key)."""


def fail(message: str, key: Any = None) -> PydanticCustomError:
    """A problem with femcal's own words; ``key`` (a model's cross check) extends its path."""
    return PydanticCustomError("femcal", "{message}", {"message": message, "key": key})


def yaml_repr(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    text = repr(list(value) if isinstance(value, tuple) else value)
    return text if len(text) <= 60 else text[:57] + "..."


def got(value: Any) -> str:
    """``'ten' (str)``: what was given, as the message shows it."""
    kind = "null" if value is None else type(value).__name__
    return f"{yaml_repr(value)} ({'mapping' if isinstance(value, Mapping) else kind})"


def dotted(path: Iterable) -> str:
    out = ""
    for key in path:
        out += f"[{int(key)}]" if isinstance(key, Index) else ("." if out else "") + str(key)
    return out


def _similarity(a: str, b: str) -> float:
    """difflib's ratio of two keys, also with their words sorted (``plot_max``/``max_plots``)."""
    a, b = a.lower(), b.lower()

    def words(s: str) -> str:
        return "_".join(sorted(re.split(r"[_\-.]", s)))

    plain = difflib.SequenceMatcher(None, a, b).ratio()
    return max(plain, difflib.SequenceMatcher(None, words(a), words(b)).ratio())


def closest(word: str, candidates: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The candidate closest to ``word`` (difflib, case-insensitive), or None."""
    scored = [(_similarity(str(word), str(c)), str(c)) for c in candidates]
    scored = [sc for sc in scored if sc[0] >= cutoff]
    return max(scored, key=lambda sc: sc[0])[1] if scored else None


def unknown_message(key: Any, path: tuple, known: Iterable[str], **how: Any) -> str:
    """``calibrate.plot_max: unknown setting; did you mean calibrate.max_plots?`` and kin.

    ``how``: ``retired`` and ``refused`` (key -> text), ``missing`` (required keys not given),
    ``what`` (default "unknown setting") and ``extra`` (appended to the first clause).
    """
    retired, refused = how.get("retired", {}), how.get("refused", {})
    what, extra = how.get("what", "unknown setting"), how.get("extra", "")
    here = dotted((*path, key))
    if key in refused:
        return f"{here}: {refused[key]}"
    if key in retired:
        return f"{here}: retired setting; {retired[key]}"
    known = list(known)
    close = closest(str(key), [*known, *retired])
    if close is None:
        return f"{here}: {what}{extra}; valid here: {', '.join(map(str, known)) or 'none'}"
    there = dotted((*path, close))
    if close in retired:
        return f"{here}: {what}; it looks like {there}, a retired setting: {retired[close]}"
    message = f"{here}: {what}; did you mean {there}?{extra}"
    if close in how.get("missing", ()):
        message += f" {there} is required and missing: {key} is probably it, misspelt."
    return message


# ------------------------------------------------------------------------- types in words
def unwrap(tp: Any, meta: Iterable = ()) -> tuple[Any, list]:
    """``Annotated[T, ...]`` -> ``T`` and its metadata (constraints, :class:`Doc`, ...)."""
    meta = list(meta)
    while get_origin(tp) is Annotated:
        tp, *more = get_args(tp)
        for m in more:
            meta += [*m.metadata, m] if isinstance(m, FieldInfo) else [m]
    return tp, meta


def _members(tp: Any) -> tuple:
    return get_args(tp) if get_origin(tp) in (Union, types.UnionType) else ()


def bounds_words(meta: list) -> str:
    """`` in [0, 1)``, `` >= 1`` or ``""``: the bounds of a number's metadata."""
    lo = next(((m.ge, "[", ">=") for m in meta if isinstance(m, at.Ge)), None)
    lo = lo or next(((m.gt, "(", ">") for m in meta if isinstance(m, at.Gt)), None)
    hi = next(((m.le, "]", "<=") for m in meta if isinstance(m, at.Le)), None)
    hi = hi or next(((m.lt, ")", "<") for m in meta if isinstance(m, at.Lt)), None)
    if lo and hi:
        return f" in {lo[1]}{lo[0]:g}, {hi[0]:g}{hi[1]}"
    return f" {lo[2]} {lo[0]:g}" if lo else (f" {hi[2]} {hi[0]:g}" if hi else "")


def is_model(tp: Any) -> bool:
    """Whether ``tp`` is a pydantic model or a pydantic dataclass (a mapping of settings)."""
    return isinstance(tp, type) and (issubclass(tp, BaseModel) or "__pydantic_fields__" in vars(tp))


def fields_of(model: type) -> dict[str, FieldInfo]:
    """The fields of a pydantic model or dataclass."""
    return model.__pydantic_fields__


def describe(tp: Any, meta: Iterable = ()) -> str:
    """What ``tp`` allows, in words: ``an integer >= 0 or null``, ``one of 'pgd', 'ga'``."""
    tp, meta = unwrap(tp, meta)
    doc = next((m.text for m in meta if isinstance(m, Doc)), None)
    if doc is not None:
        return doc
    plain = next((m.model for m in meta if isinstance(m, PlainOf)), None)
    if plain is not None:
        return describe(plain)
    members = _members(tp)
    if type(None) in members:
        inner = [m for m in members if m is not type(None)]
        return f"{describe(inner[0], meta)} or null"
    if get_origin(tp) is Literal:
        return "one of " + ", ".join(yaml_repr(c) for c in get_args(tp))
    simple = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if tp in simple:
        return simple[tp] + bounds_words(meta)
    if get_origin(tp) in (tuple, list):
        size = next((m.min_length for m in meta if isinstance(m, at.MinLen)), 0)
        text = {0: "a list", 1: "a non-empty list"}.get(size, f"a list of at least {size} items")
        unique = ", no repeats" if any(getattr(m, "unique", False) for m in meta) else ""
        return f"{text} (each item {describe(get_args(tp)[0])}{unique})"
    if is_model(tp):
        return getattr(tp, "_describe", f"a mapping of settings ({', '.join(keys_of(tp))})")
    return "a mapping" if get_origin(tp) is dict else str(tp)


def keys_of(model: type) -> dict[str, str]:
    """YAML key -> attribute of a model's settings."""
    return {(f.alias or n): n for n, f in fields_of(model).items()}


# ------------------------------------------------------------------------ errors in words
@dataclass
class _Node:
    """Where an error's location leads: the YAML path, the type there, its model and doc."""

    path: tuple
    tp: Any
    meta: list
    model: type | None  # the model holding the last key
    doc: str | None
    hints: list


def _step(node: _Node, key: Any) -> _Node:
    tp, meta = unwrap(node.tp, node.meta)
    plain = next((m.model for m in meta if isinstance(m, PlainOf)), None)
    tp = plain or tp
    members = [m for m in _members(tp) if m is not type(None)]
    if members:  # Optional, or a union tagged by its ``type``: the member the key names
        tagged = [m for m in members if is_model(unwrap(m)[0]) and _tag(unwrap(m)[0]) == key]
        if tagged:
            return _Node(node.path, tagged[0], [], node.model, node.doc, node.hints)
        return _step(_Node(node.path, members[0], [], node.model, node.doc, node.hints), key)
    hints = node.hints
    if is_model(tp):
        hints = [*hints, tp._hint] if getattr(tp, "_hint", None) else hints
        if key == getattr(tp, "_open", None):
            return _Node(node.path, fields_of(tp)[key].annotation, [], tp, None, hints)
        field = fields_of(tp).get(keys_of(tp).get(key, key))
        if field is None:
            return _Node((*node.path, key), Any, [], tp, None, hints)
        return _Node(
            (*node.path, key), field.annotation, field.metadata, tp, field.description, hints
        )
    args = get_args(tp)
    if get_origin(tp) in (tuple, list) and isinstance(key, int):
        return _Node((*node.path, Index(key)), args[0], [], None, None, hints)
    if get_origin(tp) is dict and args:
        return _Node((*node.path, key), args[1], [], None, None, hints)
    return _Node((*node.path, key), Any, [], None, None, hints)


def _tag(model: type) -> Any:
    field = fields_of(model).get("type")
    args = get_args(field.annotation) if field is not None else ()
    return args[0] if len(args) == 1 else None


def _walk(root: type, prefix: tuple, loc: tuple) -> _Node:
    hint = getattr(root, "_hint", None)
    node = _Node(prefix, root, [], None, None, [hint] if hint else [])
    for i, key in enumerate(loc):
        if key == "[key]":
            continue
        if loc[i + 1 : i + 2] == ("[key]",):  # a mapping's key: its type, at its path
            tp, meta = unwrap(node.tp, node.meta)
            key_type = get_args(next((m for m in _members(tp) if m is not type(None)), tp))[0]
            node = _Node((*node.path, key), key_type, [], None, None, node.hints)
        else:
            node = _step(node, key)
    return node


def _value_message(err: dict, node: _Node) -> str:
    value, kind = err.get("input"), err["type"]
    if kind == "union_tag_invalid":  # a tagged union's ``type`` names no variant
        node = _step(node, "type")
        value = value.get("type") if isinstance(value, Mapping) else value
        choices = [c.strip("'") for c in err["ctx"]["expected_tags"].split(", ")]
        message = f"expected one of {', '.join(map(repr, choices))}, got {got(value)}"
        close = closest(value, choices) if isinstance(value, str) else None
        return f"{dotted(node.path)}: {message}" + (f"; did you mean {close!r}?" if close else "")
    elif kind == "value_problem":
        message = f"expected {describe(node.tp, node.meta)}, got {yaml_repr(value)}: "
        message += err["ctx"]["why"]
    else:
        message = f"expected {describe(node.tp, node.meta)}, got {got(value)}"
        choices = get_args(unwrap(node.tp)[0]) if kind == "literal_error" else ()
        close = closest(value, map(str, choices)) if isinstance(value, str) else None
        message += f"; did you mean {close!r}?" if close else ""
    return f"{dotted(node.path)}: {message}"


def _with_doc(message: str, node: _Node) -> str:
    if not node.doc or not node.path or isinstance(node.path[-1], Index):
        return message
    return f"{message}{' ' if message.endswith('?') else '; '}{node.path[-1]}: {node.doc}"


def problems(
    exc: ValidationError, root: Any, *, prefix: tuple = (), complete: bool = True
) -> list[tuple[tuple, str]]:
    """``(path, message)`` of every error of ``exc``, raised validating a value as ``root``.

    Parameters
    ----------
    exc : pydantic.ValidationError
    root : type
        The model (or annotation) validated.
    prefix : tuple
        The path of the value in the file (e.g. ``("calibrate",)``).
    complete : bool
        Report missing keys (otherwise only those of models with ``_complete``).
    """
    same = {"unexpected_keyword_argument": "extra_forbidden", "missing_argument": "missing"}
    errors = [dict(e, type=same.get(e["type"], e["type"])) for e in exc.errors(include_url=False)]
    nodes = [_walk(root, prefix, err["loc"]) for err in errors]
    missing = {
        (node.path[:-1], node.path[-1]) for e, node in zip(errors, nodes) if e["type"] == "missing"
    }
    paired = set()
    for err, node in zip(errors, nodes):
        if err["type"] == "extra_forbidden" and node.model is not None:
            close = closest(str(node.path[-1]), keys_of(node.model))
            if (node.path[:-1], close) in missing:
                paired.add((node.path[:-1], close))
    out = []
    for err, node in zip(errors, nodes):
        kind, parent, key = err["type"], node.path[:-1], node.path[-1] if node.path else None
        model = node.model
        if kind == "extra_forbidden":
            extra = getattr(model, "_open_what", "")
            message = unknown_message(
                key,
                parent,
                keys_of(model),
                retired=getattr(model, "_retired", {}),
                refused=getattr(model, "_refused", {}),
                missing=[k for (p, k) in missing if p == parent],
                what=getattr(model, "_unknown", "unknown setting"),
                extra=f" (the other keys of {dotted(parent)} are {extra})" if extra else "",
            )
        elif kind == "missing":
            if not (complete or getattr(model, "_complete", False)) or (parent, key) in paired:
                continue
            field = fields_of(model)[keys_of(model)[key]]
            template = getattr(model, "_missing", None)
            message = f"{dotted(node.path)}: " + (
                template
                or f"missing setting; add it ({key}: {field.description}; expected "
                f"{describe(field.annotation, field.metadata)})"
            )
        elif kind == "femcal":
            cross = err["ctx"].get("key")
            if cross is not None:
                node.path += cross if isinstance(cross, tuple) else (cross,)
            message = f"{dotted(node.path)}: {err['ctx']['message']}"
            message = message if cross is not None else _with_doc(message, node)
        elif kind == "union_tag_invalid":
            message = _value_message(err, node)
        else:
            message = _with_doc(_value_message(err, node), node)
        hints = [h for h in node.hints if h not in message]
        out.append((node.path, f"{message}; {hints[0]}" if hints else message))
    return out


# ----------------------------------------------------------------------------- the file
def line_numbers(text: str | None) -> Callable[[tuple], int | None]:
    """A function path -> 1-based line of that key in the YAML ``text`` (None if unknown)."""
    import yaml

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader) if text is not None else None
    except yaml.YAMLError:  # pragma: no cover - the text was loaded before
        root = None

    def line(path: tuple) -> int | None:
        node, found = root, None
        for key in path:
            if isinstance(node, yaml.MappingNode):
                match = [(k, v) for k, v in node.value if k.value == str(key)]
                if not match:
                    return found
                found, node = match[0][0].start_mark.line + 1, match[0][1]
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, Index):
                if int(key) >= len(node.value):
                    return found
                node = node.value[int(key)]
                found = node.start_mark.line + 1
            else:
                return found
        return found

    return line


def raise_problems(
    found: list[tuple[tuple, str]],
    where: str,
    text: str | None,
    given: Mapping[tuple, str] | None = None,
) -> None:
    """One ConfigError for every problem, each with its line in the file, in line order; a
    problem under a path of ``given`` (path -> command-line option) names that option."""
    if not found:
        return
    line_of, given = line_numbers(text), given or {}
    lines = []
    for path, message in found:
        flag = next((f for p, f in given.items() if tuple(path[: len(p)]) == p), None)
        message = message if message.endswith((".", "?", "!")) else message + "."
        lines.append(
            (None, f"{flag} (command line): {message}") if flag else (line_of(path), message)
        )
    lines.sort(key=lambda lm: (lm[0] is None, lm[0] or 0))
    if len(lines) == 1:
        line, message = lines[0]
        raise ConfigError(f"{where}{f', line {line}' if line else ''}: {message}")
    body = "\n".join(f"  {f'line {line}: ' if line else ''}{message}" for line, message in lines)
    raise ConfigError(f"{where}: {len(lines)} invalid settings; fix each and rerun:\n{body}")
