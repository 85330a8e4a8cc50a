"""The sections of the root ``params.yaml``, one frozen dataclass each.

Every field is a setting (:func:`~femcal.settings._validate.setting`): its check, its
one-line doc and its default; a field without a default is required.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from femcal.schema import TARGETS
from femcal.settings._checks import Bool, Choice, Float, FnCheck, Int, KeyChoice, ListOf
from femcal.settings._messages import BAD, Context, Invalid, got
from femcal.settings._validate import Keywords, MapOf, Section, optional, setting
from femcal.settings.keywords import (
    BASELINE_MODELS,
    CALIBRATOR_OPTIONS,
    CALIBRATORS,
    INVERSE_FIXED,
    SPLITS,
    SURROGATE_FIXED,
)
from femcal.settings.search import SearchSpace
from femcal.settings.values import DATASET_NAME, MODEL_URI, MOMENTS, N_JOBS, NAME, PATH, SQL_URL

# --------------------------------------------------------------- settings several sections share
# The helpers build a new field each call: one dataclass field cannot serve two classes.
_BASELINES = ListOf(Choice(BASELINE_MODELS), unique=True)


def _n_trials() -> Any:
    return setting(Int(0), "complete Optuna trials (0: train on fixed alone)", 0)


def _fixed(keywords: Keywords) -> Any:
    return setting(keywords, f"{keywords.owner} hyper-parameters", {})


def _search_space(keywords: Keywords) -> Any:
    return setting(SearchSpace(keywords), "Optuna search space over the hyper-parameters", {})


def _plots() -> Any:
    return setting(Bool(), "write plots", True)


def _max_plots() -> Any:
    return optional(Int(0), "per-specimen PNGs for the first N specimens (null: all)")


# ------------------------------------------------------------------------------- the sections
@dataclass(frozen=True)
class DataSettings:
    """``data``: where the study's files and the prepared tables live."""

    raw_dir: str = setting(PATH, "folder of the study's files as fetched (fetch's output)")
    prepared_dir: str = setting(PATH, "folder of the tidy tables and parameter_space.json")
    source_dir: str | None = optional(
        PATH, "what prepare reads, in the study's layout (null: raw_dir)"
    )
    limit_configs: int | None = optional(
        Int(1), "keep only the first N configurations per split (null: all)"
    )


@dataclass(frozen=True)
class MlflowSettings:
    """``mlflow``: the tracking store, the experiment and the registered model name."""

    store_dir: str = setting(
        PATH,
        "folder of the default store sqlite:///<store_dir>/mlflow.db (MLFLOW_TRACKING_URI "
        "overrides it)",
    )
    experiment: str = setting(NAME, "MLflow experiment of every run")
    model_name: str = setting(NAME, "registered name of the surrogate")


@dataclass(frozen=True)
class TrainSplitSettings:
    """``train.<split>``: one surrogate trained on a prepared split (search + ensemble)."""

    n_trials: int = _n_trials()
    final_members: int = setting(Int(1), "ensemble members of the final model", 1)
    register: bool = setting(Bool(), "register the final model in MLflow", False)
    fixed: dict = _fixed(SURROGATE_FIXED)
    search_space: dict = _search_space(SURROGATE_FIXED)
    seed: int | None = optional(Int(0), "seed of this split (default: train.seed)")
    split: str | None = optional(
        Choice(SPLITS), "prepared table trained on (default: the section's name)"
    )
    model_name: str | None = optional(NAME, "registered name (default: mlflow.model_name)")
    target: str = setting(
        Choice(tuple(TARGETS)),
        "output learnt: rom_deg, or idp_mpa (an FE campaign's IDP head; needs fixed "
        "log_target: false)",
        "rom_deg",
    )


@dataclass(frozen=True)
class TrainSettings:
    """``train``: Optuna storage and study, and one section per split (``train.<split>``)."""

    _open: ClassVar[tuple] = (
        "splits",
        Section(TrainSplitSettings),
        "splits: mappings such as large: {n_trials: 3, fixed: {...}}",
    )

    storage: str = setting(
        SQL_URL, "Optuna RDB storage, a SQLAlchemy URL (FEMCAL_OPTUNA_STORAGE overrides it)"
    )
    study_name: str = setting(NAME, "base name of the Optuna studies")
    val_fraction: float = setting(
        Float(0, 1, lo_open=True, hi_open=True), "fraction of configurations for validation"
    )
    seed: int = setting(Int(0), "seed of the sampler, the split and the members")
    splits: dict = field(default_factory=dict)

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        for name, split in v["splits"].items():
            if split.split is None and name not in SPLITS:
                yield (
                    (name,),
                    (
                        f"{name} is not a prepared split ({', '.join(SPLITS)}); add split: large "
                        "(the table it trains on)"
                    ),
                )


