"""A model's terms: an effect, tied or split, acting in a set of load cases; and a model, the
set of its terms.

The diagnosis names every form of an effect it fits with one string, a *term*:

``<effect>[@<load case>,<load case>...][:split]``

* ``facet_contact``: the effect in its likely load cases (its registered form);
* ``facet_contact:split``: the same with its per-load-case parameters split
  (:mod:`femcal.effects.split`);
* ``facet_contact@Extension,AxialRotation,LateralBending``: acting in these load cases, a
  set the effect's ``load_case_prior`` allows (:class:`femcal.effects.base.Effect`); listed in
  the order of :data:`~femcal.schema.LOAD_CASES`, and left out where it is the likely set.

A model is its terms joined by ``+`` (``facet_contact:split+ligament_tension``), ``none`` for
the disc alone.

This module alone reads and writes that grammar: :meth:`Term.parse` and ``str(Term)``,
:meth:`Model.parse` and ``str(Model)``. A :class:`Term` and a :class:`Model` are the
diagnosis' own values (hashable, ordered by their strings); the functions on strings below
serve the command line and the files. :func:`acting_in` builds the effect class of a
load-case set, and :meth:`Term.case_cost` prices it against the likely set in criterion units.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from functools import cached_property, total_ordering

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

#: The suffix of a split form.
SPLIT_SUFFIX = ":split"
#: Separates an effect's name from the load cases it acts in.
CASES_MARK = "@"
#: Separates the load cases.
CASES_SEP = ","
#: Joins a model's terms.
TERMS_SEP = "+"
#: The disc alone's model, written.
DISC_ALONE = "none"
#: A load case whose prior is at least this is *likely*: the registered form acts there.
LIKELY = 0.5

_ACTING: dict[tuple[type, tuple[str, ...]], type] = {}


@total_ordering
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
        likely ones (the registered form's ``load_cases``). Given in any order, they are put
        in that order, and None where they are the registered effect's likely ones, so two
        terms naming the same form are equal.
    """

    effect: str
    split: bool = False
    cases: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.cases is None:
            return
        cases = tuple(lc for lc in LOAD_CASES if lc in self.cases)
        if _is_registered(self.effect) and cases == _registered(self.effect).load_cases:
            object.__setattr__(self, "cases", None)
        else:
            object.__setattr__(self, "cases", cases)

    @classmethod
    def parse(cls, text: str | Term) -> Term:
        """The term ``text`` names (:func:`parse_term`); a term is returned as is."""
        return parse_term(text)

    def __str__(self) -> str:
        return format_term(self)

    def __lt__(self, other: Term) -> bool:
        if not isinstance(other, Term):
            return NotImplemented
        return str(self) < str(other)

    @property
    def acting(self) -> tuple[str, ...]:
        """The load cases it acts in (the registered effect's likely ones where none are
        given), in :data:`~femcal.schema.LOAD_CASES` order."""
        return self.cases if self.cases is not None else _registered(self.effect).load_cases

    @property
    def beyond(self) -> tuple[str, ...]:
        """The load cases it acts in beyond the registered effect's likely ones."""
        likely = _registered(self.effect).load_cases
        return tuple(lc for lc in self.acting if lc not in likely)

    @property
    def prior(self) -> dict[str, float]:
        """The registered effect's prior per load case (cases it cannot act in left out)."""
        return dict(_registered(self.effect).load_case_prior)

    def with_cases(self, cases: Iterable[str]) -> Term:
        """This term acting in ``cases`` instead (its split kept)."""
        return replace(self, cases=tuple(cases))

    def as_split(self) -> Term:
        """This term in its split form (its load cases kept)."""
        return replace(self, split=True)

    def as_tied(self) -> Term:
        """This term in its tied form (its load cases kept)."""
        return replace(self, split=False)

    def case_cost(self) -> float:
        """What its load cases cost in criterion units against the likely ones:
        ``-2 ln [P(cases) / P(likely cases)]``, each case of the prior acting or not
        independently. 0 for the likely set; inf where a case of prior 1 is left out or a case
        of prior 0 taken in."""
        prior = self.prior
        cases = set(self.acting)
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

    def toggles(self) -> list[Term]:
        """This term with one load case whose prior lies strictly between 0 and 1 added or
        left out (at least one load case kept, two for a split form), in
        :data:`~femcal.schema.LOAD_CASES` order."""
        prior = self.prior
        cases = self.acting
        least = 2 if self.split else 1  # a split form needs two load cases
        out = []
        for lc in LOAD_CASES:
            if not 0.0 < prior.get(lc, 0.0) < 1.0:
                continue
            new = tuple(c for c in cases if c != lc) if lc in cases else (*cases, lc)
            if len(new) >= least:
                out.append(self.with_cases(new))
        return out


