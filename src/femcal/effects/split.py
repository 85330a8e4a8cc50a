"""Per-load-case parameters: an effect whose declared parameters differ in each load case.

An :class:`~femcal.effects.base.EffectParameter` with ``per_load_case=True`` *may* differ per
load case. The effect as registered ties it (one value for all of its load cases); its split
form, named ``<effect>:split`` (e.g. ``facet_contact:split``), gives each of its load cases a
copy named ``<parameter>[<load case>]`` (``facet_gap_deg[Extension]``,
``facet_gap_deg[AxialRotation]``), and evaluates the effect's own law in each load case with
that case's values. So a user effect gets the split by declaring which parameters may split;
its law is written once, for one load case at a time as for the tied form.

Anatomy is why: facets engage in extension by compression of the articular surfaces and in
axial rotation by impingement of the contralateral facet, at other rotations and with other
stiffness; different ligaments tighten in flexion and in lateral bending.

The diagnosis decides between the tied and the split form with its criterion, which counts a
split's extra parameters by their effective number (:mod:`femcal.diagnose`);
``femcal calibrate --effects facet_contact:split`` calibrates the split form.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from femcal.effects.base import Effect, EffectParameter
from femcal.effects.terms import Term, as_split, parse_term
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

__all__ = [
    "base_name",
    "case_parameter",
    "has_split_form",
    "is_split",
    "is_split_effect",
    "split_effect",
    "tied_parameter",
]

_SPLIT: dict[type[Effect], type[Effect]] = {}


def is_split(name: str | Term) -> bool:
    """Whether an effect term names a split form (:attr:`femcal.effects.terms.Term.split`)."""
    return parse_term(name).split


def base_name(name: str | Term) -> str:
    """The registered effect a term refers to: ``facet_contact:split`` and
    ``facet_contact@Extension,LateralBending`` -> ``facet_contact``
    (:attr:`femcal.effects.terms.Term.effect`)."""
    return parse_term(name).effect


def is_split_effect(effect: Effect) -> bool:
    """Whether an effect (an instance of a model's) is a split form (:func:`split_effect`)."""
    return isinstance(effect, _SplitEffect)


def has_split_form(name: str | Term) -> bool:
    """Whether a registered, tied effect has a split form (a parameter that may differ per
    load case, and two load cases or more)."""
    from femcal.effects.base import get_effect

    cls = get_effect(name)
    return (
        not is_split(name)
        and len(cls.load_cases) > 1
        and any(q.per_load_case for q in cls.parameters)
    )


def case_parameter(name: str, load_case: str) -> str:
    """The name of a split parameter's copy in one load case: ``gap[Extension]``."""
    return f"{name}[{load_case}]"


def tied_parameter(name: str) -> str:
    """The parameter a per-load-case copy is of: ``gap[Extension]`` -> ``gap`` (a tied
    parameter's name is returned as is)."""
    return name.split("[", 1)[0]


def split_effect(cls: type[Effect]) -> type[Effect]:
    """The split form of an effect class (built once per class).

    Raises
    ------
    ConfigError
        The effect declares no parameter that may differ per load case, or acts in one load
        case only (there is nothing to split).
    """
    if cls in _SPLIT:
        return _SPLIT[cls]
    splittable = [q.name for q in cls.parameters if q.per_load_case]
    if not splittable or len(cls.load_cases) < 2:
        raise ConfigError(
            f"Effect '{cls.name}' has no split form: "
            + (
                f"it acts in one load case only ({cls.load_cases[0]})"
                if splittable
                else "none of its parameters may differ per load case"
            )
            + f". Use '{cls.name}' (tied), or declare EffectParameter(..., per_load_case=True) "
            "on the parameters that may differ per load case."
        )
    params: list[EffectParameter] = []
    for q in cls.parameters:
        if q.per_load_case:
            params += [
                EffectParameter(
                    case_parameter(q.name, lc), q.unit, q.lower, q.upper, q.log, q.start, q.grid
                )
                for lc in cls.load_cases
            ]
        else:
            params.append(q)
    split = type(
        f"{cls.__name__}Split",
        (_SplitEffect,),
        {
            "name": as_split(cls.name),
            "kind": cls.kind,
            "load_cases": cls.load_cases,
            "load_case_prior": dict(cls.load_case_prior),
            "parameters": tuple(params),
            "tied": cls,
            "__doc__": f"{cls.name} with {', '.join(splittable)} per load case.",
        },
    )
    _SPLIT[cls] = split
    return split


class _SplitEffect(Effect):
    """An effect's split form (:func:`split_effect`): the tied effect's law, evaluated in each
    load case with that case's parameter values."""

    #: The effect this is the split form of.
    tied: type[Effect]

    def __init__(self) -> None:
        self._law = self.tied()

    def _case_values(self, p: Mapping[str, torch.Tensor], load_case: str) -> dict:
        return {
            q.name: p[case_parameter(q.name, load_case) if q.per_load_case else q.name]
            for q in self.tied.parameters
        }

    def _per_case(self, x: torch.Tensor, p, cases: Sequence[int] | None, law) -> torch.Tensor:
        cases = list(range(len(LOAD_CASES))) if cases is None else list(cases)
        parts = []
        for j, c in enumerate(cases):
            xj = x[:, j : j + 1]
            lc = LOAD_CASES[c]
            if lc in self.load_cases:
                parts.append(law(xj, self._case_values(p, lc)))
            else:
                parts.append(torch.zeros_like(xj))
        return torch.cat(parts, dim=1)

    def moment_at(self, rotation_deg, p, cases=None):
        return self._per_case(rotation_deg, p, cases, self._law.moment)

    def rotation_at(self, moment_nm, p, cases=None):
        return self._per_case(moment_nm, p, cases, self._law.rotation)

    def moment(self, rotation_deg, p):
        return self.moment_at(rotation_deg, p)

    def rotation(self, moment_nm, p):
        return self.rotation_at(moment_nm, p)

    @classmethod
    def expand_tied(cls, values: torch.Tensor) -> torch.Tensor:
        """The tied effect's unit coordinates (g, p_tied) copied into each load case
        (g, p_split): the split form starts where the tied one is."""
        cols = []
        for j, q in enumerate(cls.tied.parameters):
            cols += [j] * (len(cls.load_cases) if q.per_load_case else 1)
        return values[:, cols]