@dataclass(frozen=True)
class BaselinesSettings:
    """``baselines``: the study's model zoo."""

    seed: int = setting(Int(0), "seed of the stochastic baselines")
    n_jobs: int = setting(
        N_JOBS,
        "parallel jobs of the baselines that support it",
    )
    models: tuple[str, ...] = setting(_BASELINES, "baseline models to fit")


@dataclass(frozen=True)
class InterpolationSettings:
    """``interpolation``: train on some moments, test on the others."""

    train_moments: tuple[float, ...] = setting(MOMENTS, "moments trained on, Nm")
    test_moments: tuple[float, ...] = setting(MOMENTS, "moments tested on, Nm")
    final_members: int = setting(Int(1), "ensemble members of the surrogate")
    baselines: tuple[str, ...] = setting(_BASELINES, "baselines checked too")

    @staticmethod
    def _cross(v: dict) -> Iterable[tuple[str, str]]:
        both = sorted(set(v["train_moments"] or ()) & set(v["test_moments"] or ()))
        if both:
            yield (
                "test_moments",
                (
                    f"{', '.join(f'{m:g}' for m in both)} Nm also trained on; test on moments "
                    "left out of train_moments"
                ),
            )


@dataclass(frozen=True)
class InverseSettings:
    """``inverse``: the study's inverse network (RoM curves -> parameters)."""

    surrogate_uri: str = setting(MODEL_URI, "surrogate the training samples come from")
    moments: tuple[float, ...] = setting(MOMENTS, "moment grid of the curves, Nm")
    n_samples: int = setting(Int(2), "surrogate samples to train on", 50_000)
    n_trials: int = _n_trials()
    seed: int = setting(Int(0), "seed of the samples, the split and the network", 0)
    study_name: str = setting(NAME, "Optuna study name", "ivd-inverse")
    register_as: str | None = optional(NAME, "registered name (null: not registered)")
    fixed: dict = _fixed(INVERSE_FIXED)
    search_space: dict = _search_space(INVERSE_FIXED)


_PER_SIDE = Float(0)


def _per_side(value: Any, path: tuple, ctx: Context) -> Any:
    """A number >= 0 for both sides of the trained range, or ``{below: ..., above: ...}``."""
    if isinstance(value, Mapping):
        if set(value) != {"below", "above"}:
            raise Invalid(f"expected {{below: number >= 0, above: number >= 0}}, got {got(value)}")
        out = {side: ctx.check(_PER_SIDE, value[side], (*path, side)) for side in value}
        return BAD if any(v is BAD for v in out.values()) else out
    return _PER_SIDE(value, path, ctx)


@dataclass(frozen=True)
class MomentSettings:
    """``moments``: the moment policy every command shares (femcal.moments.MomentPolicy).

    Each setting is one value per side of the trained range, ``{below, above}`` (one number
    serves both sides).
    """

    error_growth: Any = setting(
        FnCheck("{below, above} numbers >= 0, or one number >= 0", _per_side),
        "growth of the surrogate's error sd per unit log-moment distance beyond range, per side",
    )
    max_log_ratio: Any = setting(
        FnCheck("{below, above} numbers >= 0, or one number >= 0", _per_side),
        "log-moment distance beyond the trained range up to which moments are used, per side",
    )


@dataclass(frozen=True)
class EffectsSettings:
    """``effects``: the user's effect modules, imported before the effect registry is used."""

    _hint: ClassVar[str] = (
        "the effects section must be {modules: [paths]}, each path a .py file or a folder of "
        "them relative to the project root. Write e.g. `effects: {modules: [my_effects.py]}` "
        "(the effects a calibration uses are listed under calibrate.datasets.<name>.effects)"
    )

    modules: tuple[str, ...] = setting(
        ListOf(PATH), ".py files or folders of them, relative to the params file's folder", []
    )


