"""A model's terms: an effect, tied or split, acting in a set of load cases.

The diagnosis names every form of an effect it fits with one string, a *term*:

``<effect>[@<load case>,<load case>...][:split]``

* ``facet_contact``: the effect in its likely load cases (its registered form);
* ``facet_contact:split``: the same with its per-load-case parameters split
  (:mod:`femcal.effects.split`);
* ``facet_contact@Extension,AxialRotation,LateralBending``: acting in these load cases, a
  set the effect's ``load_case_prior`` allows (:class:`femcal.effects.base.Effect`); listed in
  the order of :data:`~femcal.schema.LOAD_CASES`, and left out where it is the likely set.

This module alone reads and writes that grammar: :func:`parse_term` and :func:`format_term`
(``str(Term)``). :func:`acting_in` builds the effect class of a load-case set, and
:func:`case_prior_cost` prices it against the likely set in criterion units.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

#: The suffix of a split form.
SPLIT_SUFFIX = ":split"
#: Separates an effect's name from the load cases it acts in.
CASES_MARK = "@"
#: Separates the load cases.
CASES_SEP = ","
#: A load case whose prior is at least this is *likely*: the registered form acts there.
LIKELY = 0.5

_ACTING: dict[tuple[type, tuple[str, ...]], type] = {}


@dataclass(frozen=True)
class Term:
    """One term of a model.

    Attributes
    ----------
    effect : str
        The registered effect's name.
    split : bool
        Its per-load-case parameters split (:mod:`femcal.effects.split`).
    cases : tuple of str or None
        The load cases it acts in, in :data:`~femcal.schema.LOAD_CASES` order; None: its
        likely ones (the registered form's ``load_cases``).
    """

    effect: str
    split: bool = False
    cases: tuple[str, ...] | None = None

    def __str__(self) -> str:
        return format_term(self)


def parse_term(name: str) -> Term:
    """The term a string names (see the module docstring); the effect is not looked up.

    Raises
    ------
    ConfigError
        A load case after ``@`` is not one of :data:`~femcal.schema.LOAD_CASES`, or none is
        given.
    """
    split = name.endswith(SPLIT_SUFFIX)
    body = name[: -len(SPLIT_SUFFIX)] if split else name
    effect, mark, listed = body.partition(CASES_MARK)
    if not mark:
        return Term(effect, split)
    cases = [c for c in listed.split(CASES_SEP) if c]
    unknown = [c for c in cases if c not in LOAD_CASES]
    if unknown or not cases:
        raise ConfigError(
            f"Effect term {name!r}: after '{CASES_MARK}' give load cases from "
            f"{list(LOAD_CASES)} separated by '{CASES_SEP}'; got {cases or 'none'}."
        )
    return Term(effect, split, tuple(lc for lc in LOAD_CASES if lc in cases))


def split_terms(text: str) -> list[str]:
    """The terms of a comma-separated list, as ``--effects`` takes it: a load case after a term
    with ``@`` belongs to that term (``ligament_tension@Flexion,Extension:split,neutral_zone``
    -> ``["ligament_tension@Flexion,Extension:split", "neutral_zone"]``)."""
    terms: list[str] = []
    for item in (part.strip() for part in text.split(CASES_SEP)):
        if not item:
            continue
        case = item[: -len(SPLIT_SUFFIX)] if item.endswith(SPLIT_SUFFIX) else item
        if terms and case in LOAD_CASES and CASES_MARK in terms[-1]:
            terms[-1] += CASES_SEP + item
        else:
            terms.append(item)
    return terms


def format_term(term: Term) -> str:
    """A term's string (see the module docstring): the load cases left out where they are
    the effect's likely ones (the effect is looked up only then)."""
    text = term.effect
    if term.cases is not None:
        cases = tuple(lc for lc in LOAD_CASES if lc in term.cases)
        if cases != _registered(term.effect).load_cases:
            text += CASES_MARK + CASES_SEP.join(cases)
    return text + (SPLIT_SUFFIX if term.split else "")


def _registered(effect: str) -> type:
    from femcal.effects.base import effect_registry

    return effect_registry.get(effect)


def cases_of(name: str) -> tuple[str, ...]:
    """The load cases the term ``name`` acts in (the registered effect's where none are
    written)."""
    term = parse_term(name)
    return term.cases if term.cases is not None else _registered(term.effect).load_cases


def with_cases(name: str, cases: Iterable[str]) -> str:
    """The term ``name`` acting in ``cases`` instead (its split kept)."""
    term = parse_term(name)
    return format_term(Term(term.effect, term.split, tuple(cases)))


def as_split(name: str) -> str:
    """The term ``name`` in its split form (its load cases kept)."""
    term = parse_term(name)
    return format_term(Term(term.effect, True, term.cases))


def prior_of(name: str) -> dict[str, float]:
    """The registered effect's prior per load case (cases it cannot act in left out)."""
    return dict(_registered(parse_term(name).effect).load_case_prior)


def case_prior_cost(name: str) -> float:
    """What the term's load cases cost in criterion units against the likely ones:
    ``-2 ln [P(cases) / P(likely cases)]``, each case of the prior acting or not
    independently. 0 for the likely set; inf where a case of prior 1 is left out or a case of
    prior 0 taken in."""
    prior = prior_of(name)
    cases = set(cases_of(name))
    cost = 0.0
    for lc, p in prior.items():
        likely = p >= LIKELY
        if (lc in cases) == likely:
            continue
        here, there = (p, 1.0 - p) if lc in cases else (1.0 - p, p)
        if here <= 0.0:
            return math.inf
        cost += -2.0 * math.log(here / there)
    if cases - set(prior):
        return math.inf
    return cost


def model_case_cost(model: Sequence[str]) -> float:
    """:func:`case_prior_cost` summed over a model's terms."""
    return sum(case_prior_cost(name) for name in model)


def toggles(name: str) -> list[str]:
    """The term with one load case whose prior lies strictly between 0 and 1 added or left
    out (at least one load case kept, two for a split form), in
    :data:`~femcal.schema.LOAD_CASES` order."""
    prior = prior_of(name)
    cases = cases_of(name)
    least = 2 if parse_term(name).split else 1  # a split form needs two load cases
    out = []
    for lc in LOAD_CASES:
        if not 0.0 < prior.get(lc, 0.0) < 1.0:
            continue
        new = tuple(c for c in cases if c != lc) if lc in cases else (*cases, lc)
        if len(new) >= least:
            out.append(with_cases(name, new))
    return out


def acting_in(cls: type, cases: Sequence[str]) -> type:
    """The effect class ``cls`` acting in ``cases`` (its law unchanged; built once per class
    and set of cases): ``cls`` itself where they are its ``load_cases``.

    Raises
    ------
    ConfigError
        A load case the effect's ``load_case_prior`` does not allow (prior 0 or absent).
    """
    cases = tuple(lc for lc in LOAD_CASES if lc in cases)
    if cases == tuple(cls.load_cases):
        return cls
    key = (cls, cases)
    if key not in _ACTING:
        allowed = [lc for lc, p in cls.load_case_prior.items() if p > 0]
        if not set(cases) <= set(allowed):
            raise ConfigError(
                f"Effect '{cls.name}' may act in {allowed} only (its load_case_prior); got "
                f"{list(cases)}. Leave out the other load cases, or give them a prior > 0."
            )
        _ACTING[key] = type(
            f"{cls.__name__}In{''.join(c[:3] for c in cases)}",
            (cls,),
            {
                "name": format_term(Term(cls.name, False, cases)),
                "load_cases": cases,
                "load_case_prior": dict(cls.load_case_prior),
                "__doc__": f"{cls.name} acting in {', '.join(cases)}.",
            },
        )
    return _ACTING[key]
