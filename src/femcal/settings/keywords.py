"""The registries' names and the keyword arguments of the estimators and the calibrators
(``fixed``, ``options``), static so that validating imports nothing heavy
(``tests/test_settings.py`` checks them against the signatures and registries); their Optuna
search spaces are :func:`femcal.training.search_space.space_of`'s.
"""

import sys
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field, PlainValidator, model_validator

from femcal.settings._format import Doc, fail, got, one_of
from femcal.settings.values import (
    MODEL_URI,
    Bool,
    Float,
    Int,
    Keywords,
    ListOf,
    OptionSection,
    Section,
    keyword,
    light_class,
    plain,
    with_options,
)

# ------------------------------------------------------------------ registries' names
#: Hidden activations of the networks (femcal.surrogates.nn.ACTIVATIONS).
ACTIVATIONS: tuple[str, ...] = ("silu", "gelu", "relu", "tanh", "softplus")
#: What ``femcal calibrate --plots`` writes (femcal.calibration.report.plot_mode).
PLOT_CHOICES: tuple[str, ...] = ("all", "summary", "none")
#: The study's baseline models (femcal.surrogates baseline registry); plugins add more.
BASELINE_MODELS: tuple[str, ...] = (
    *("linear", "poly2", "poly3", "poly4", "poly5", "svr", "random_forest"),
    *("gaussian_process", "lightgbm"),
)
#: Built-in calibrators (femcal.calibration registry); installed plugins add more.
CALIBRATORS: tuple[str, ...] = ("pgd", "pgd-study", "ga", "inverse")
#: Built-in physical effects (femcal.effects.builtin); plugins and effect files add more.
BUILTIN_EFFECTS: tuple[str, ...] = ("facet_contact", "ligament_tension", "neutral_zone")
#: Prepared splits (femcal.prepare.SPLITS) and FE campaign splits (femcal.fe.campaign).
SPLITS: tuple[str, ...] = ("large", "small", "test")
#: Built-in FE solver adapters (femcal.fe registry); plugins add more.
SOLVERS: tuple[str, ...] = ("calculix",)
#: Mesh presets of the disc geometry (femcal.fe.geometry.MESH_PRESETS).
MESH_PRESETS: tuple[str, ...] = ("coarse", "default", "fine")


class Registered(tuple):
    """An open registry's built-in names (what help texts list) that also contains its plugins:
    the entry points of ``group`` and, once ``<package>.base`` is loaded, its
    ``<kind>_registry``'s names. ``how`` says how to add one (``what`` is registered, ``page``
    names the how-to)."""

    def __new__(cls, names: tuple, kind: str, package: str, what: str, page: str) -> "Registered":
        self = super().__new__(cls, names)
        self.group, self.registry = f"femcal.{kind}s", f"{package}.base:{kind}_registry"
        self.how = (
            f'decorate {what} with @register_{kind}("name") ({package}) and name it in the entry-'
            f"point group {self.group} of your package (docs: How-to > Write a {page} plugin)"
        )
        return self

    def plugins(self) -> tuple[str, ...]:
        """The plugins' names beyond the built-ins, sorted; imports and loads nothing."""
        from importlib.metadata import entry_points

        names = {ep.name for ep in entry_points(group=self.group)}
        module, attribute = self.registry.split(":")
        if module in sys.modules:
            names.update(n for n, _ in getattr(sys.modules[module], attribute).items(load=False))
        return tuple(sorted(names - set(self)))

    def __contains__(self, name: object) -> bool:
        return tuple.__contains__(self, name) or name in self.plugins()

    def choice(self) -> Any:
        """A setting naming one of them (a plugin's too, checked when validated)."""

        def check(value: Any) -> str:
            names = (*self, *self.plugins())
            if isinstance(value, str) and value in names:
                return value
            message = one_of(value, names)
            raise fail(f"{message}{' T' if '?' in message else '; t'}o add one, {self.how}")

        words = f"one of {', '.join(map(repr, self))}, or a plugin's name (group {self.group})"
        return Annotated[str, PlainValidator(check), Doc(words)]


_PAGE = "solver, surrogate or baseline"
CALIBRATOR_NAMES = Registered(
    CALIBRATORS, "calibrator", "femcal.calibration", "a calibrator function", "calibrator"
)
SOLVER_NAMES = Registered(SOLVERS, "solver", "femcal.fe", "a solver adapter class", _PAGE)
_BASELINE = ("baseline", "femcal.surrogates", "a baseline class", _PAGE)
BASELINE_NAMES = Registered(BASELINE_MODELS, *_BASELINE)
METHOD, SOLVER, BASELINE = (n.choice() for n in (CALIBRATOR_NAMES, SOLVER_NAMES, BASELINE_NAMES))


# ------------------------------------------------------------------ network hyper-parameters
class _Network(Keywords):
    """The architecture both networks share: hidden widths (or width and depth), activation."""

    hidden: ListOf(Int(1), min_len=1) = keyword("hidden-layer widths (or give width and depth)")
    width: Int(1) = keyword("width of every hidden layer (with depth: hidden = [width] * depth)")
    depth: Int(1) = keyword("number of hidden layers (with width)")
    activation: Literal[ACTIVATIONS] = keyword("hidden activation")
    weight_decay: Float(0) = keyword("AdamW weight decay")
    dropout: Float(0, lt=1) = keyword("dropout after each hidden activation")
    patience: Int(0) = keyword("early stopping: epochs without a better validation MAE")

    @model_validator(mode="after")
    def _hidden_or_width(self) -> Any:
        if "hidden" in self.model_fields_set and {"width", "depth"} & self.model_fields_set:
            why = "give either hidden or width and depth, not both (width/depth win)"
            raise fail(why, "hidden")
        return self


