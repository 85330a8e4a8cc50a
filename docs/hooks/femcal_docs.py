"""MkDocs hook: the pages femcal generates at build time (mkdocs.yml, ``hooks:``).

A page asks for generated content with an HTML comment on a line of its own:

* ``<!-- femcal:cli -->``: ``femcal --help`` and each sub-command's help, from the argparse
  parser of :func:`femcal.cli.build_parser` (nothing is run);
* ``<!-- femcal:settings root -->`` / ``<!-- femcal:settings fe-only -->``: a table of every key
  of ``params.yaml`` / of the sections only ``fe/params.yaml`` has, from the settings model of
  :mod:`femcal.settings`;
* ``<!-- femcal:environment -->``: the environment variables femcal reads;
* ``<!-- femcal:figure NAME | CAPTION -->``: ``docs/figures/NAME`` when the figure script has
  made it, else a note saying how to make it (so the page builds on a fresh clone);
* ``<!-- femcal:json PATH -->``: a two-column table of a flat JSON file of the repository
  (a DVC metrics file), or a note when it is absent;
* ``<!-- femcal:include PATH -->``: a Markdown file of the repository, e.g. ``CHANGELOG.md``.

It also adds to the nav the optional pages listed in ``OPTIONAL_PAGES`` that exist.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import typing
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.femcal_docs")

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
MARKER = re.compile(r"^<!-- femcal:(\w+)\s*(.*?)\s*-->$", re.M)

#: Pages other engineers write: (nav section, title, file); listed only when the file exists.
OPTIONAL_PAGES = [
    ("Benchmarks", "Anatomy cohorts", "anatomy-cohorts.md"),
    ("Explanation", "FE posterior elements", "fe-posterior-elements.md"),
]


# ------------------------------------------------------------------------------------- nav
def on_config(config, **kwargs):
    nav = config.get("nav") or []
    for section, title, name in OPTIONAL_PAGES:
        if not (DOCS / name).is_file():
            continue
        for entry in nav:
            if isinstance(entry, dict) and section in entry:
                if {title: name} not in entry[section]:  # `mkdocs serve` rebuilds
                    entry[section].append({title: name})
                break
    return config


# ------------------------------------------------------------------------------------- CLI
def cli_markdown() -> str:
    from femcal.cli import build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal: one width for every build
    try:
        parser = build_parser()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        helps = {a.dest: a.help for a in sub._choices_actions}
        parts = ["## `femcal`", "", "```text", parser.format_help().rstrip(), "```", ""]
        for name, p in sub.choices.items():
            parts += [f"## `femcal {name}`", "", helps.get(name) or "", ""]
            parts += ["```text", p.format_help().rstrip(), "```", ""]
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old
    return "\n".join(parts)


# -------------------------------------------------------------------------------- settings
def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _default(info: object, model: type) -> str:
    from femcal.settings.values import Keywords

    if info.is_required():
        return "required"
    value = info.get_default(call_default_factory=True)
    options = getattr(model, "_options", None)  # keywords declared by an options dataclass
    name = next(n for n, i in model.__pydantic_fields__.items() if i is info)
    if value is None and name in getattr(options, "__dataclass_fields__", {}):
        value = options.__dataclass_fields__[name].default
    elif value is None and issubclass(model, Keywords):
        return "the function's" if model._owner != "function" else "not set"
    return f"`{json.dumps(value, default=str)}`"


def _models(annotation: object, metadata: list | tuple = ()) -> list[type]:
    """Models with settings inside a type annotation (``X | None``, ``dict[str, X]``, a
    mapping validated against a model and kept as given); a search space's entries are one
    row (its own)."""
    from femcal.settings._format import PlainOf, is_model, unwrap

    tp, meta = unwrap(annotation, metadata)
    plain = [m.model for m in meta if isinstance(m, PlainOf)]
    if plain:
        return [m for m in plain if not hasattr(m, "_keywords")]
    if is_model(tp):
        return [tp]
    return [m for arg in typing.get_args(tp) for m in _models(arg)]


def _class_rows(model: type, prefix: str) -> list[tuple[str, str, str, str]]:
    """(key, allowed values, default, doc) of every setting of ``model``, nested ones too."""
    from femcal.settings._format import describe, fields_of

    rows: list[tuple[str, str, str, str]] = []
    opened = getattr(model, "_open", None)  # e.g. train's splits: their keys are names
    for name, info in fields_of(model).items():
        key = f"{prefix}.<name>" if name == opened else f"{prefix}.{info.alias or name}"
        if name != opened:
            allowed = describe(info.annotation, info.metadata)
            rows.append((key, allowed, _default(info, model), info.description or ""))
        by_name = typing.get_origin(info.annotation) is dict and not any(
            type(m).__name__ == "PlainOf" for m in info.metadata
        )
        for inner in _models(info.annotation, info.metadata):
            below = f"{key}.<name>" if by_name and name != opened else key
            rows += _class_rows(inner, below)
    return rows


def settings_markdown(schema: str) -> str:
    from femcal.settings import SECTIONS

    kind = schema.removesuffix("-only")
    out = []
    for name, (model, files) in SECTIONS.items():
        if kind not in files or (schema.endswith("-only") and set(files) != {kind}):
            continue
        doc = (model.__doc__ or "").strip().splitlines()[0] if model.__doc__ else ""
        doc = re.sub(r"^``[^`]+``: ", "", doc).replace("``", "`")
        out += [f"### `{name}`", "", doc[:1].upper() + doc[1:], ""]
        out += ["| key | allowed | default | what |", "| --- | --- | --- | --- |"]
        for key, allowed, default, what in _class_rows(model, name):
            out.append(f"| `{key}` | {_cell(allowed)} | {_cell(default)} | {_cell(what)} |")
        out.append("")
    return "\n".join(out)


def environment_markdown() -> str:
    from femcal import settings

    env = getattr(settings, "ENVIRONMENT", {})
    lines = ["| variable | read by | what |", "| --- | --- | --- |"]
    for name, var in env.items():
        commands = ", ".join(f"`{c}`" for c in getattr(var, "commands", ()))
        lines.append(f"| `{name}` | {commands} | {_cell(getattr(var, 'doc', ''))} |")
    return "\n".join(lines)


# --------------------------------------------------------------------- figures, files, json
def figure_markdown(arg: str, page_dir: Path) -> str:
    name, _, caption = (s.strip() for s in arg.partition("|"))
    path = DOCS / "figures" / name
    if path.is_file():
        rel = os.path.relpath(path, page_dir).replace(os.sep, "/")
        return f"![{caption}]({rel})\n\n*{caption}*"
    return (
        f'!!! note "Figure not built: {name}"\n'
        f"    {caption}. Run `dvc repro` (or `dvc pull`), then "
        "`.venv/bin/python docs/scripts/tutorial_figures.py`, then build the site again."
    )


def json_markdown(arg: str) -> str:
    path = ROOT / arg
    if not path.is_file():
        return f'!!! note "Not found: {arg}"\n    `dvc repro` writes it.'
    data = json.loads(path.read_text())
    lines = [f"`{arg}`:", "", "| key | value |", "| --- | --- |"]
    for key, value in data.items():
        if isinstance(value, float):
            value = f"{value:.4g}"
        lines.append(f"| `{key}` | {_cell(value)} |")
    return "\n".join(lines)


def include_markdown(arg: str) -> str:
    """A Markdown file of the repository; ``PATH demote`` drops its title and moves every
    other heading one level down. A file under docs/figures/ or reports/ that is absent (a
    fresh clone) becomes a note; any other absent file fails the build."""
    name, _, option = arg.partition(" ")
    path = ROOT / name
    if not path.is_file() and name.startswith(("docs/figures/", "reports/")):
        return (
            f'!!! note "Not built here: {name}"\n'
            "    `dvc repro` (then, for docs/figures/, "
            "`.venv/bin/python docs/scripts/tutorial_figures.py`) writes it."
        )
    text = path.read_text()
    if option.strip() == "demote":
        text = re.sub(r"\A# .*\n", "", text)
        text = re.sub(r"^(#+) ", r"#\1 ", text, flags=re.M)
    return text


def on_page_markdown(markdown, page, config, files, **kwargs):
    page_dir = (DOCS / page.file.src_uri).parent

    def replace(match: re.Match) -> str:
        kind, arg = match.group(1), match.group(2)
        if kind == "cli":
            return cli_markdown()
        if kind == "settings":
            return settings_markdown(arg or "root")
        if kind == "environment":
            return environment_markdown()
        if kind == "figure":
            return figure_markdown(arg, page_dir)
        if kind == "json":
            return json_markdown(arg)
        if kind == "include":
            return include_markdown(arg)
        log.warning("%s: unknown femcal marker %r", page.file.src_uri, kind)
        return match.group(0)

    return MARKER.sub(replace, markdown)