@dataclass(frozen=True)
class DatasetSettings:
    """``calibrate.datasets.<name>``: one measurement file and the effects added to the disc."""

    measurements: str = setting(PATH, "a long/wide CSV, or a folder of ROM_Results_* files")
    effects: tuple[str, ...] = setting(
        ListOf(NAME, unique=True), "effects added to the disc model ([] = the disc alone)", []
    )
    noise_deg: float | None = optional(
        Float(0, lo_open=True),
        "sd of one measurement, degrees (null: only the surrogate's error is counted)",
    )


def _dataset(value: Any, path: tuple, ctx: Context) -> Any:
    if isinstance(value, str) and value.strip():
        return DatasetSettings(measurements=value)
    if isinstance(value, Mapping):
        return Section(DatasetSettings)(value, path, ctx)
    raise Invalid(
        f"expected a path or {{measurements: path, effects: [names], noise_deg: sd}}, got "
        f"{got(value)}"
    )


def _method_options(value: Any, path: tuple, ctx: Context) -> Any:
    return CALIBRATOR_OPTIONS[path[-1]](value, path, ctx)


@dataclass(frozen=True)
class CalibrateSettings:
    """``calibrate``: the calibration stages, one per dataset, and the calibrator."""

    _retired: ClassVar[dict[str, str]] = {
        "max_extrapolation": "replaced by moments.max_log_ratio (and moments.error_growth), the "
        "moment policy every command shares; delete it and set those in the moments section",
        "measurements": "replaced by calibrate.datasets.<name>.measurements (one stage per "
        "dataset); move it there",
        "metrics_file": "each dataset's figures go to reports/calibrate-<name>.json; delete it",
        "effects": "replaced by calibrate.datasets.<name>.effects (effects per dataset); move "
        "it there",
    }

    out_dir: str = setting(PATH, "outputs go to <out_dir>/<dataset>/")
    method: str = setting(Choice(CALIBRATORS), "calibration method")
    model_uri: str = setting(MODEL_URI, "the surrogate: a model folder or a models:/ URI")
    datasets: dict = setting(
        MapOf(
            FnCheck("a path or {measurements, effects}", _dataset),
            DATASET_NAME,
            what="datasets",
        ),
        "name -> {measurements: path, effects: [names], noise_deg: sd}, one calibrate@<name> "
        "stage each",
        {},
    )
    holdout_uri: str | None = optional(
        MODEL_URI, "held-out surrogate that re-evaluates every calibration"
    )
    start_bank: str | None = optional(PATH, "prepared table whose configurations are pgd's starts")
    seed: int = setting(Int(0), "seed of the calibrator", 0)
    chunk_size: int | None = optional(Int(1), "specimens per batch (null: all at once)")
    plots: bool = _plots()
    max_plots: int | None = _max_plots()
    options: dict = setting(
        MapOf(
            FnCheck("calibrator options", _method_options),
            KeyChoice(CALIBRATORS, "calibration method"),
            what="calibrator options per method",
        ),
        "method -> the calibrator's keyword options",
        {},
    )


@dataclass(frozen=True)
class PlantSettings:
    """``plant``: a cohort with hidden effects built from the Test set's FE curves."""

    out_dir: str = setting(PATH, "folder of the planted cohort")
    n_per_class: int = setting(Int(1), "specimens per class (4 classes)")
    moments: tuple[float, ...] = setting(MOMENTS, "moments of the cohort, Nm")
    noise_deg: float = setting(Float(0), "measurement noise sd, degrees")
    seed: int = setting(Int(0), "seed of the cohort", 0)


@dataclass(frozen=True)
class DiagnoseSettings:
    """``diagnose``: where the model fails and which effect is missing."""

    measurements: str = setting(PATH, "measurement file diagnosed")
    out_dir: str = setting(PATH, "output folder")
    metrics_file: str | None = optional(PATH, "summary figures (DVC metrics)")
    noise_deg: float | None = optional(
        Float(0, lo_open=True), "measurement noise sd, degrees (null: estimated)"
    )
    candidates: tuple[str, ...] | None = optional(
        ListOf(NAME, unique=True), "effects tried (null: every registered one)"
    )
    min_delta: float = setting(Float(0), "BIC gain an effect needs", 10.0)
    alpha: float = setting(
        Float(0, 1, lo_open=True, hi_open=True), "level of the adequacy tests", 0.01
    )
    max_effects: int = setting(Int(0), "effects forward selection may add per specimen", 3)
    seed: int = setting(Int(0), "seed of the diagnosis", 0)
    plots: bool = _plots()
    max_plots: int | None = _max_plots()
