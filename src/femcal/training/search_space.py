"""The Optuna search space as params.yaml writes it (``train.<split>.search_space``,
``inverse.search_space``): keyword -> an entry ``{type: float|int|categorical, ...}`` of the
form :func:`femcal.training.study.suggest` reads, whose bounds and choices must be values of
the keyword (:func:`space_of`). This module imports nothing heavy: the settings read it with
:func:`~femcal.settings.values.light_class`.
"""

from functools import partial
from typing import Annotated, Any, ClassVar, Literal, get_origin

from pydantic import (
    AfterValidator,
    PlainValidator,
    TypeAdapter,
    ValidationError,
    create_model,
    model_validator,
)

from femcal.settings._format import describe, fail, got, members, one_of, text, unwrap
from femcal.settings.values import Bool, Float, Keywords, ListOf, Section, keyword, plain, setting


class FloatEntry(Section):
    """``{type: float, low, high, log}``: a number between low and high."""

    _complete: ClassVar[bool] = True

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

    type: Literal["int"] = setting("the Optuna distribution")

    @model_validator(mode="after")
    def _integers(self) -> Any:
        for key in ("low", "high"):
            if float(getattr(self, key)) != int(getattr(self, key)):
                raise fail(f"an int entry needs integer bounds; got {getattr(self, key):g}", key)
        return self


for _entry, _kind in ((FloatEntry, "float"), (IntEntry, "int")):
    _entry._missing = f"missing: a {_kind} entry needs low and high"
    _entry._refused = {"choices": f"choices are for type categorical; a {_kind} has low and high"}


def _scalar(value: Any) -> Any:
    if value is None or isinstance(value, list | dict):
        raise fail(f"expected a number, string or boolean, got {got(value)}")
    return value


_CHOICES = ListOf(Annotated[Any, AfterValidator(_scalar)], min_len=1, unique=True)


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
    choices: _CHOICES = setting("the values to choose from")


_ENTRIES = {"float": FloatEntry, "int": IntEntry, "categorical": CategoricalEntry}
_KINDS = {int: ("int", "categorical"), float: ("float", "int", "categorical")}


def _entry(name: str, annotation: Any, value: Any) -> Section:
    """A search-space entry over the keyword ``name`` (``annotation``): the model its ``type``
    names; its bounds and choices, as written, must be values of the keyword."""
    if not isinstance(value, dict):
        raise fail(f"expected a mapping {{type: float|int|categorical, ...}}, got {got(value)}")
    if not isinstance(value.get("type"), str) or value["type"] not in _ENTRIES:
        raise fail(one_of(value.get("type"), _ENTRIES), "type")  # a list or mapping too
    entry = _ENTRIES[value["type"]].model_validate(value)
    tp = unwrap((members(unwrap(annotation)[0]) or [annotation])[0])[0]
    kinds = _KINDS.get(tp) or (("categorical",) if tp is bool or get_origin(tp) is Literal else ())
    if value["type"] not in kinds:
        allowed = " or ".join(kinds) or "none (it cannot be searched)"
        fix = "; search width and depth instead" if name == "hidden" else ""
        why = f"{name} is {describe(annotation)}, so type {value['type']} does not fit"
        raise fail(f"{why}; use {allowed}{fix}", "type")
    values = {("choices", i): c for i, c in enumerate(value.get("choices") or ())}
    values.update({(k,): value[k] for k in ("low", "high") if k in value})
    for where, item in values.items():
        try:  # as written: 16 for an int, 0.001 for a float
            TypeAdapter(annotation).validate_python(item)
        except ValidationError as exc:
            raise fail(text(exc.errors()[0]), where) from None
    return entry


def space_of(keywords: type[Keywords]) -> Any:
    """The search space over ``keywords``: keyword -> entry, kept as plain data."""
    entry = lambda k, f: Annotated[Any, PlainValidator(partial(_entry, k, f.rebuild_annotation()))]  # noqa: E731
    fields = {k: (entry(k, f), keyword(f.description)) for k, f in keywords.model_fields.items()}
    doc = f"An Optuna search space over the {keywords._owner} keywords."
    model = create_model(f"{keywords.__name__}Space", __base__=Keywords, __doc__=doc, **fields)
    model._keywords, model._owner, model._reasons = keywords, keywords._owner, keywords._reasons
    model._describe = "a mapping hyper-parameter -> {type: float|int|categorical, low, high, ...}"
    return plain(model)
