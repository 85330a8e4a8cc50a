"""The sections only ``fe/params.yaml`` has: the FE campaign (``fe``) and ``validate``.

The adapter's keyword arguments (``fe.settings``) depend on ``fe.solver``; they are checked
against :data:`~femcal.settings.keywords.SOLVER_SETTINGS` once both are known (see
:mod:`femcal.settings.params`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.settings._checks import Choice, Float, FnCheck, Int, KeyChoice, ListOf
from femcal.settings._messages import BAD, Context, Invalid, got, unknown_message, yaml_repr
from femcal.settings._validate import MapOf, Section, optional, setting
from femcal.settings.keywords import (
    CALIBRATOR_OPTIONS,
    SOLVER_SETTINGS,
    SOLVERS,
    SPLITS,
    SURROGATE_FIXED,
)
from femcal.settings.values import DASK_ADDRESS, MODEL_URI, MOMENTS, NAME, PATH


def _bounds(value: Any, path: tuple, ctx: Context) -> Any:
    if isinstance(value, str) and value.strip():
        return value
    if not isinstance(value, Mapping) or not value:
        raise Invalid(
            "expected a ParameterBounds.csv path or a mapping name -> [lower, upper], got "
            f"{got(value)}"
        )
    out, bad = {}, False
    pair = ListOf(Float(), min_len=2)
    for name, bounds in value.items():
        where = (*path, name)
        if name not in PARAMETER_NAMES:
            ctx.report(
                where, unknown_message(name, path, PARAMETER_NAMES, {}, (), "unknown parameter")
            )
            bad = True
            continue
        lo_hi = ctx.check(pair, bounds, where, "[lower, upper] in physical units")
        if lo_hi is BAD:
            bad = True
        elif len(lo_hi) != 2 or not lo_hi[0] < lo_hi[1]:
            ctx.report_at(
                where,
                f"expected [lower, upper] with lower < upper, got {yaml_repr(list(bounds))}",
            )
            bad = True
        else:
            out[name] = lo_hi
    return BAD if bad else out


def _solver_settings(value: Any, path: tuple, ctx: Context) -> Any:
    # A mapping here; its keys are checked against fe.solver's adapter (SOLVER_SETTINGS).
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise Invalid(f"expected a mapping of the adapter's keyword arguments, got {got(value)}")
    return dict(value)


@dataclass(frozen=True)
class FeSettings:
    """``fe``: the FE campaign (fe/params.yaml)."""

    solver: str = setting(Choice(SOLVERS), "FE solver adapter (femcal.fe registry)")
    bounds: Any = setting(
        FnCheck("a ParameterBounds.csv path or a mapping name -> [lower, upper]", _bounds),
        "the sampling box: name -> [lower, upper], or a ParameterBounds.csv path",
    )
    splits: dict = setting(
        MapOf(Int(0), KeyChoice(SPLITS, "split"), what="split -> configurations"),
        "configurations per split (large, small, test)",
    )
    seed: int = setting(Int(0), "seed of the designs")
    load_cases: tuple[str, ...] = setting(
        ListOf(Choice(LOAD_CASES), unique=True), "load cases simulated (all four)"
    )
    moments: tuple[float, ...] = setting(MOMENTS, "moments simulated, Nm")
    out_dir: str = setting(PATH, "dataset folder in the study's layout")
    store: str = setting(
        PATH, "durable store of finished jobs (JSON lines; .jsonl.gz to commit it)"
    )
    settings: dict = setting(
        FnCheck("a mapping of the adapter's keyword arguments", _solver_settings),
        "the adapter's keyword arguments (part of every job's hash)",
        {},
    )
    scratch_dir: str | None = optional(PATH, "per-job scratch (null: temp)")
    metrics_file: str | None = optional(PATH, "campaign figures (DVC metrics)")
    scheduler_address: str | None = optional(
        DASK_ADDRESS,
        "Dask scheduler, tcp://host:port (null: a local cluster, or FEMCAL_DASK_ADDRESS)",
    )
    n_workers: int = setting(Int(1), "workers of the local cluster", 2)

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        if v["load_cases"] is not None and sorted(v["load_cases"]) != sorted(LOAD_CASES):
            yield (
                "load_cases",
                (
                    "a dataset in the study's layout needs all four load cases "
                    f"{list(LOAD_CASES)}; got {list(v['load_cases'])}"
                ),
            )


@dataclass(frozen=True)
class IdpRange:
    """A literature range of the intradiscal pressure at one force, MPa."""

    _complete: ClassVar[bool] = True

    low: float = setting(Float(0), "lowest value, MPa")
    mean: float = setting(Float(0), "mean value, MPa")
    high: float = setting(Float(0), "highest value, MPa")

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        if not v["low"] <= v["mean"] <= v["high"]:
            yield (
                "mean",
                (f"need low <= mean <= high; got {v['low']:g}, {v['mean']:g}, {v['high']:g}"),
            )


@dataclass(frozen=True)
class PublishedIdp:
    """An intradiscal pressure published for one posture or activity (no force known), MPa."""

    _complete: ClassVar[bool] = True

    source: str = setting(NAME, "citation: authors, year, journal, volume:pages")
    condition: str = setting(NAME, "posture or activity, as the source names it")
    idp_mpa: float = setting(Float(0, lo_open=True), "the published value, MPa")
    kind: str = setting(Choice(("in vivo", "in vitro")), "in vivo or in vitro")
    subjects: int = setting(Int(1), "subjects or specimens measured")
    level: str = setting(NAME, "disc level, e.g. L4-L5")


@dataclass(frozen=True)
class AdaptSettings:
    """``adapt``: adaptive sampling, fine-tuning, and the challenger against the champion."""

    _complete: ClassVar[bool] = True

    model_uri: str = setting(MODEL_URI, "the surrogate to adapt (a model folder or models:/ URI)")
    targets: str = setting(PATH, "measurements whose calibrations steer the runs")
    train: str = setting(PATH, "the surrogate's prepared training table")
    heldout: str = setting(PATH, "prepared table of held-out FE configurations (the judge)")
    out_model: str = setting(PATH, "folder of the champion's files (the winner)")
    out_dir: str = setting(PATH, "folder of the rounds' tables")
    store: str = setting(PATH, "campaign store of the new FE runs")
    rounds: int = setting(Int(1), "rounds of FE runs and fine-tuning", 3)
    n_explore: int = setting(Int(0), "configurations explored per round (ensemble spread)", 16)
    n_candidates: int = setting(Int(1), "Latin-hypercube candidates ranked by spread", 2048)
    finetune: dict = setting(
        SURROGATE_FIXED, "NeuralSurrogate settings of the fine-tuning (warm start)", {}
    )
    calibrate_options: dict = setting(
        CALIBRATOR_OPTIONS["pgd"], "pgd options of the rounds' calibrations", {}
    )
    seed: int = setting(Int(0), "seed of the candidates and calibrations", 0)


@dataclass(frozen=True)
class RefineSettings:
    """``validate.refine``: FE-in-the-loop refinement of the calibration before validating it."""

    _complete: ClassVar[bool] = True

    model_uri: str = setting(
        MODEL_URI, "the surrogate whose Jacobian steers the steps (a model folder or models:/ URI)"
    )
    max_fe_runs: int = setting(
        Int(1), "FE runs per specimen at most, the first included (1: validate only)", 1
    )
    tol_deg: float = setting(
        Float(0, lo_open=True), "FE-evaluated MAE at which a specimen is confirmed, deg", 0.05
    )


@dataclass(frozen=True)
class ValidateSettings:
    """``validate``: FE re-simulation of the calibrated parameters and the IDP check."""

    calibration_dir: str = setting(PATH, "calibration folder validated")
    measurements: str = setting(PATH, "the measurements that were calibrated to")
    out_dir: str = setting(PATH, "output folder")
    store: str = setting(PATH, "campaign store of the FE runs")
    metrics_file: str | None = optional(PATH, "figures (DVC metrics)")
    forces: tuple[float, ...] = setting(
        ListOf(Float(0, lo_open=True), unique=True), "axial compression forces, N", []
    )
    idp_literature: dict = setting(
        MapOf(Section(IdpRange), Float(0, lo_open=True), what="force in N -> {low, mean, high}"),
        "published in vitro IDP range per force: force in N -> {low, mean, high} in MPa",
        {},
    )
    idp_published: tuple = setting(
        ListOf(Section(PublishedIdp)),
        "published IDP values without a known force (in vivo postures): the axial force at "
        "which each calibrated disc reaches them is reported",
        [],
    )
    idp_model_uri: str | None = optional(
        MODEL_URI,
        "the IDP head (train@idp), compared with FE's pressures under the moments (null: not "
        "compared)",
    )
    refine: RefineSettings | None = optional(
        Section(RefineSettings), "FE-in-the-loop refinement (null: validate the calibration as is)"
    )


def _range_of(lo: float, hi: float, unit: str) -> FnCheck:
    """A ``[low, high]`` pair of numbers within ``[lo, hi]``, ``low <= high``."""
    what = f"a pair [low, high] of numbers in [{lo:g}, {hi:g}] {unit}".rstrip()

    def check(value: Any, path: tuple, ctx: Context) -> Any:
        ok = isinstance(value, list | tuple) and len(value) == 2
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        if not ok or not lo <= value[0] <= value[1] <= hi:
            raise Invalid(f"expected {what} with low <= high, got {got(value)}")
        return (float(value[0]), float(value[1]))

    return FnCheck(what, check)


@dataclass(frozen=True)
class CohortSettings:
    """``cohort``: an FE-made cohort with hidden posterior elements (femcal.fe.cohort).

    Four balanced classes (the disc alone, facets, ligaments, both); each specimen's disc
    parameters are drawn uniformly from ``fe.bounds`` (trimmed by ``disc_margin`` at each
    side) and its elements' properties uniformly (log-uniformly for the stiffnesses) from the
    ranges below, around the defaults of ``fe.settings.posterior`` (docs/fe-cohort.md).
    """

    _complete: ClassVar[bool] = True

    out_dir: str = setting(PATH, "cohort folder: the study's layout (Test/) and answers.csv")
    store: str = setting(PATH, "durable store of the cohort's FE jobs (.jsonl.gz to commit it)")
    per_class: int = setting(Int(1), "specimens per class (4 classes)", 26)
    seed: int = setting(Int(0), "seed of the draws and of the measurement noise", 0)
    noise_deg: float = setting(Float(0), "sd of the Gaussian noise added to the RoM, deg", 0.05)
    disc_margin: float = setting(
        Float(0, 0.45), "fraction of each parameter's range left out at both ends", 0.05
    )
    facet_gap_mm: tuple = setting(
        _range_of(0, 3, "mm"), "facet clearance drawn from [low, high], mm", [0.25, 1.0]
    )
    facet_stiffness_n_per_mm: tuple = setting(
        _range_of(1, 1e5, "N/mm"),
        "facet contact stiffness drawn log-uniformly from [low, high], N/mm",
        [25.0, 100.0],
    )
    ligament_stiffness_scale: tuple = setting(
        _range_of(0.1, 10, ""),
        "factor on every ligament's default stiffness, drawn log-uniformly from [low, high]",
        [0.5, 2.0],
    )
    ligament_slack_shift: tuple = setting(
        _range_of(-0.3, 0.5, ""),
        "added to every ligament's default slack strain (then clipped to its range)",
        [-0.15, 0.05],
    )


# ------------------------------------------------------------------ posterior elements
# The posterior elements of the CalculiX model (femcal.fe.posterior): their parameters, units,
# ranges and defaults, declared here once. Axes as the disc model's: x lateral (right), y
# anterior, z cranial; the lower endplate at z = 0, the disc centre at x = y = 0. Sources:
# docs/fe-posterior-elements.md.

#: The ligaments the model knows, caudal-cranial tension-only springs.
LIGAMENTS: tuple[str, ...] = (
    "supraspinous",
    "interspinous",
    "flavum",
    "capsular",
    "intertransverse",
)

#: Default properties and attachment of each ligament (keys: the fields of
#: :class:`LigamentSettings`). Stiffness of the linear region: Pintar et al. 1992 (supraspinous,
#: interspinous, flavum, capsular), the tri-linear table quoted by Guo et al. 2021 (PMC8147546)
#: for the intertransverse; toe strain: the first transition strain of that table; rest lengths:
#: Naserkhaki et al. 2018 (L4-L5) but the capsule's, its vertical span across the joint (an
#: estimate: a shorter vertical spring's nodes pass each other in extension and it pulls
#: again). Positions: estimates for the 50 x 35 mm disc. Slack strain 0.45 of the four
#: posterior ligaments (0 of the intertransverse): calibrated so that the segment-to-disc RoM
#: ratios at 10 Nm fall near the published ones (docs/fe-posterior-elements.md).
LIGAMENT_DEFAULTS: dict[str, dict[str, float]] = {
    "supraspinous": {
        "stiffness_n_per_mm": 23.7,
        "toe_strain": 0.20,
        "slack_strain": 0.45,
        "lateral_mm": 0.0,
        "posterior_mm": 60.0,
        "height_mm": 5.5,
        "length_mm": 27.49,
    },
    "interspinous": {
        "stiffness_n_per_mm": 11.6,
        "toe_strain": 0.139,
        "slack_strain": 0.45,
        "lateral_mm": 0.0,
        "posterior_mm": 45.0,
        "height_mm": 5.5,
        "length_mm": 8.85,
    },
    "flavum": {
        "stiffness_n_per_mm": 27.2,
        "toe_strain": 0.059,
        "slack_strain": 0.45,
        "lateral_mm": 0.0,
        "posterior_mm": 35.0,
        "height_mm": 5.5,
        "length_mm": 15.89,
    },
    "capsular": {
        "stiffness_n_per_mm": 33.9,
        "toe_strain": 0.25,
        "slack_strain": 0.45,
        "lateral_mm": 18.0,
        "posterior_mm": 30.0,
        "height_mm": 5.5,
        "length_mm": 10.0,
    },
    "intertransverse": {
        "stiffness_n_per_mm": 10.7,
        "toe_strain": 0.182,
        "slack_strain": 0.0,
        "lateral_mm": 35.0,
        "posterior_mm": 22.0,
        "height_mm": 5.5,
        "length_mm": 18.69,
    },
}


@dataclass(frozen=True)
class FacetSettings:
    """``fe.settings.posterior.facets``: two facet joints, each one unilateral gap element.

    Each joint is a CalculiX ``GAPUNI`` between a node tied to the upper (moving) endplate and a
    coincident node of the fixed lower vertebra, at ``(+-lateral_mm, -posterior_mm,
    height_mm)``. It closes when the upper node has moved ``gap_mm`` along the joint's contact
    normal: in the transverse plane at ``axial_angle_deg`` from the lateral direction
    (the joint plane's angle to the sagittal plane), tilted ``inclination_deg`` downwards.
    """

    _complete: ClassVar[bool] = True

    gap_mm: float = setting(Float(0, 3), "facet joint clearance, mm, in [0, 3]", 0.5)
    stiffness_n_per_mm: float = setting(
        Float(1, 1e5), "contact stiffness of each closed facet, N/mm, in [1, 1e5]", 50.0
    )
    lateral_mm: float = setting(
        Float(5, 40), "distance of each facet from the mid-sagittal plane, mm, in [5, 40]", 16.0
    )
    posterior_mm: float = setting(
        Float(18, 60), "distance of the facets behind the disc centre, mm, in [18, 60]", 30.0
    )
    height_mm: float = setting(
        Float(-20, 30), "height of the facet centres above the lower endplate, mm", 5.5
    )
    axial_angle_deg: float = setting(
        Float(0, 90), "joint plane to the sagittal plane (transverse view), deg, in [0, 90]", 45.0
    )
    inclination_deg: float = setting(
        Float(0, 80), "downward tilt of the contact normal, deg, in [0, 80]", 30.0
    )


@dataclass(frozen=True)
class LigamentSettings:
    """One ligament: a tension-only nonlinear spring (``SPRINGA``), one per side if lateral.

    The spring is vertical, centred at ``(+-lateral_mm, -posterior_mm, height_mm)`` with rest
    length ``length_mm``; it carries no force below the elongation ``slack_strain *
    length_mm``, a quadratic toe over the next ``toe_strain * length_mm`` whose slope reaches
    ``stiffness_n_per_mm``, then that slope (linear region). Defaults per ligament:
    :data:`LIGAMENT_DEFAULTS`.
    """

    _complete: ClassVar[bool] = True

    stiffness_n_per_mm: float = setting(
        Float(0.1, 1000), "stiffness of the linear region (each side), N/mm, in [0.1, 1000]"
    )
    toe_strain: float = setting(Float(0, 1), "strain span of the toe region, in [0, 1]")
    slack_strain: float = setting(
        Float(-0.3, 0.5), "strain at which force starts (< 0: pre-strained), in [-0.3, 0.5]"
    )
    lateral_mm: float = setting(
        Float(0, 60), "distance from the mid-sagittal plane (0: one midline spring), mm"
    )
    posterior_mm: float = setting(Float(0, 100), "distance behind the disc centre, mm")
    height_mm: float = setting(Float(-30, 40), "centre above the lower endplate, mm")
    length_mm: float = setting(Float(0.5, 60), "rest length (upper to lower attachment), mm")


def _ligaments(value: Any, path: tuple, ctx: Context) -> Any:
    if value is None:
        return {}
    if isinstance(value, list | tuple):
        value = {name: {} for name in value}
    if not isinstance(value, Mapping):
        raise Invalid(
            f"expected a list of ligament names or a mapping name -> settings, got {got(value)}"
        )
    out, bad = {}, False
    for name, overrides in value.items():
        where = (*path, name)
        if name not in LIGAMENTS:
            ctx.report(where, unknown_message(name, path, LIGAMENTS, {}, (), "unknown ligament"))
            bad = True
            continue
        if overrides is not None and not isinstance(overrides, Mapping):
            ctx.report_at(where, f"expected a mapping of ligament settings, got {got(overrides)}")
            bad = True
            continue
        merged = {**LIGAMENT_DEFAULTS[name], **(overrides or {})}
        out[name] = ctx.check(Section(LigamentSettings), merged, where)
        bad |= out[name] is BAD
    return BAD if bad else out


@dataclass(frozen=True)
class PosteriorSettings:
    """``fe.settings.posterior``: the posterior elements joined to the disc (all optional).

    Absent (or null) ``facets`` and an empty ``ligaments``: the disc alone.
    """

    _complete: ClassVar[bool] = True

    facets: FacetSettings | None = optional(
        Section(FacetSettings), "facet joints (GAPUNI contact; null: none)"
    )
    ligaments: dict = setting(
        FnCheck("a list of ligament names or a mapping name -> settings", _ligaments),
        f"tension-only ligaments ({', '.join(LIGAMENTS)}): a list, or name -> overrides",
        {},
    )

    @property
    def active(self) -> bool:
        """Whether any posterior element is present."""
        return self.facets is not None or bool(self.ligaments)


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _posterior(value: Any, path: tuple, ctx: Context) -> Any:
    # Validated against PosteriorSettings; kept as plain data (it is hashed into job keys).
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise Invalid(f"expected a mapping (facets, ligaments) or null, got {got(value)}")
    checked = Section(PosteriorSettings)(value, path, ctx)
    return BAD if checked is BAD else _plain(value)


#: The check of ``fe.settings.posterior`` (a CalculixDisc keyword).
POSTERIOR_KEYWORD = (
    FnCheck("null or a mapping of posterior elements (facets, ligaments)", _posterior),
    "posterior elements joined to the disc: facets, ligaments (leave out for the disc alone)",
)
SOLVER_SETTINGS["calculix"].table.setdefault("posterior", POSTERIOR_KEYWORD)


def posterior_settings(
    value: PosteriorSettings | Mapping | None, where: str = "fe/params.yaml"
) -> PosteriorSettings:
    """Validated posterior elements from their settings (a mapping, an instance or None).

    Parameters
    ----------
    value : PosteriorSettings, mapping or None
        ``fe.settings.posterior``; None or an empty mapping is the disc alone.
    where : str
        The file the value came from, named in messages.

    Returns
    -------
    PosteriorSettings

    Raises
    ------
    ConfigError
        Unknown elements or fields, values out of range: the file, the field, what was given
        and what is allowed.
    """
    if isinstance(value, PosteriorSettings):
        return value
    if value is None:
        return PosteriorSettings()
    ctx = Context(complete=True)
    path = ("fe", "settings", "posterior")
    if not isinstance(value, Mapping):
        ctx.report_at(path, f"expected a mapping (facets, ligaments) or null, got {got(value)}")
        checked = BAD
    else:
        checked = Section(PosteriorSettings)(value, path, ctx)
    if ctx.problems or checked is BAD:
        problems = "\n".join(f"  - {message}" for _, message in ctx.problems)
        raise ConfigError(
            f"{where}: invalid posterior elements:\n{problems}\nFix the values in {where} "
            "(docs/fe-posterior-elements.md lists every field, its unit and range)."
        )
    return checked