@dataclass(frozen=True)
class Model:
    """A model: the disc with a set of terms, at most one per registered effect.

    Attributes
    ----------
    terms : tuple of Term
        Its terms, ordered by their strings (given in any order); empty for the disc alone.

    A model is hashable and ordered by its terms' strings (the order of their strings' tuples),
    so sorting models, and iterating a model's terms, gives the same order every time.
    ``str(model)`` writes it (:data:`TERMS_SEP`-joined terms, :data:`DISC_ALONE` for the disc
    alone) and :meth:`parse` reads it.
    """

    terms: tuple[Term, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "terms", tuple(sorted(self.terms, key=str)))

    @classmethod
    def of(cls, *terms: Term) -> Model:
        """The model of ``terms``."""
        return cls(terms)

    @classmethod
    def parse(cls, text: str) -> Model:
        """The model ``text`` names: terms joined by ``+``, ``none`` (or nothing) for the
        disc alone (:func:`parse_term` for each term)."""
        if text in ("", DISC_ALONE):
            return cls()
        return cls(tuple(parse_term(part) for part in text.split(TERMS_SEP)))

    @cached_property
    def key(self) -> tuple[str, ...]:
        """Its terms' strings, in order: what models are ordered by."""
        return tuple(str(t) for t in self.terms)

    def __str__(self) -> str:
        return TERMS_SEP.join(self.key) if self.terms else DISC_ALONE

    def __lt__(self, other: Model) -> bool:
        if not isinstance(other, Model):
            return NotImplemented
        return self.key < other.key

    def __le__(self, other: Model) -> bool:
        return self == other or self < other

    def __gt__(self, other: Model) -> bool:
        return other < self

    def __ge__(self, other: Model) -> bool:
        return self == other or other < self

    def __iter__(self) -> Iterator[Term]:
        return iter(self.terms)

    def __len__(self) -> int:
        return len(self.terms)

    def __contains__(self, term: object) -> bool:
        return term in self.terms

    @property
    def effects(self) -> tuple[str, ...]:
        """The registered effects it holds, by name, in its terms' order."""
        return tuple(t.effect for t in self.terms)

    @property
    def n_split(self) -> int:
        """How many of its terms are split forms."""
        return sum(t.split for t in self.terms)

    def plus(self, term: Term) -> Model:
        """This model with ``term`` added."""
        return Model((*self.terms, term))

    def without(self, term: Term) -> Model:
        """This model with ``term`` left out."""
        return Model(tuple(t for t in self.terms if t != term))

    def replace(self, old: Term, new: Term) -> Model:
        """This model with ``new`` in place of ``old``."""
        return Model(tuple(new if t == old else t for t in self.terms))

    def case_cost(self) -> float:
        """:meth:`Term.case_cost` summed over its terms."""
        return sum(t.case_cost() for t in self.terms)


def parse_term(name: str | Term) -> Term:
    """The term a string names (see the module docstring); a :class:`Term` is returned as is.
    The effect is looked up only where load cases are given (to leave them out where they are
    its likely ones).

    Raises
    ------
    ConfigError
        A load case after ``@`` is not one of :data:`~femcal.schema.LOAD_CASES`, or none is
        given.
    """
    if isinstance(name, Term):
        return name
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
    return Term(effect, split, tuple(cases))


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


def _is_registered(effect: str) -> bool:
    from femcal.effects.base import effect_registry

    return effect in effect_registry


def cases_of(name: str | Term) -> tuple[str, ...]:
    """The load cases the term ``name`` acts in (:attr:`Term.acting`)."""
    return parse_term(name).acting


def with_cases(name: str | Term, cases: Iterable[str]) -> str:
    """The term ``name`` acting in ``cases`` instead (its split kept), written."""
    return str(parse_term(name).with_cases(cases))


def as_split(name: str | Term) -> str:
    """The term ``name`` in its split form (its load cases kept), written."""
    return str(parse_term(name).as_split())


def prior_of(name: str | Term) -> dict[str, float]:
    """The registered effect's prior per load case (:attr:`Term.prior`)."""
    return parse_term(name).prior


def case_prior_cost(name: str | Term) -> float:
    """What the term's load cases cost against the likely ones (:meth:`Term.case_cost`)."""
    return parse_term(name).case_cost()


def model_case_cost(model: Sequence[str | Term]) -> float:
    """:func:`case_prior_cost` summed over a model's terms."""
    return sum(case_prior_cost(name) for name in model)


def toggles(name: str | Term) -> list[str]:
    """The term's toggles (:meth:`Term.toggles`), written."""
    return [str(t) for t in parse_term(name).toggles()]


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
