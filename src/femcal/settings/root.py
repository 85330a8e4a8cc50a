"""The sections of the root ``params.yaml``, one model each: every field a setting (its type
with bounds or choices, one-line doc, default; none: required). The diagnosis' defaults are
those of :class:`femcal.diagnose.DiagnoseOptions`, read from it."""

from typing import Annotated, Any, ClassVar, Literal

from pydantic import ValidationError, ValidationInfo, WrapValidator, model_validator

from femcal.schema import TARGETS
from femcal.settings._format import fail, keys_of
from femcal.settings.keywords import (
    BASELINE,
    METHOD,
    SPLITS,
    CalibratorOptions,
    InverseKeywords,
    SurrogateKeywords,
)
from femcal.settings.values import (
    DATASET_NAME,
    MODEL_URI,
    MOMENTS,
    N_JOBS,
    NAME,
    PATH,
    SQL_URL,
    Bool,
    Float,
    Int,
    ListOf,
    OptionSection,
    Section,
    light_class,
    plain,
    setting,
    with_options,
)

_BASELINES = ListOf(BASELINE, unique=True)
_MAX_PLOTS = "per-specimen PNGs for the first N specimens (null: all)"
_SPACE = "Optuna search space over the hyper-parameters"
space_of = light_class("training.search_space", "space_of")  # keyword -> an Optuna entry
_TRIALS = "complete Optuna trials (0: train on fixed alone)"
_TARGET = "output learnt: rom_deg, or idp_mpa (the IDP head; needs fixed log_target: false)"


class DataSettings(Section):
    """``data``: where the study's files and the prepared tables live."""

    raw_dir: PATH = setting("folder of the study's files as fetched (fetch's output)")
    prepared_dir: PATH = setting("folder of the tidy tables and parameter_space.json")
    source_dir: PATH | None = setting("what prepare reads, as laid out (null: raw_dir)", None)
    limit_configs: Int(1) | None = setting("the first N configurations per split (null: all)", None)


class MlflowSettings(Section):
    """``mlflow``: the tracking store, the experiment and the registered model name."""

    store_dir: PATH = setting("folder of sqlite:///<store_dir>/mlflow.db (or MLFLOW_TRACKING_URI)")
    experiment: NAME = setting("MLflow experiment of every run")
    model_name: NAME = setting("registered name of the surrogate")


class TrainSplitSettings(Section):
    """``train.<split>``: one surrogate trained on a prepared split (search + ensemble)."""

    n_trials: Int(0) = setting(_TRIALS, 0)
    final_members: Int(1) = setting("ensemble members of the final model", 1)
    register_model: Bool = setting("register the final model in MLflow", False, alias="register")
    fixed: plain(SurrogateKeywords) = setting("NeuralSurrogate hyper-parameters", {})
    search_space: space_of(SurrogateKeywords) = setting(_SPACE, {})
    seed: Int(0) | None = setting("seed of this split (default: train.seed)", None)
    split: Literal[SPLITS] | None = setting("table trained on (default: the section's name)", None)
    model_name: NAME | None = setting("registered name (default: mlflow.model_name)", None)
    target: Literal[tuple(TARGETS)] = setting(_TARGET, "rom_deg")
    stated_error_split: Literal[SPLITS] | None = setting("held-out split of its stated error", None)


