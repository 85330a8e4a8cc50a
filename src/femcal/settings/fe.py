"""The sections only ``fe/params.yaml`` has (``fe``, ``validate``, ``adapt``, ``cohort``); the
solver adapters' keyword arguments (``fe.settings``) are declared beside each adapter
(:mod:`femcal.fe.calculix_settings`)."""

from typing import Annotated, Any, ClassVar, Literal

from pydantic import PlainValidator, ValidationError, ValidationInfo, WrapValidator, model_validator

from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.settings._format import Doc, fail, got, yaml_repr
from femcal.settings.keywords import SOLVER, SOLVERS, SPLITS, PgdKeywords, SurrogateKeywords
from femcal.settings.values import (
    MODEL_URI,
    MOMENTS,
    NAME,
    PATH,
    Float,
    Int,
    Keywords,
    ListOf,
    OptionSection,
    Section,
    light_class,
    plain,
    setting,
    with_options,
)

_ADAPT = light_class("fe.options", "AdaptOptions")  # the FE workflows' options, declared there
_BOUNDS = "a ParameterBounds.csv path or a mapping name -> [lower, upper]"
_PAIR = (ListOf(Float(), min_len=2), setting("[lower, upper]", None))


@with_options(**{n: _PAIR for n in PARAMETER_NAMES})
class Bounds(Keywords):
    """The sampling box: parameter -> [lower, upper] in physical units."""

    _unknown: ClassVar[str] = "unknown parameter"
    _describe: ClassVar[str] = "a mapping parameter -> [lower, upper]"

    @model_validator(mode="after")
    def _ordered(self) -> Any:
        for name in self.model_fields_set:
            pair = getattr(self, name)
            if len(pair) != 2 or not pair[0] < pair[1]:
                message = f"expected [lower, upper] with lower < upper, got {yaml_repr(pair)}"
                raise fail(message, name)
        return self


def _path_or_bounds(value: Any, handler: Any) -> Any:
    if isinstance(value, str) and value.strip():
        return value
    if not isinstance(value, dict) or not value:
        raise fail(f"expected {_BOUNDS}, got {got(value)}")
    return handler(value)


class Batch(Section):
    """``fe.batches[i]`` as a mapping: a Latin hypercube over the box narrowed to ``bounds``."""

    n: Int(1) = setting("configurations of the batch")
    bounds: plain(Bounds, typed=True) = setting("parameter -> [lower, upper] inside fe.bounds")


def _size_or_box(value: Any, handler: Any) -> Any:
    if isinstance(value, int) and not isinstance(value, bool) and value >= 1:
        return value
    if not isinstance(value, dict):
        raise fail(f"expected a number of configurations >= 1 or {{n, bounds}}, got {got(value)}")
    return handler(value)


@with_options(**{n: (Int(0), setting(f"configurations of the {n} split", None)) for n in SPLITS})
class Splits(Keywords):
    """``fe.splits``: configurations per split."""

    _unknown: ClassVar[str] = "unknown split"
    _describe: ClassVar[str] = "a mapping split -> configurations (large, small, test)"


#: The keyword arguments of each FE solver adapter (``fe.settings``), by solver; each
#: declared beside its adapter.
SOLVER_SETTINGS: dict[str, type[Keywords]] = {
    "calculix": light_class("fe.calculix_settings", "CalculixSettings"),
}


# ----------------------------------------------------------------------------- the sections
def _solver_settings(value: Any, handler: Any, info: ValidationInfo) -> Any:
    """``fe.settings``: checked against a built-in solver's keywords; a plugin solver's pass
    as given (its adapter's signature checks them where it is built)."""
    if info.data is None:  # a partial section's keys, each again alone: checked with it
        try:
            return handler(value)
        except ValidationError:
            return dict(value or {})
    if info.data.get("solver", SOLVERS[0]) in SOLVER_SETTINGS:
        return handler(value)
    if value is not None and not isinstance(value, dict):
        raise fail(f"expected a mapping of the solver's keyword arguments, got {got(value)}")
    return dict(value or {})


