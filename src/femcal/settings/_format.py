"""Pydantic's validation errors as femcal's messages: file, line, key, what was given, the fix.

:func:`describe` words what a type allows (``an integer >= 0 or null``); :func:`problems`
turns a ValidationError into ``(path, message)`` pairs (an unknown key names the closest valid
one); :func:`raise_problems` adds each line in the YAML file and raises one ConfigError.
Models tune the messages with class variables: ``_unknown`` (what an unknown key is called),
``_retired``/``_refused`` (key -> what to do instead), ``_complete`` (missing keys reported in
a partial check too), ``_missing`` (its message), ``_open`` (the field holding the other keys;
``_open_what`` says what they are), ``_describe`` (the model in words), ``_hint`` (appended).
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
    """``value`` as YAML writes it (null, true, lists), cut to 60 characters."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    text = repr(list(value) if isinstance(value, tuple) else value)
    return text if len(text) <= 60 else text[:57] + "..."


def got(value: Any) -> str:
    """``'ten' (str)``: what was given, as the message shows it."""
    kind = "mapping" if isinstance(value, Mapping) else type(value).__name__
    return f"{yaml_repr(value)} ({'null' if value is None else kind})"


def dotted(path: Iterable) -> str:
    """``calibrate.datasets.test``, ``plant.moments[0]``: a path as messages show it."""
    out = ""
    for key in path:
        out += f"[{int(key)}]" if isinstance(key, Index) else ("." if out else "") + str(key)
    return out