class TrainSettings(Section):
    """``train``: Optuna storage and study, and one section per split (``train.<split>``)."""

    _open: ClassVar[str] = "splits"
    _open_what: ClassVar[str] = "splits: mappings such as large: {n_trials: 3, fixed: {...}}"

    storage: SQL_URL = setting("Optuna RDB storage, a SQLAlchemy URL (or FEMCAL_OPTUNA_STORAGE)")
    study_name: NAME = setting("base name of the Optuna studies")
    val_fraction: Float(gt=0, lt=1) = setting("fraction of configurations for validation")
    seed: Int(0) = setting("seed of the sampler, the split and the members")
    splits: dict[str, TrainSplitSettings] = setting("the splits trained, by name", {})

    @model_validator(mode="before")
    @classmethod
    def _gather_splits(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        splits = {k: v for k, v in data.items() if k not in keys_of(cls) and isinstance(v, dict)}
        return {**{k: v for k, v in data.items() if k not in splits}, "splits": splits}

    @model_validator(mode="after")
    def _named_splits(self) -> Any:
        for name, split in self.splits.items():
            if split.split is None and name not in SPLITS:
                why = f"{name} is not a prepared split ({', '.join(SPLITS)}); add split: large"
                raise fail(f"{why} (the table it trains on)", (name,))
        return self


class BaselinesSettings(Section):
    """``baselines``: the study's model zoo."""

    seed: Int(0) = setting("seed of the stochastic baselines")
    n_jobs: N_JOBS = setting("parallel jobs of the baselines that support it")
    models: _BASELINES = setting("baseline models to fit")


class InterpolationSettings(Section):
    """``interpolation``: train on some moments, test on the others."""

    train_moments: MOMENTS = setting("moments trained on, Nm")
    test_moments: MOMENTS = setting("moments tested on, Nm")
    final_members: Int(1) = setting("ensemble members of the surrogate")
    baselines: _BASELINES = setting("baselines checked too")

    @model_validator(mode="after")
    def _disjoint(self) -> Any:
        both = ", ".join(f"{m:g}" for m in sorted(set(self.train_moments) & set(self.test_moments)))
        if both:
            why = f"{both} Nm also trained on; test on moments left out of train_moments"
            raise fail(why, "test_moments")
        return self


class InverseSettings(Section):
    """``inverse``: the study's inverse network (RoM curves -> parameters)."""

    surrogate_uri: MODEL_URI = setting("surrogate the training samples come from")
    moments: MOMENTS = setting("moment grid of the curves, Nm")
    n_samples: Int(2) = setting("surrogate samples to train on", 50_000)
    n_trials: Int(0) = setting(_TRIALS, 0)
    seed: Int(0) = setting("seed of the samples, the split and the network", 0)
    study_name: NAME = setting("Optuna study name", "ivd-inverse")
    register_as: NAME | None = setting("registered name (null: not registered)", None)
    fixed: plain(InverseKeywords) = setting("InverseModel hyper-parameters", {})
    search_space: space_of(InverseKeywords) = setting(_SPACE, {})


class Sides(Section):
    """A value per side of the trained moment range; one number serves both sides."""

    _complete: ClassVar[bool] = True
    _describe: ClassVar[str] = "{below, above} numbers >= 0, or one number >= 0"

    below: Float(0) = setting("below the trained range")
    above: Float(0) = setting("above the trained range")

    @model_validator(mode="before")
    @classmethod
    def _one_number(cls, value: Any) -> Any:
        if isinstance(value, int | float) and not isinstance(value, bool) and 0 <= value < 1e308:
            return {"below": value, "above": value}
        return value

    def pair(self) -> tuple[float, float]:
        """``(below, above)``."""
        return (self.below, self.above)


class MomentSettings(Section):
    """``moments``: the moment policy every command shares (femcal.moments.MomentPolicy), each
    setting one value per side of the trained range, ``{below, above}`` (or one number)."""

    error_growth: Sides = setting("growth of the error sd per unit log-moment beyond range")
    max_log_ratio: Sides = setting("log-moment distance beyond range up to which moments count")


class EffectsSettings(Section):
    """``effects``: the user's effect modules, imported before the effect registry is used."""

    _hint: ClassVar[str] = (
        "the effects section must be {modules: [paths]}, each path a .py file or a folder of "
        "them relative to the project root. Write e.g. `effects: {modules: [my_effects.py]}` "
        "(the effects a calibration uses are listed under calibrate.datasets.<name>.effects)"
    )

    modules: ListOf(PATH) = setting(".py files or folders of them (relative paths)", ())


class DatasetSettings(Section):
    """``calibrate.datasets.<name>``: one measurement file and the effects added to the disc."""

    _describe: ClassVar[str] = "a path or {measurements: path, effects: [names], noise_deg: sd}"

    measurements: PATH = setting("a long/wide CSV, or a folder of ROM_Results_* files")
    effects: ListOf(NAME, unique=True) = setting("effects added to the disc ([]: none)", ())
    noise_deg: Float(gt=0) | None = setting("sd of one measurement, deg (null: not counted)", None)

    @model_validator(mode="before")
    @classmethod
    def _a_path(cls, value: Any) -> Any:
        return {"measurements": value} if isinstance(value, str) and value.strip() else value


def _datasets(value: Any, handler: Any, info: ValidationInfo) -> Any:
    """The datasets; in a partial check, an entry that only misses keys is kept as given
    (unvalidated) for the command that reads it to name what it misses."""
    try:
        return handler(value)
    except ValidationError as exc:
        errors = exc.errors()
        if (info.context or {}).get("complete", True) or any(
            e["type"] != "missing_setting" or len(e["loc"]) != 2 for e in errors
        ):
            raise
        good = handler({k: v for k, v in value.items() if k not in {e["loc"][0] for e in errors}})
        return {k: good.get(k) or DatasetSettings.model_construct(**value[k]) for k in value}


_DATASETS = Annotated[dict[DATASET_NAME, DatasetSettings], WrapValidator(_datasets)]


class CalibrateSettings(Section):
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

    out_dir: PATH = setting("outputs go to <out_dir>/<dataset>/")
    method: METHOD = setting("calibration method")
    model_uri: MODEL_URI = setting("the surrogate: a model folder or a models:/ URI")
    datasets: _DATASETS = setting("name -> a dataset, one calibrate@<name> stage each", {})
    holdout_uri: MODEL_URI | None = setting("held-out surrogate re-evaluating each fit", None)
    start_bank: PATH | None = setting("prepared table whose configurations are pgd's starts", None)
    seed: Int(0) = setting("seed of the calibrator", 0)
    chunk_size: Int(1) | None = setting("specimens per batch (null: all at once)", None)
    plots: Bool = setting("write plots", True)
    max_plots: Int(0) | None = setting(_MAX_PLOTS, None)
    options: plain(CalibratorOptions) = setting("method -> the calibrator's keyword options", {})

    def method_options(self, method: str | None = None) -> dict[str, Any]:
        """The keyword options of ``method`` (default: :attr:`method`), as given."""
        return dict(self.options.get(method or self.method) or {})


class PlantSettings(Section):
    """``plant``: a cohort with hidden effects built from the Test set's FE curves."""

    out_dir: PATH = setting("folder of the planted cohort")
    n_per_class: Int(1) = setting("specimens per class (4 classes)")
    moments: MOMENTS = setting("moments of the cohort, Nm")
    noise_deg: Float(0) = setting("measurement noise sd, degrees")
    seed: Int(0) = setting("seed of the cohort", 0)


@with_options
class DiagnoseSettings(OptionSection):
    """``diagnose``: where the model fails and which effect is missing."""

    _options: ClassVar[type] = light_class("diagnose.options", "DiagnoseOptions")

    measurements: PATH = setting("measurement file diagnosed")
    out_dir: PATH = setting("output folder")
    metrics_file: PATH | None = setting("summary figures (DVC metrics)", None)
    noise_deg: Float(gt=0) | None = setting("measurement noise sd, degrees (null: estimated)", None)
    candidates: ListOf(NAME, unique=True) | None = setting("effects tried (null: all)", None)
    plots: Bool = setting("write plots", True)
    max_plots: Int(0) | None = setting(_MAX_PLOTS, None)