_CALCULIX = plain(SOLVER_SETTINGS["calculix"])
_SOLVER_SETTINGS = Annotated[_CALCULIX, WrapValidator(_solver_settings)]
_BATCH = Annotated[plain(Batch, typed=True), WrapValidator(_size_or_box)]
_PATH_OR_BOUNDS = Annotated[plain(Bounds, typed=True), WrapValidator(_path_or_bounds), Doc(_BOUNDS)]


@with_options
class FeSettings(OptionSection):
    """``fe``: the FE campaign (fe/params.yaml)."""

    _options: ClassVar[type] = light_class("fe.options", "CampaignOptions")

    solver: SOLVER = setting("FE solver adapter (femcal.fe registry; plugins too)")
    bounds: _PATH_OR_BOUNDS = setting("the sampling box: " + _BOUNDS)
    splits: plain(Splits, typed=True) = setting("configurations per split (large, small, test)")
    batches: ListOf(_BATCH) = setting("more Latin-hypercube batches of the large split", [])
    seed: Int(0) = setting("seed of the designs")
    load_cases: ListOf(Literal[LOAD_CASES], unique=True) = setting("load cases (all four)")
    moments: MOMENTS = setting("moments simulated, Nm")
    out_dir: PATH = setting("dataset folder in the study's layout")
    store: PATH = setting("durable store of finished jobs (JSON lines; .jsonl.gz to commit it)")
    settings: _SOLVER_SETTINGS = setting("the adapter's keywords (in every job's hash)", {})
    metrics_file: PATH | None = setting("campaign figures (DVC metrics)", None)

    @model_validator(mode="after")
    def _all_load_cases(self) -> Any:
        if sorted(self.load_cases) != sorted(LOAD_CASES):
            why = f"a dataset in the study's layout needs all four load cases {list(LOAD_CASES)}"
            raise fail(f"{why}; got {list(self.load_cases)}", "load_cases")
        return self


class IdpRange(Section):
    """A literature range of the intradiscal pressure at one force, MPa."""

    _complete: ClassVar[bool] = True

    low: Float(0) = setting("lowest value, MPa")
    mean: Float(0) = setting("mean value, MPa")
    high: Float(0) = setting("highest value, MPa")

    @model_validator(mode="after")
    def _ordered(self) -> Any:
        if not self.low <= self.mean <= self.high:
            message = f"need low <= mean <= high; got {self.low:g}, {self.mean:g}, {self.high:g}"
            raise fail(message, "mean")
        return self


class PublishedIdp(Section):
    """An intradiscal pressure published for one posture or activity (no force known), MPa."""

    _complete: ClassVar[bool] = True

    source: NAME = setting("citation: authors, year, journal, volume:pages")
    condition: NAME = setting("posture or activity, as the source names it")
    idp_mpa: Float(gt=0) = setting("the published value, MPa")
    kind: Literal["in vivo", "in vitro"] = setting("in vivo or in vitro")
    subjects: Int(1) = setting("subjects or specimens measured")
    level: NAME = setting("disc level, e.g. L4-L5")


@with_options
class AdaptSettings(OptionSection):
    """``adapt``: adaptive sampling, fine-tuning, and the challenger against the champion."""

    _complete: ClassVar[bool] = True
    _options: ClassVar[type] = _ADAPT

    model_uri: MODEL_URI = setting("the surrogate to adapt (a model folder or models:/ URI)")
    targets: PATH = setting("measurements whose calibrations steer the runs")
    train: PATH = setting("the surrogate's prepared training table")
    heldout: PATH = setting("prepared table of held-out FE configurations (the judge)")
    out_model: PATH = setting("folder of the champion's files (the winner)")
    out_dir: PATH = setting("folder of the rounds' tables")
    store: PATH = setting("campaign store of the new FE runs")
    finetune: plain(SurrogateKeywords) = setting("NeuralSurrogate settings of the fine-tuning", {})
    calibrate_options: plain(PgdKeywords) = setting("pgd options of the rounds' calibrations", {})
    seed: Int(0) = setting("seed of the candidates and calibrations", _ADAPT.seed)

    def options(self) -> dict[str, Any]:
        """The keywords of :class:`femcal.fe.options.AdaptOptions` this section sets."""
        plain_ = {k: dict(getattr(self, k)) for k in ("finetune", "calibrate_options")}
        return {**super().options(), **plain_, "seed": self.seed}


