"""Optuna search spaces: ``search_space`` entries over the keywords of an estimator.

An entry is one of three variants, told apart by its ``type`` (the form
:func:`femcal.training.study.suggest` reads): ``{type: float, low, high, log}``,
``{type: int, low, high, log}`` or ``{type: categorical, choices}``. Its bounds or choices
must be valid values of the hyper-parameter itself.
"""

from types import UnionType
from typing import Annotated, Any, ClassVar, Literal, Union, get_args, get_origin

from pydantic import (
    AfterValidator,
    Field,
    TypeAdapter,
    ValidationError,
    create_model,
    model_validator,
)

from femcal.settings._format import Index, describe, fail, got, unwrap
from femcal.settings.values import Bool, Float, Keywords, ListOf, Section, plain, setting


class FloatEntry(Section):
    """``{type: float, low, high, log}``: a number between low and high."""

    _complete: ClassVar[bool] = True
    _missing: ClassVar[str] = "missing: a float entry needs low and high"
    _refused: ClassVar[dict[str, str]] = {
        "choices": "choices are for type categorical; a float has low and high"
    }

    type: Literal["float"] = setting("the Optuna distribution")
    low: Float() = setting("lower bound")
    high: Float() = setting("upper bound")
    log: Bool = setting("sample in log scale (needs low > 0)", False)

    @model_validator(mode="after")
    def _ordered(self) -> Any:
        if not self.low < self.high:
            raise fail(f"high must be > low; got low {self.low:g}, high {self.high:g}", "high")
        if self.log and self.low <= 0:
            raise fail(f"a log-scale entry needs low > 0; got {self.low:g}", "low")
        return self


class IntEntry(FloatEntry):
    """``{type: int, low, high, log}``: an integer between low and high."""

    _missing: ClassVar[str] = "missing: a int entry needs low and high"
    _refused: ClassVar[dict[str, str]] = {
        "choices": "choices are for type categorical; a int has low and high"
    }

    type: Literal["int"] = setting("the Optuna distribution")

    @model_validator(mode="after")
    def _integers(self) -> Any:
        for key in ("low", "high"):
            if float(getattr(self, key)) != int(getattr(self, key)):
                raise fail(f"an int entry needs integer bounds; got {getattr(self, key):g}", key)
        return self


def _scalar(value: Any) -> Any:
    if value is None or isinstance(value, list | dict):
        raise fail(f"expected a number, string or boolean, got {got(value)}")
    return value


class CategoricalEntry(Section):
    """``{type: categorical, choices}``: one of the choices."""

    _complete: ClassVar[bool] = True
    _missing: ClassVar[str] = "missing: a categorical entry needs choices: [a, b, ...]"
    _refused: ClassVar[dict[str, str]] = {
        "low": "low is for type float or int; a categorical has choices only",
        "high": "high is for type float or int; a categorical has choices only",
        "log": "log is for type float or int",
    }

    type: Literal["categorical"] = setting("the Optuna distribution")
    choices: ListOf(Annotated[Any, AfterValidator(_scalar)], min_len=1, unique=True) = setting(
        "the values to choose from"
    )


#: One search-space entry, by its ``type``.
SearchEntry = Annotated[FloatEntry | IntEntry | CategoricalEntry, Field(discriminator="type")]


def _kinds(annotation: Any) -> tuple[str, ...]:
    tp = unwrap(annotation)[0]
    if get_origin(tp) in (Union, UnionType):
        tp = next(unwrap(a)[0] for a in get_args(tp) if a is not type(None))
    if tp is int:
        return ("int", "categorical")
    if tp is float:
        return ("float", "int", "categorical")
    return ("categorical",) if tp is bool or get_origin(tp) is Literal else ()


class _Space(Keywords):
    _keywords: ClassVar[type[Keywords]]

    @model_validator(mode="wrap")
    @classmethod
    def _values_of_the_keyword(cls, data: Any, handler: Any) -> Any:
        result = handler(data)
        for name, spec in data.items():
            field = cls._keywords.model_fields[name]
            annotation = (
                Annotated[(field.annotation, *field.metadata)]
                if field.metadata
                else field.annotation
            )
            kinds = _kinds(annotation)
            if spec["type"] not in kinds:
                allowed = " or ".join(kinds) or "none (it cannot be searched)"
                fix = "; search width and depth instead" if name == "hidden" else ""
                raise fail(
                    f"{name} is {describe(annotation)}, so type {spec['type']} does not fit; "
                    f"use {allowed}{fix}",
                    (name, "type"),
                )
            values = {("choices", Index(i)): c for i, c in enumerate(spec.get("choices") or ())}
            values.update({(k,): spec[k] for k in ("low", "high") if k in spec})
            for where, value in values.items():  # as written: 16 for an int, 0.001 for a float
                try:
                    TypeAdapter(annotation).validate_python(value)
                except ValidationError:
                    message = f"expected {describe(annotation)}, got {got(value)}"
                    raise fail(message, (name, *where)) from None
        return result


def space_of(keywords: type[Keywords]) -> Any:
    """The search space over ``keywords``: keyword -> entry, kept as plain data."""
    fields = {
        name: (SearchEntry, Field(None, description=field.description))
        for name, field in keywords.model_fields.items()
    }
    model = create_model(f"{keywords.__name__}Space", __base__=_Space, **fields)
    model.__doc__ = f"An Optuna search space over the {keywords._owner} keywords."
    for attr in ("_keywords", "_unknown", "_refused"):
        setattr(model, attr, keywords if attr == "_keywords" else getattr(keywords, attr))
    model._describe = (
        "a mapping hyper-parameter -> {type: float|int|categorical, low, high, log, choices}"
    )
    return plain(model)
