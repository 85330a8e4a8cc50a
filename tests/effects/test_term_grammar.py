"""The term grammar (``<effect>@<load cases>:split``) is read and written in one module.

:mod:`femcal.effects.terms` holds it (:class:`~femcal.effects.terms.Term` and
:class:`~femcal.effects.terms.Model`, their ``parse`` and ``str``); every other module of
``src/femcal`` uses those types. This test walks the syntax tree of every other module and
fails where one takes a term string apart or puts one together itself.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from femcal.effects.terms import Model, Term

SRC = Path(__file__).resolve().parents[2] / "src" / "femcal"
#: The module that reads and writes the grammar.
GRAMMAR = SRC / "effects" / "terms.py"
#: The grammar's names: using one outside the module is parsing or writing it.
NAMES = {"SPLIT_SUFFIX", "CASES_MARK", "CASES_SEP", "TERMS_SEP"}
#: String methods that take a term apart or test its marks.
METHODS = {
    "partition",
    "rpartition",
    "split",
    "rsplit",
    "endswith",
    "startswith",
    "removesuffix",
    "removeprefix",
    "index",
    "find",
    "rfind",
    "count",
    "replace",
}
#: Other ``@`` notations that are not terms: an MLflow model alias (``models:/name@alias``),
#: split in tracking.py and recognised in settings/values.py.
NOT_TERMS = {("tracking.py", "@"), ("values.py", "@")}


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the docstring constants of a module, its classes and functions."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(
            node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef
        ) and (doc := node.body[:1]):
            if isinstance(doc[0], ast.Expr) and isinstance(doc[0].value, ast.Constant):
                out.add(id(doc[0].value))
    return out


def _is_mark(value: object) -> bool:
    """A string constant that is the grammar's mark or holds the split suffix."""
    return isinstance(value, str) and (value == "@" or ":split" in value)


def offenders(text: str, name: str) -> list[str]:
    """Where the module ``name`` (its source ``text``) parses or writes the term grammar
    itself: ``name:line: what``."""
    tree = ast.parse(text, filename=name)
    file_name = Path(name).name
    docs = _docstrings(tree)
    out = []
    for node in ast.walk(tree):
        what = None
        if isinstance(node, ast.Name) and node.id in NAMES:
            what = node.id
        elif isinstance(node, ast.Attribute) and node.attr in NAMES:
            what = node.attr
        elif isinstance(node, ast.alias) and node.name in NAMES:
            what = f"import {node.name}"
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in METHODS
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and _is_mark(node.args[0].value)
            and (file_name, node.args[0].value) not in NOT_TERMS
        ):
            what = f".{node.func.attr}({node.args[0].value!r})"
        elif (
            isinstance(node, ast.Compare)
            and isinstance(node.left, ast.Constant)
            and _is_mark(node.left.value)
            and any(isinstance(op, ast.In | ast.NotIn) for op in node.ops)
            and (file_name, node.left.value) not in NOT_TERMS
        ):
            what = f"{node.left.value!r} in ..."
        elif (
            isinstance(node, ast.Constant)
            and id(node) not in docs
            and isinstance(node.value, str)
            and node.value.endswith(":split")
        ):
            what = f"writes {node.value!r}"
        if what:
            out.append(f"{name}:{getattr(node, 'lineno', '?')}: {what}")
    return out


def test_no_module_but_the_terms_module_parses_or_writes_a_term():
    found = [
        hit
        for path in sorted(SRC.rglob("*.py"))
        if path != GRAMMAR
        for hit in offenders(path.read_text(), str(path.relative_to(SRC)))
    ]
    assert not found, (
        "These places parse or write the term grammar themselves; use "
        "femcal.effects.terms.Term / Model (Term.parse, Model.parse, str(term), str(model)) "
        "and their attributes instead:\n" + "\n".join(found)
    )


@pytest.mark.parametrize(
    "code",
    [
        "split = name.endswith(':split')",
        "effect, _, cases = name.partition('@')",
        "from femcal.effects.terms import SPLIT_SUFFIX",
        "label = name + ':split'",
        "label = f'{name}:split'",
        "acting = '@' in name",
    ],
)
def test_the_scan_finds_a_term_taken_apart_or_put_together(code):
    assert offenders(code + "\n", "diagnose/probe.py"), code


def test_the_scan_leaves_docstrings_and_other_notations_alone():
    code = (
        '"""The split form, ``facet_contact:split``."""\n'
        "name, alias = ref.split('@', 1)\n"
        "lc = text.split(':')[0]\n"
    )
    assert offenders(code, "tracking.py") == []


def test_a_model_reads_back_what_it_writes():
    text = "facet_contact@Extension,LateralBending,AxialRotation:split+neutral_zone"
    model = Model.parse(text)
    assert str(model) == text and Model.parse(str(model)) == model
    assert model.effects == ("facet_contact", "neutral_zone") and model.n_split == 1
    assert str(Model()) == "none" and Model.parse("none") == Model()
    assert Model.of(Term("neutral_zone"), Term("facet_contact")) == Model.parse(
        "facet_contact+neutral_zone"
    )


#: The helpers that take a term's string (``femcal.effects.terms`` and ``.split``): the
#: command line's and the files', not the search's.
STRING_HELPERS = {
    "parse_term",
    "format_term",
    "split_terms",
    "base_name",
    "is_split",
    "cases_of",
    "with_cases",
    "as_split",
    "toggles",
    "prior_of",
    "case_prior_cost",
    "model_case_cost",
}
#: The diagnosis' edges: the result (its written terms) and the out-of-box reading, which
#: reads the probabilities' labels.
EDGES = {"result.py", "report.py", "outside.py"}


@pytest.mark.parametrize(
    "path",
    sorted(p for p in (SRC / "diagnose").glob("*.py") if p.name not in EDGES),
    ids=lambda p: p.name,
)
def test_the_search_uses_terms_and_models_not_their_strings(path):
    tree = ast.parse(path.read_text())
    used = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        and node.module in ("femcal.effects.terms", "femcal.effects.split")
        for alias in node.names
    }
    assert not used & STRING_HELPERS, (
        f"{path.name} imports {sorted(used & STRING_HELPERS)}: the search works on "
        "femcal.effects.terms.Term and Model (their attributes and methods)."
    )
