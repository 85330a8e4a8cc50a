"""Validation errors as femcal's messages: file, line, dotted key, what was given, the fix.

Each section's wrap validator (:func:`reword`) words the errors at its own keys: an unknown key
names the closest valid one, a missing key says what to add, a bad value gets pydantic's text,
what was given and the key's doc. :func:`problems` adds the dotted paths, :func:`raise_problems`
each line in the YAML file. :func:`describe` words what a type allows (help texts, options).
Class variables of a section tune its messages: ``_unknown`` (what an unknown key is called; a
keyword table's: ``unknown <_owner> keyword``), ``_retired``/``_refused``/``_reasons`` (key ->
what to do instead), ``_complete`` (missing keys reported in a partial check too), ``_missing``
(its message), ``_open`` (the field holding the other keys; ``_open_what`` says what they are),
``_describe`` (the section in words), ``_hint`` (appended to each message).
"""

import difflib
import re
import types
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, Union, get_args, get_origin

import annotated_types as at
import yaml
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo
from pydantic_core import PydanticCustomError

from femcal.errors import ConfigError

#: Our error types (their ``ctx`` holds the message); a ``missing_setting`` is reported only
#: in a complete check.
CUSTOM = ("setting_problem", "missing_setting")


@dataclass(frozen=True)
class Doc:
    """What a custom type allows, as messages say it (``a path (a non-empty string)``)."""

    text: str


@dataclass(frozen=True)
class PlainOf:
    """A mapping validated against ``model`` and kept as plain data (keyword arguments)."""

    model: type


def fail(message: str, key: Any = None) -> PydanticCustomError:
    """A problem in femcal's words; ``key`` (a model's cross check) extends its path."""
    return PydanticCustomError("setting_problem", "{message}", {"message": message, "key": key})


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
    """``calibrate.datasets.test``, ``plant.moments[0]`` (an int is a list position)."""
    return "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path).removeprefix(".")


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


def one_of(value: Any, names: Iterable[str]) -> str:
    """``expected one of 'a', 'b', got 'c' (str); did you mean 'a'?``."""
    names = list(names)
    close = closest(value, names) if isinstance(value, str) else None
    fix = f"; did you mean {close!r}?" if close else ""
    return f"expected one of {', '.join(map(repr, names))}, got {got(value)}{fix}"


def unknown_message(
    key: Any,
    known: Iterable[str],
    missing: Iterable = (),
    model: Any = None,
    what: str = "unknown setting",
) -> tuple[str, str | None]:
    """``unknown setting; did you mean {there}?`` and the closest key (``{there}`` stands for its
    dotted path); ``missing``: the required keys not given; ``model``: the section, whose class
    variables tune the message (module docstring)."""
    reasons = {k: f"not settable here; {v}" for k, v in getattr(model, "_reasons", {}).items()}
    retired, refused = getattr(model, "_retired", {}), {**reasons, **getattr(model, "_refused", {})}
    what = f"unknown {model._owner} keyword" if hasattr(model, "_owner") else what
    what, other = getattr(model, "_unknown", what), getattr(model, "_open_what", None)
    extra = f" (the other keys of {{parent}} are {other})" if other else ""
    if key in refused or key in retired:
        return refused.get(key) or f"retired setting; {retired[key]}", None
    known = list(known)
    close = closest(str(key), [*known, *retired])
    if close is None:
        return f"{what}{extra}; valid here: {', '.join(map(str, known)) or 'none'}", None
    if close in retired:
        return f"{what}; it looks like {{there}}, a retired setting: {retired[close]}", close
    message = f"{what}; did you mean {{there}}?{extra}"
    if close in missing:
        message += f" {{there}} is required and missing: {key} is probably it, misspelt."
    return message, close


# ------------------------------------------------------------------------- types in words
def unwrap(tp: Any, meta: Iterable = ()) -> tuple[Any, list]:
    """``Annotated[T, ...]`` -> ``T`` and its metadata (constraints, :class:`Doc`, ...), after
    ``meta``, as pydantic reads them."""
    info = FieldInfo.from_annotation(tp)
    return info.annotation, [*meta, *info.metadata]


def members(tp: Any) -> list:
    """The members of a union but None (``[]``: not a union)."""
    union = get_origin(tp) in (Union, types.UnionType)
    return [m for m in get_args(tp) if m is not type(None)] if union else []


def bounds_words(meta: list) -> str:
    """`` in [0, 1)``, `` >= 1`` or ``""``: the bounds of a number's metadata."""
    signs = {"ge": ("[", ">="), "gt": ("(", ">"), "le": ("]", "<="), "lt": (")", "<")}
    b = {type(m).__name__.lower(): m for m in meta if isinstance(m, at.Ge | at.Gt | at.Le | at.Lt)}
    b = {k: (getattr(m, k), *signs[k]) for k, m in b.items()}
    lo, hi = b.get("ge") or b.get("gt"), b.get("le") or b.get("lt")
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
    given = [m.text for m in meta if isinstance(m, Doc)]
    given += [describe(m.model) for m in meta if isinstance(m, PlainOf)]
    if given:
        return given[0]
    if type(None) in get_args(tp) and members(tp):
        return f"{describe(members(tp)[0], meta)} or null"
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
        what = f"{tp._owner} keywords" if hasattr(tp, "_owner") else "settings"
        return getattr(tp, "_describe", f"a mapping of {what} ({', '.join(keys_of(tp))})")
    return "a mapping" if get_origin(tp) is dict else str(tp)