class SurrogateKeywords(_Network):
    """NeuralSurrogate keywords settable in ``train.<split>.fixed`` and ``search_space``."""

    _owner: ClassVar[str] = "NeuralSurrogate"
    _reasons: ClassVar[dict[str, str]] = {
        "n_members": "the ensemble size is train.<split>.final_members (trials train one member)",
        "seed": "set train.seed, or train.<split>.seed for one split",
        "space": "the parameter space comes from the prepared data",
        "warm_start": "training starts anew; the FE pipeline's adaptive sampling fine-tunes",
    }

    log_target: Bool = keyword("model log RoM (RoM must then be > 0)")
    loss: Literal["l1", "l2"] = keyword("training loss on the scaled (log-)RoM")
    learning_rate: Float(gt=0) = keyword("peak learning rate (AdamW, one-cycle)")
    batch_size: Int(1) = keyword("configurations per optimisation step")
    max_epochs: Int(1) = keyword("epochs per ensemble member")
    val_fraction: Float(0, lt=1) = keyword("validation fraction without a validation set")
    log_params: Bool = keyword("parameters with positive bounds enter in log scale")
    lr_schedule: Literal["onecycle", "cosine", "constant"] = keyword("learning-rate schedule")
    moment_degree: Int(0, 8) | None = keyword("degree of each curve's polynomial (null: 3)")


class InverseKeywords(_Network):
    """InverseModel keywords settable in ``inverse.fixed`` and ``search_space``."""

    _owner: ClassVar[str] = "InverseModel"
    _reasons: ClassVar[dict[str, str]] = {
        "seed": "set inverse.seed",
        "space": "the parameter space comes from the surrogate",
    }

    learning_rate: Float(gt=0) = keyword("initial AdamW learning rate")
    batch_size: Int(1) = keyword("samples per step")
    max_epochs: Int(1) = keyword("upper bound on epochs")
    min_delta: Float(0) = keyword("smallest validation-MAE improvement that counts")
    scheduler_patience: Int(0) = keyword("ReduceLROnPlateau patience in epochs")
    scheduler_factor: Float(gt=0, lt=1) = keyword("ReduceLROnPlateau factor")
    log_input: Bool = keyword("standardise log RoM rather than RoM")
    val_fraction: Float(0, lt=1) = keyword("fraction of samples held out for validation")


# ------------------------------------------------------------------ calibrator options
_RNG = {"rng": "set calibrate.seed"}  # every calibrator takes its seed from calibrate.seed


def _calibrator(method: str, **reasons: str) -> type:
    """The keyword options of the calibrator ``method``, declared by its options dataclass in
    ``femcal.calibration.<method>_options``; ``reasons``: keyword not settable there -> why."""
    name, module = method.title().replace("-", ""), method.replace("-", "_")  # PgdStudy, pgd_study
    body = {
        "__doc__": f"The {method} calibrator's options (``calibrate.options.{method}``).",
        "__module__": __name__,
        "_owner": f"{method} calibrator",
        "_options": light_class(f"calibration.{module}_options", f"{name}Options"),
        "_reasons": {**reasons, **_RNG},
    }
    return with_options(type(f"{name}Keywords", (OptionSection, Keywords), body))


_BANK = "set calibrate.start_bank (a prepared table whose configurations are the starts)"
PgdKeywords = _calibrator("pgd", start_bank=_BANK)
PgdStudyKeywords, GaKeywords = _calibrator("pgd-study"), _calibrator("ga")


class InverseCalibratorKeywords(Keywords):
    """The inverse calibrator's options (``calibrate.options.inverse``)."""

    _owner: ClassVar[str] = "inverse calibrator"
    _reasons: ClassVar[dict] = {"model": "give model_uri (a registered inverse model)", **_RNG}

    model_uri: MODEL_URI = keyword("the registered inverse model (train-inverse)")


#: The options model of each calibrator, by method.
CALIBRATOR_OPTIONS: dict[str, type[Keywords]] = dict(
    zip(CALIBRATORS, (PgdKeywords, PgdStudyKeywords, GaKeywords, InverseCalibratorKeywords))
)


def _method(method: str, model: type) -> tuple:
    return (plain(model), Field(None, alias=method, description=model.__doc__))


@with_options(**{m.replace("-", "_"): _method(m, model) for m, model in CALIBRATOR_OPTIONS.items()})
class CalibratorOptions(Section):
    """``calibrate.options``: each calibrator's keyword options, by method."""

    _unknown: ClassVar[str] = "unknown calibration method"
    _describe: ClassVar[str] = "calibrator options per method"

    @model_validator(mode="before")
    @classmethod
    def _plugins_as_given(cls, value: Any) -> Any:
        """A plugin calibrator's options pass as given; its signature checks them where it is
        called (:func:`femcal.stages.calibrate.plugin_options`)."""
        if not isinstance(value, dict) or set(value) <= set(CALIBRATOR_OPTIONS):
            return value
        found = CALIBRATOR_NAMES.plugins()
        plugins = [k for k in value if k not in CALIBRATOR_OPTIONS and k in found]
        for name in plugins:
            if value[name] is not None and not isinstance(value[name], dict):
                what = f"a mapping of the {name} calibrator's keyword options"
                raise fail(f"expected {what}, got {got(value[name])}", name)
        return {k: v for k, v in value.items() if k not in plugins}
