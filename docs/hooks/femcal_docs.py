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
import dataclasses
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


def _default(value: object) -> str:
    if value is dataclasses.MISSING:
        return "required"
    return f"`{json.dumps(value, default=str)}`"


def _models(annotation: object) -> list[type]:
    """Classes with settings inside a type annotation (``X | None``, ``dict[str, X]``)."""
    if isinstance(annotation, type) and (
        dataclasses.is_dataclass(annotation) or hasattr(annotation, "model_fields")
    ):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


def _check_rows(check: object, key: str) -> list[tuple[str, str, str, str]]:
    """Rows below a key whose check holds further settings (sections, maps, keyword tables)."""
    inner = getattr(check, "inner", None)
    if inner is not None:  # Nullable
        return _check_rows(inner, key)
    if hasattr(check, "cls"):  # Section
        return _class_rows(check.cls, key)
    if hasattr(check, "value") and hasattr(check, "what"):  # MapOf
        return _check_rows(check.value, f"{key}.<name>")
    table = getattr(check, "table", None)
    if isinstance(table, dict):  # Keywords: keyword -> (check, doc)
        return [
            (f"{key}.{k}", c.describe(), "the function's", doc)
            for k, (c, doc) in table.items()
            if hasattr(c, "describe")
        ]
    return []


def _hidden_rows(key: str) -> list[tuple[str, str, str, str]]:
    """Settings behind a check function the walk cannot see into: a dataset entry of
    ``calibrate.datasets`` and each calibrator's options (``calibrate.options.<method>``)."""
    import femcal.settings as settings

    if key == "calibrate.datasets" and hasattr(settings, "DatasetSettings"):
        return _class_rows(settings.DatasetSettings, f"{key}.<name>")
    if key == "calibrate.options":
        options = getattr(settings, "CALIBRATOR_OPTIONS", {})
        return [row for m, check in options.items() for row in _check_rows(check, f"{key}.{m}")]
    return []


def _class_rows(cls: type, prefix: str) -> list[tuple[str, str, str, str]]:
    """(key, allowed values, default, doc) of every setting of ``cls``, nested ones too."""
    rows: list[tuple[str, str, str, str]] = []
    if hasattr(cls, "model_fields"):  # a pydantic model
        for name, info in cls.model_fields.items():
            key = f"{prefix}.{info.alias or name}"
            default = "required" if info.is_required() else _default(info.get_default())
            allowed = getattr(info.annotation, "__name__", None) or str(info.annotation)
            rows.append((key, allowed.replace("typing.", ""), default, info.description or ""))
            for model in _models(info.annotation):
                rows += _class_rows(model, key)
        return rows
    for f in dataclasses.fields(cls):
        check = f.metadata.get("check")
        if check is None:
            continue
        key = f"{prefix}.{f.metadata.get('key') or f.name}"
        if f.default is not dataclasses.MISSING:
            default = _default(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default = _default(f.default_factory())
        else:
            default = "required"
        rows.append((key, check.describe(), default, f.metadata.get("doc", "")))
        rows += _check_rows(check, key) or _hidden_rows(key)
    opened = getattr(cls, "_open", None)  # e.g. train's splits: (attribute, check, what)
    if isinstance(opened, tuple) and len(opened) >= 2:
        rows += _check_rows(opened[1], f"{prefix}.<name>")
    return rows


def settings_markdown(schema: str) -> str:
    from femcal.settings import params

    sections = getattr(params, "_SECTIONS", None)
    hints = typing.get_type_hints(params.Settings)
    out = []
    for name, hint in hints.items():
        models = _models(hint)
        if not models:
            continue
        if sections is not None and name in sections:
            wanted = sections[name][1]  # the schemas that have this section
            if schema.removesuffix("-only") not in wanted:
                continue
            others = {"root", "fe"} - {schema.removesuffix("-only")}
            if schema.endswith("-only") and others & set(wanted):
                continue
        cls = models[0]
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        doc = re.sub(r"^``[^`]+``: ", "", doc).replace("``", "`")
        out += [f"### `{name}`", "", doc[:1].upper() + doc[1:], ""]
        out += ["| key | allowed | default | what |", "| --- | --- | --- | --- |"]
        for key, allowed, default, what in _class_rows(cls, name):
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
