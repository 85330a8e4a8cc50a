"""The sections only ``fe/params.yaml`` has (``fe``, ``validate``, ``adapt``, ``cohort``), the
CalculiX adapter's keyword arguments (``fe.settings``) and the posterior elements, whose
parameters, units, ranges and defaults are declared here once. Axes as the disc model's (x
lateral, y anterior, z cranial; lower endplate at z = 0, disc centre at x = y = 0); sources and
calibration: docs/fe-posterior-elements.md.
"""

from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    ConfigDict,
    PlainValidator,
    TypeAdapter,
    ValidationError,
    ValidationInfo,
    WrapValidator,
    model_validator,
)
from pydantic.dataclasses import dataclass

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.settings._format import Doc, fail, got, problems, reword, yaml_repr
from femcal.settings.keywords import (
    SOLVER,
    SOLVERS,
    SPLITS,
    GeometryKeywords,
    PgdKeywords,
    SurrogateKeywords,
)
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
    keyword,
    light_class,
    plain,
    setting,
    with_options,
)

_ADAPT = light_class("fe.options", "AdaptOptions")  # the FE workflows' options, declared there


def _element(cls: type) -> type:
    """A posterior element's settings: a frozen pydantic dataclass, every key known."""
    cls._reword = model_validator(mode="wrap")(classmethod(reword))
    return dataclass(frozen=True, config=ConfigDict(extra="forbid"))(cls)


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
        what = "a ParameterBounds.csv path or a mapping name -> [lower, upper]"
        raise fail(f"expected {what}, got {got(value)}")
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


# ------------------------------------------------------------------ posterior elements
@_element
class FacetSettings:
    """``fe.settings.posterior.facets``: two facet joints, each a unilateral gap element: a
    CalculiX ``GAPUNI`` between a node tied to the upper endplate and a fixed one at
    ``(+-lateral_mm, -posterior_mm, height_mm)``, closed once the upper node has moved ``gap_mm``
    along the contact normal (``axial_angle_deg`` from lateral, tilted ``inclination_deg`` down).
    """

    _complete: ClassVar[bool] = True

    gap_mm: Float(0, 3) = setting("facet joint clearance, mm", 0.5)
    stiffness_n_per_mm: Float(1, 1e5) = setting("contact stiffness of a closed facet, N/mm", 50.0)
    lateral_mm: Float(5, 40) = setting("distance from the mid-sagittal plane, mm", 16.0)
    posterior_mm: Float(18, 60) = setting("distance behind the disc centre, mm", 30.0)
    height_mm: Float(-20, 30) = setting("centre height above the lower endplate, mm", 5.5)
    axial_angle_deg: Float(0, 90) = setting("joint plane to sagittal plane (top view), deg", 45.0)
    inclination_deg: Float(0, 80) = setting("downward tilt of the contact normal, deg", 30.0)


@_element
class LigamentSettings:
    """One ligament: a tension-only nonlinear spring (``SPRINGA``), one per side if lateral,
    vertical at ``(+-lateral_mm, -posterior_mm, height_mm)``, rest length ``length_mm``: no
    force below the elongation ``slack_strain * length_mm``, a quadratic toe over the next
    ``toe_strain * length_mm`` up to the slope ``stiffness_n_per_mm``, then that slope.
    """

    _complete: ClassVar[bool] = True

    stiffness_n_per_mm: Float(0.1, 1000) = setting("linear-region stiffness (each side), N/mm")
    toe_strain: Float(0, 1) = setting("strain span of the toe region")
    slack_strain: Float(-0.3, 0.5) = setting("strain at which force starts (< 0: pre-strained)")
    lateral_mm: Float(0, 60) = setting("distance from the mid-sagittal plane (0: midline), mm")
    posterior_mm: Float(0, 100) = setting("distance behind the disc centre, mm")
    height_mm: Float(-30, 40) = setting("centre above the lower endplate, mm")
    length_mm: Float(0.5, 60) = setting("rest length (upper to lower attachment), mm")


#: Default properties and attachment of each ligament (the fields of :class:`LigamentSettings`):
#: stiffness from Pintar et al. 1992 and Guo et al. 2021, rest lengths from Naserkhaki et al.
#: 2018, slack strains calibrated to the segment-to-disc RoM ratios (docs/fe-posterior-elements.md).
LIGAMENT_DEFAULTS: dict[str, dict[str, float]] = {
    name: dict(zip(LigamentSettings.__pydantic_fields__, row, strict=True))
    for name, *row in (
        # name, stiffness_n_per_mm, toe_strain, slack_strain, lateral, posterior, height, length
        ("supraspinous", 23.7, 0.20, 0.45, 0.0, 60.0, 5.5, 27.49),
        ("interspinous", 11.6, 0.139, 0.45, 0.0, 45.0, 5.5, 8.85),
        ("flavum", 27.2, 0.059, 0.45, 0.0, 35.0, 5.5, 15.89),
        ("capsular", 33.9, 0.25, 0.45, 18.0, 30.0, 5.5, 10.0),
        ("intertransverse", 10.7, 0.182, 0.0, 35.0, 22.0, 5.5, 18.69),
    )
}
#: The ligaments the model knows.
LIGAMENTS: tuple[str, ...] = tuple(LIGAMENT_DEFAULTS)
_LIGAMENTS = f"tension-only ligaments ({', '.join(LIGAMENTS)}): a list, or name -> overrides"