# ------------------------------------------------------------------------ errors in words
def text(err: dict) -> str:
    """One error's message without its path: ours, or pydantic's then what was given (and,
    for a misspelt choice, the closest)."""
    if err["type"] in CUSTOM:
        return err["ctx"]["message"]
    value, expected = err.get("input"), (err.get("ctx") or {}).get("expected", "")
    message = re.sub(r"valid (tuple|list)", "list", err["msg"]).replace("dictionary", "mapping")
    close = closest(value, re.findall(r"'([^']*)'", expected)) if isinstance(value, str) else None
    return f"{message}, got {got(value)}" + (f"; did you mean {close!r}?" if close else "")


_SAME = {"unexpected_keyword_argument": "extra_forbidden", "missing_argument": "missing"}


def reword(cls: type, data: Any, handler: Callable) -> Any:
    """A wrap model validator of every section: the errors at the keys of ``cls`` in femcal's
    words (a misspelt required key is reported once, as the unknown key)."""
    try:
        return handler(data)
    except ValidationError as exc:
        title, errors = exc.title, exc.errors(include_url=False)
    keys, fields = keys_of(cls), fields_of(cls)
    errors = [{**e, "type": _SAME.get(e["type"], e["type"])} for e in errors]
    top = [(e["type"], e["loc"][0]) for e in errors if len(e["loc"]) == 1]
    missing = [k for t, k in top if t == "missing"]
    paired = {closest(str(k), keys) for t, k in top if t == "extra_forbidden"} & set(missing)
    out = []
    for err in errors:
        loc, kind, ctx, message = err["loc"], err["type"], err.get("ctx") or {}, None
        field = fields.get(keys.get(loc[0], "")) if loc else None
        if field and loc[1:] and isinstance(loc[1], int) and get_origin(field.annotation) is dict:
            loc = (loc[0], str(loc[1]), *loc[2:])  # a number key of a mapping, not a position
        loc = loc[1:] if loc and loc[0] == getattr(cls, "_open", None) else loc
        if kind == "extra_forbidden" and len(loc) == 1:
            message, close = unknown_message(loc[0], keys, missing, cls)
            kind, ctx = "setting_problem", {"close": close}
        elif kind == "missing" and len(loc) == 1:
            if loc[0] in paired:
                continue
            what = f"{field.description}; expected {describe(field.annotation, field.metadata)}"
            message = getattr(cls, "_missing", f"missing setting; add it ({loc[0]}: {what})")
            kind = "setting_problem" if getattr(cls, "_complete", False) else "missing_setting"
        elif not loc and kind not in CUSTOM:
            message = f"expected {describe(cls)}, got {got(err.get('input'))}"
        elif len(loc) == 1 and field and field.description and ctx.get("key") is None:
            message = text(err)
            message += f"{' ' if message.endswith('?') else '; '}{loc[0]}: {field.description}"
        message, hint = message or text(err), getattr(cls, "_hint", None)
        message += f"; {hint}" if hint and hint not in message else ""
        kind, ctx = kind if kind in CUSTOM else "setting_problem", {**ctx, "message": message}
        err = {"type": PydanticCustomError(kind, "{message}", ctx), "input": err.get("input")}
        out.append({**err, "loc": loc})
    raise ValidationError.from_exception_data(title, out) from None


def problems(
    exc: ValidationError, *, prefix: tuple = (), complete: bool = True
) -> list[tuple[tuple, str]]:
    """``(path, message)`` of every error of ``exc`` (raised at ``prefix`` in the file); a
    missing key only when ``complete``."""
    out = []
    for err in exc.errors(include_url=False):
        ctx = err.get("ctx") or {}
        if err["type"] == "missing_setting" and not complete:
            continue
        key = ctx.get("key")
        path = (*prefix, *(k for k in err["loc"] if k != "[key]"))
        path += () if key is None else key if isinstance(key, tuple) else (key,)
        message = text(err).replace("{parent}", dotted(path[:-1]))
        message = message.replace("{there}", dotted((*path[:-1], ctx.get("close"))))
        out.append((path, f"{dotted(path)}: {message}"))
    return out


# ----------------------------------------------------------------------------- the file
def line_of(root: Any, path: tuple) -> int | None:
    """The 1-based line of the key at ``path`` in the YAML node ``root`` (of its deepest key
    found; None: not even the first)."""
    node, found = root, None
    for key in path:
        if isinstance(node, yaml.MappingNode):
            match = [(k.start_mark.line + 1, v) for k, v in node.value if k.value == str(key)]
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            match = [(node.value[key].start_mark.line + 1, node.value[key])]
        else:
            match = []
        if not match:
            return found
        found, node = match[0]
    return found


def raise_problems(
    found: list[tuple[tuple, str]],
    where: str,
    text: str | None,
    given: Mapping[tuple, str] | None = None,
) -> None:
    """One ConfigError for every problem, each with its line in the YAML ``text``, in line
    order; a problem under a path of ``given`` (path -> command-line option) names that option."""
    if not found:
        return
    root, lines = yaml.compose(text, Loader=yaml.SafeLoader) if text is not None else None, []
    for path, message in found:
        flag = next((f for p, f in (given or {}).items() if tuple(path[: len(p)]) == p), None)
        message = message if message.endswith((".", "?", "!")) else message + "."
        lines.append(
            (None, f"{flag} (command line): {message}") if flag else (line_of(root, path), message)
        )
    lines.sort(key=lambda lm: (lm[0] is None, lm[0] or 0))
    if len(lines) == 1:
        line, message = lines[0]
        raise ConfigError(f"{where}{f', line {line}' if line else ''}: {message}")
    body = "\n".join(f"  {f'line {line}: ' if line else ''}{message}" for line, message in lines)
    raise ConfigError(f"{where}: {len(lines)} invalid settings; fix each and rerun:\n{body}")
