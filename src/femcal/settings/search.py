"""Optuna search spaces: ``search_space`` entries over the keywords of an estimator.

Each entry is ``{type: float|int|categorical, low, high, log, choices}`` (the form
:func:`femcal.training.study.suggest` reads), and its bounds or choices must be valid values of the
hyper-parameter itself.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

from femcal.settings._checks import Bool, Check, Choice, Float, FnCheck, Int, ListOf
from femcal.settings._messages import BAD, Context, Index, Invalid, got
from femcal.settings._validate import Keywords, Section, optional, setting


def _scalar(value: Any, path: tuple, ctx: Context) -> Any:
    if value is None or isinstance(value, list | dict):
        raise Invalid(f"expected a number, string or boolean, got {got(value)}")
    return value


@dataclass(frozen=True)
class SearchEntry:
    """One Optuna search-space entry: ``{type, low, high, log}`` or ``{type, choices}``."""

    _complete: ClassVar[bool] = True

    type: str = setting(Choice(("float", "int", "categorical")), "the Optuna distribution")
    low: float | None = optional(Float(), "lower bound (float and int)")
    high: float | None = optional(Float(), "upper bound (float and int)")
    log: bool = setting(Bool(), "sample in log scale (float and int; needs low > 0)", False)
    choices: tuple | None = optional(
        ListOf(FnCheck("a number, string or boolean", _scalar), min_len=1, unique=True),
        "the values to choose from (categorical)",
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


class SearchSpace(Check):
    """An Optuna search space over the keywords of ``table`` (see
    :func:`femcal.training.study.suggest`).

    Each entry is ``{type: float|int|categorical, low, high, log, choices}``: float and int
    need ``low < high`` (``low > 0`` with ``log``), categorical needs ``choices``; the bounds
    and choices must be valid values of the hyper-parameter itself.
    """

    def __init__(self, keywords: Keywords) -> None:
        self.keywords = keywords

    def describe(self) -> str:
        return "a mapping hyper-parameter -> {type: float|int|categorical, low, high, log, choices}"

    def __call__(self, value: Any, path: tuple, ctx: Context) -> Any:
        out, bad = {}, False
        for name, spec in self.mapping(value).items():
            if self.keywords.reject(name, path, ctx):
                bad = True
                continue
            out[name] = self._entry(name, spec, (*path, name), ctx)
            bad |= out[name] is BAD
        return BAD if bad else out

    def _entry(self, name: str, spec: Any, path: tuple, ctx: Context) -> Any:
        entry = ctx.check(Section(SearchEntry), spec, path)
        if entry is BAD:
            return BAD
        check, _ = self.keywords.table[name]
        kinds = _search_kinds(check)
        if entry.type not in kinds:
            allowed = " or ".join(kinds) if kinds else "none (it cannot be searched)"
            fix = "; search width and depth instead" if name == "hidden" else ""
            ctx.report_at(
                (*path, "type"),
                f"{name} is {check.describe()}, so type {entry.type} does not fit; "
                f"use {allowed}{fix}",
            )
            return BAD
        bad = False
        if entry.type == "categorical":
            for i, choice in enumerate(entry.choices):
                bad |= ctx.check(check, choice, (*path, "choices", Index(i))) is BAD
        else:
            for bound in ("low", "high"):  # as written: 16 for an int, 0.001 for a float
                bad |= ctx.check(check, spec[bound], (*path, bound)) is BAD
        return BAD if bad else entry


def _search_kinds(check: Check) -> tuple[str, ...]:
    if isinstance(check, Int):
        return ("int", "categorical")
    if isinstance(check, Float):
        return ("float", "int", "categorical")
    if isinstance(check, Bool | Choice):
        return ("categorical",)
    return ()