@with_options(**{n: (LigamentSettings, setting(f"the {n} ligament", None)) for n in LIGAMENTS})
class Ligaments(Keywords):
    """``fe.settings.posterior.ligaments``: ligament -> its settings (the defaults overridden)."""

    _unknown: ClassVar[str] = "unknown ligament"
    _describe: ClassVar[str] = "a list of ligament names or a mapping name -> settings"

    @model_validator(mode="before")
    @classmethod
    def _with_defaults(cls, value: Any) -> Any:
        value = {name: {} for name in value} if isinstance(value, list | tuple) else value
        if not isinstance(value, dict):
            return value
        for name, overrides in value.items():
            if overrides is not None and not isinstance(overrides, dict):
                raise fail(f"expected a mapping of ligament settings, got {got(overrides)}", name)
        defaults = LIGAMENT_DEFAULTS
        return {k: {**defaults[k], **(v or {})} if k in defaults else v for k, v in value.items()}


@_element
class PosteriorSettings:
    """``fe.settings.posterior``: the posterior elements joined to the disc (all optional;
    null ``facets`` and no ``ligaments``: the disc alone)."""

    _complete: ClassVar[bool] = True
    _describe: ClassVar[str] = "a mapping (facets, ligaments) or null"

    facets: FacetSettings | None = setting("facet joints (GAPUNI contact; null: none)", None)
    ligaments: plain(Ligaments, typed=True) = setting(_LIGAMENTS, {})

    @model_validator(mode="before")
    @classmethod
    def _a_mapping(cls, value: Any) -> Any:
        return {} if value is None else value  # ArgsKwargs: PosteriorSettings(facets=...)

    @property
    def active(self) -> bool:
        """Whether any posterior element is present."""
        return self.facets is not None or bool(self.ligaments)


class CalculixSettings(Keywords):
    """The CalculiX adapter's keyword arguments (``fe.settings``; part of every job's hash)."""

    _owner: ClassVar[str] = "CalculixDisc"

    geometry: plain(GeometryKeywords) = keyword("a mesh preset (coarse, default, fine) or fields")
    kappa: Literal["scale", "ignore"] = keyword("how the fibre dispersion Kappa enters")
    executable: NAME = keyword("the CalculiX executable")
    initial_increment: Float(gt=0, le=1) = keyword("first load increment")
    max_attempts: Int(1) = keyword("attempts per job (retries of a fibre-routine abort)")
    timeout_s: Float(gt=0) | None = keyword("CPU seconds per attempt (null = none)")
    max_increments: Int(1) = keyword("load increments at most")
    retry_factor: Float(gt=0, le=1) = keyword("increment factor of a retry")
    nucleus_d1: Float(gt=0) = keyword("compressibility of the nucleus")
    annulus_d1: Float(gt=0) = keyword("compressibility of the annulus")
    posterior: plain(PosteriorSettings) | None = keyword("facets, ligaments (none: the disc alone)")


#: The keyword arguments of each FE solver adapter (``fe.settings``), by solver.
SOLVER_SETTINGS: dict[str, type[Keywords]] = {"calculix": CalculixSettings}


def posterior_settings(
    value: PosteriorSettings | dict | None, where: str = "fe/params.yaml"
) -> PosteriorSettings:
    """Validated posterior elements from ``fe.settings.posterior`` (a mapping, an instance, or
    None: the disc alone) of the file ``where``; ConfigError: each problem (the field, what was
    given and what is allowed)."""
    if isinstance(value, PosteriorSettings):
        return value
    try:
        return TypeAdapter(PosteriorSettings).validate_python(value)
    except ValidationError as exc:
        found = problems(exc, prefix=("fe", "settings", "posterior"))
        listing = "\n".join(f"  - {message}" for _, message in found)
        raise ConfigError(
            f"{where}: invalid posterior elements:\n{listing}\nFix the values in {where} "
            "(docs/fe-posterior-elements.md lists every field, its unit and range)."
        ) from None


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


_BOUNDS = "a ParameterBounds.csv path or a mapping name -> [lower, upper]"
_SOLVER_SETTINGS = Annotated[plain(CalculixSettings), WrapValidator(_solver_settings)]
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
        plain_ = {
            "finetune": dict(self.finetune),
            "calibrate_options": dict(self.calibrate_options),
        }
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