def closest(word: str, candidates: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The candidate closest to ``word`` (difflib's ratio, case-insensitive, also with the
    words sorted: ``plot_max`` ~ ``max_plots``), or None below ``cutoff``."""

    def score(a: str, b: str) -> float:
        a, b = a.lower(), b.lower()
        sort = lambda s: "_".join(sorted(re.split(r"[_\-.]", s)))  # noqa: E731
        return max(
            difflib.SequenceMatcher(None, x, y).ratio() for x, y in ((a, b), (sort(a), sort(b)))
        )

    scored = [(score(str(word), str(c)), str(c)) for c in candidates]
    return max([sc for sc in scored if sc[0] >= cutoff], key=lambda sc: sc[0], default=(0, None))[1]


def unknown_message(key: Any, path: tuple, known: Iterable[str], **how: Any) -> str:
    """``calibrate.plot_max: unknown setting; did you mean calibrate.max_plots?``; ``how``:
    ``retired``/``refused`` (key -> text), ``missing`` (required keys not given), ``what``
    (default "unknown setting"), ``extra`` (appended to the first clause)."""
    retired, refused = how.get("retired", {}), how.get("refused", {})
    what, extra, here = (
        how.get("what", "unknown setting"),
        how.get("extra", ""),
        dotted((*path, key)),
    )
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


def _members(tp: Any) -> list:
    """The members of a union but None (``[]``: not a union)."""
    union = get_origin(tp) in (Union, types.UnionType)
    return [m for m in get_args(tp) if m is not type(None)] if union else []


def bounds_words(meta: list) -> str:
    """`` in [0, 1)``, `` >= 1`` or ``""``: the bounds of a number's metadata."""
    b = {
        k: getattr(m, k)
        for m in meta
        for k in ("ge", "gt", "le", "lt")
        if isinstance(m, getattr(at, k.title()))
    }
    lo = ("ge" in b and (b["ge"], "[", ">=")) or ("gt" in b and (b["gt"], "(", ">"))
    hi = ("le" in b and (b["le"], "]", "<=")) or ("lt" in b and (b["lt"], ")", "<"))
    if lo and hi:
        return f" in {lo[1]}{lo[0]:g}, {hi[0]:g}{hi[1]}"
    return f" {lo[2]} {lo[0]:g}" if lo else (f" {hi[2]} {hi[0]:g}" if hi else "")


def is_model(tp: Any) -> bool:
    """Whether ``tp`` is a pydantic model or a pydantic dataclass (a mapping of settings)."""
    return isinstance(tp, type) and (issubclass(tp, BaseModel) or "__pydantic_fields__" in vars(tp))


def fields_of(model: type) -> dict[str, FieldInfo]:
    """The fields of a pydantic model or dataclass."""
    return model.__pydantic_fields__


def keys_of(model: type) -> dict[str, str]:
    """YAML key -> attribute of a model's settings."""
    return {(f.alias or n): n for n, f in fields_of(model).items()}


def describe(tp: Any, meta: Iterable = ()) -> str:
    """What ``tp`` allows, in words: ``an integer >= 0 or null``, ``one of 'pgd', 'ga'``."""
    tp, meta = unwrap(tp, meta)
    for kind in (Doc, PlainOf):
        found = [m for m in meta if isinstance(m, kind)]
        if found:
            return found[0].text if kind is Doc else describe(found[0].model)
    if type(None) in get_args(tp) and _members(tp):
        return f"{describe(_members(tp)[0], meta)} or null"
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


# ------------------------------------------------------------------------ errors in words
@dataclass
class _Node:
    """Where an error's location leads: the YAML path, the type there (with its metadata),
    the model holding the last key, that key's doc and the hints of the models passed."""

    path: tuple
    tp: Any
    meta: Any = ()
    model: type | None = None
    doc: str | None = None
    hints: tuple = ()


def _tag(model: type) -> Any:
    """The one value of a model's ``type`` field (the tag of a tagged union), or None."""
    args = get_args(fields_of(model)["type"].annotation) if "type" in fields_of(model) else ()
    return args[0] if len(args) == 1 else None


def _step(node: _Node, key: Any) -> _Node:
    """The node ``key`` leads to from ``node``."""
    tp, meta = unwrap(node.tp, node.meta)
    tp = next((m.model for m in meta if isinstance(m, PlainOf)), tp)
    if _members(tp):  # Optional, or a union tagged by its ``type``: the member the key names
        tagged = [m for m in _members(tp) if is_model(unwrap(m)[0]) and _tag(unwrap(m)[0]) == key]
        member = _Node(node.path, (tagged or _members(tp))[0], [], node.model, node.doc, node.hints)
        return member if tagged else _step(member, key)
    path, hints = (*node.path, key), node.hints
    if is_model(tp):
        hints += (tp._hint,) if getattr(tp, "_hint", None) else ()
        if key == getattr(tp, "_open", None):
            return _Node(node.path, fields_of(tp)[key].annotation, [], tp, None, hints)
        field = fields_of(tp).get(keys_of(tp).get(key, key))
        if field is None:
            return _Node(path, Any, [], tp, None, hints)
        return _Node(path, field.annotation, field.metadata, tp, field.description, hints)
    args = get_args(tp)
    if get_origin(tp) in (tuple, list) and isinstance(key, int):
        return _Node((*node.path, Index(key)), args[0], hints=hints)
    return _Node(path, args[1] if get_origin(tp) is dict and args else Any, hints=hints)


def _walk(root: type, prefix: tuple, loc: tuple) -> _Node:
    """The node of an error's location ``loc`` in ``root``, at ``prefix`` in the file."""
    node = _Node(prefix, root, [], hints=(root._hint,) if getattr(root, "_hint", None) else ())
    for i, key in enumerate(loc):
        if key == "[key]":
            continue
        if loc[i + 1 : i + 2] == ("[key]",):  # a mapping's key: its type, at its path
            tp = unwrap(node.tp, node.meta)[0]
            key_type = get_args((_members(tp) or [tp])[0])[0]
            node = _Node((*node.path, key), key_type, [], hints=node.hints)
        else:
            node = _step(node, key)
    return node


def _value_message(err: dict, node: _Node) -> str:
    """``key: expected <what is allowed>, got <value> (<type>)[; did you mean ...?]``."""
    value, kind = err.get("input"), err["type"]
    if kind == "union_tag_invalid":  # a tagged union's ``type`` names no variant
        node = _step(node, "type")
        value = value.get("type") if isinstance(value, Mapping) else value
        choices = [c.strip("'") for c in err["ctx"]["expected_tags"].split(", ")]
        message = f"expected one of {', '.join(map(repr, choices))}, got {got(value)}"
    elif kind == "value_problem":
        message = f"expected {describe(node.tp, node.meta)}, got {yaml_repr(value)}: "
        return f"{dotted(node.path)}: {message}{err['ctx']['why']}"
    else:
        message = f"expected {describe(node.tp, node.meta)}, got {got(value)}"
        choices = get_args(unwrap(node.tp)[0]) if kind == "literal_error" else ()
    close = closest(value, map(str, choices)) if isinstance(value, str) else None
    return f"{dotted(node.path)}: {message}" + (f"; did you mean {close!r}?" if close else "")


def _with_doc(message: str, node: _Node) -> str:
    """The message, then the key's doc (``max_plots: per-specimen PNGs ...``)."""
    if not node.doc or not node.path or isinstance(node.path[-1], Index):
        return message
    return f"{message}{' ' if message.endswith('?') else '; '}{node.path[-1]}: {node.doc}"


def _message(err: dict, node: _Node, missing: set, paired: set, complete: bool) -> str | None:
    """The message of one error (None: not reported)."""
    kind, model = err["type"], node.model
    parent, key = node.path[:-1], node.path[-1] if node.path else None
    if kind == "extra_forbidden":
        extra = getattr(model, "_open_what", "")
        return unknown_message(
            key,
            parent,
            keys_of(model),
            retired=getattr(model, "_retired", {}),
            refused=getattr(model, "_refused", {}),
            missing=[k for (p, k) in missing if p == parent],
            what=getattr(model, "_unknown", "unknown setting"),
            extra=f" (the other keys of {dotted(parent)} are {extra})" if extra else "",
        )
    if kind == "missing":
        if not (complete or getattr(model, "_complete", False)) or (parent, key) in paired:
            return None
        field = fields_of(model)[keys_of(model)[key]]
        return f"{dotted(node.path)}: " + getattr(
            model,
            "_missing",
            f"missing setting; add it ({key}: {field.description}; expected "
            f"{describe(field.annotation, field.metadata)})",
        )
    if kind == "femcal":
        cross = err["ctx"].get("key")
        if cross is not None:
            node.path += cross if isinstance(cross, tuple) else (cross,)
            return f"{dotted(node.path)}: {err['ctx']['message']}"
        return _with_doc(f"{dotted(node.path)}: {err['ctx']['message']}", node)
    message = _value_message(err, node)
    return message if kind == "union_tag_invalid" else _with_doc(message, node)


def problems(
    exc: ValidationError, root: Any, *, prefix: tuple = (), complete: bool = True
) -> list[tuple[tuple, str]]:
    """``(path, message)`` of every error of ``exc``, raised validating a value as ``root``
    (a model or annotation) at ``prefix`` in the file (e.g. ``("calibrate",)``); missing keys
    only when ``complete`` (or in models with ``_complete``)."""
    same = {"unexpected_keyword_argument": "extra_forbidden", "missing_argument": "missing"}
    errors = [dict(e, type=same.get(e["type"], e["type"])) for e in exc.errors(include_url=False)]
    nodes = [_walk(root, prefix, err["loc"]) for err in errors]
    missing = {(n.path[:-1], n.path[-1]) for e, n in zip(errors, nodes) if e["type"] == "missing"}
    paired = (
        {  # a misspelt required key: reported once, as the unknown key
            (n.path[:-1], closest(str(n.path[-1]), keys_of(n.model)))
            for e, n in zip(errors, nodes)
            if e["type"] == "extra_forbidden" and n.model is not None
        }
        & missing
    )
    out = []
    for err, node in zip(errors, nodes):
        message = _message(err, node, missing, paired, complete)
        if message is not None:
            hints = [h for h in node.hints if h not in message]
            out.append((node.path, f"{message}; {hints[0]}" if hints else message))
    return out


# ----------------------------------------------------------------------------- the file
def line_numbers(text: str | None) -> Callable[[tuple], int | None]:
    """A function path -> 1-based line of that key in the YAML ``text`` (None if unknown)."""
    import yaml

    root = yaml.compose(text, Loader=yaml.SafeLoader) if text is not None else None

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
    line_of, lines = line_numbers(text), []
    for path, message in found:
        flag = next((f for p, f in (given or {}).items() if tuple(path[: len(p)]) == p), None)
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