@with_options
class RefineSettings(OptionSection):
    """``validate.refine``: FE-in-the-loop refinement of the calibration before validating it."""

    _complete: ClassVar[bool] = True
    _options: ClassVar[type] = light_class("fe.options", "ValidateOptions")

    model_uri: MODEL_URI = setting("the surrogate whose Jacobian steers the steps")


class ValidateSettings(Section):
    """``validate``: FE re-simulation of the calibrated parameters and the IDP check."""

    calibration_dir: PATH = setting("calibration folder validated")
    measurements: PATH = setting("the measurements that were calibrated to")
    out_dir: PATH = setting("output folder")
    store: PATH = setting("campaign store of the FE runs")
    metrics_file: PATH | None = setting("figures (DVC metrics)", None)
    forces: ListOf(Float(gt=0), unique=True) = setting("axial compression forces, N", ())
    idp_literature: dict[Float(gt=0), IdpRange] = setting("in vitro IDP range per force, N", {})
    idp_published: ListOf(PublishedIdp) = setting("published IDP values, no force known", ())
    idp_model_uri: MODEL_URI | None = setting("the IDP head (train@idp; null: none)", None)
    refine: RefineSettings | None = setting("FE-in-the-loop refinement (null: none)", None)
    target_noise_deg: Float(0) | None = setting("the data's noise sd, deg (null: unknown)", None)
    predictive_report: PATH | None = setting("the predict stage's figures (null: none)", None)
    adapt_report: PATH | None = setting("the adapt stage's figures (null: none)", None)


def _range_of(lo: float, hi: float, unit: str) -> Any:
    """A ``[low, high]`` pair of numbers within ``[lo, hi]``, ``low <= high``."""
    what = f"a pair [low, high] of numbers in [{lo:g}, {hi:g}] {unit}".rstrip()

    def check(value: Any) -> tuple[float, float]:
        ok = isinstance(value, list | tuple) and len(value) == 2
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        if not ok or not lo <= value[0] <= value[1] <= hi:
            raise fail(f"expected {what} with low <= high, got {got(value)}")
        return (float(value[0]), float(value[1]))

    return Annotated[tuple[float, float], PlainValidator(check), Doc(what)]


_STIFFNESS = _range_of(1, 1e5, "N/mm")
_SCALE, _SHIFT = _range_of(0.1, 10, ""), _range_of(-0.3, 0.5, "")


class CohortSettings(Section):
    """``cohort``: an FE-made cohort with hidden posterior elements (femcal.fe.cohort): four
    balanced classes (the disc alone, facets, ligaments, both); disc parameters uniform in
    ``fe.bounds`` (less ``disc_margin`` at each side), the elements' properties uniform
    (stiffnesses log-uniform) in the ranges below (docs/fe-cohort.md).
    """

    _complete: ClassVar[bool] = True

    out_dir: PATH = setting("cohort folder: the study's layout (Test/) and answers.csv")
    store: PATH = setting("durable store of the cohort's FE jobs (.jsonl.gz to commit it)")
    per_class: Int(1) = setting("specimens per class (4 classes)", 26)
    seed: Int(0) = setting("seed of the draws and of the measurement noise", 0)
    noise_deg: Float(0) = setting("sd of the Gaussian noise added to the RoM, deg", 0.05)
    disc_margin: Float(0, 0.45) = setting("fraction of each range left out at both ends", 0.05)
    facet_gap_mm: _range_of(0, 3, "mm") = setting("facet clearance, mm", (0.25, 1.0))
    facet_stiffness_n_per_mm: _STIFFNESS = setting("facet stiffness (log), N/mm", (25.0, 100.0))
    ligament_stiffness_scale: _SCALE = setting("factor on ligament stiffness (log)", (0.5, 2.0))
    ligament_slack_shift: _SHIFT = setting("added to each slack strain (clipped)", (-0.15, 0.05))
