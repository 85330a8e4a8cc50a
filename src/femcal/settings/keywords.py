"""The static keyword tables: what ``fixed``, ``search_space``, ``options`` and ``settings`` take.

The registries' names (surrogates, calibrators, splits, FE solvers, mesh presets) and the
keyword arguments of the estimators, the calibrators and the FE adapter, each with its check
and a one-line doc. They are static so that validating needs no heavy import (no torch,
Lightning, scikit-learn or MLflow); ``tests/test_settings.py`` checks them against the real
signatures and registries.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from femcal.settings._checks import Bool, Check, Choice, Float, FnCheck, Int, ListOf, Nullable
from femcal.settings._messages import Context, Invalid, got
from femcal.settings._validate import Keywords
from femcal.settings.values import MODEL_URI, NAME

# ------------------------------------------------------------------ registries' names
#: Hidden activations of the networks (femcal.surrogates.nn.ACTIVATIONS).
ACTIVATIONS: tuple[str, ...] = ("silu", "gelu", "relu", "tanh", "softplus")
#: What ``femcal calibrate --plots`` writes (femcal.calibration.report.plot_mode): every figure,
#: the summary page only, or none.
PLOT_CHOICES: tuple[str, ...] = ("all", "summary", "none")
#: The study's baseline models (femcal.surrogates registry, without "nn").
BASELINE_MODELS: tuple[str, ...] = (
    "linear",
    "poly2",
    "poly3",
    "poly4",
    "poly5",
    "svr",
    "random_forest",
    "gaussian_process",
    "lightgbm",
)
#: Registered calibrators (femcal.calibration registry).
CALIBRATORS: tuple[str, ...] = ("pgd", "pgd-study", "ga", "inverse")
#: Built-in physical effects (femcal.effects.builtin); installed plugins and effect files
#: (``--effects-module``, ``effects.modules``) register more at run time.
BUILTIN_EFFECTS: tuple[str, ...] = ("facet_contact", "ligament_tension", "neutral_zone")
#: Prepared splits (femcal.prepare.SPLITS) and FE campaign splits (femcal.fe.campaign).
SPLITS: tuple[str, ...] = ("large", "small", "test")
#: Registered FE solver adapters (femcal.fe registry).
SOLVERS: tuple[str, ...] = ("calculix",)
#: Mesh presets of the disc geometry (femcal.fe.geometry.MESH_PRESETS).
MESH_PRESETS: tuple[str, ...] = ("coarse", "default", "fine")


# ------------------------------------------------------------------ network hyper-parameters
#: The architecture, shared by both networks: hidden widths (or width and depth), activation.
_NETWORK: dict[str, tuple[Check, str]] = {
    "hidden": (ListOf(Int(1), min_len=1), "hidden-layer widths (or give width and depth)"),
    "width": (Int(1), "width of every hidden layer (with depth: hidden = [width] * depth)"),
    "depth": (Int(1), "number of hidden layers (with width)"),
    "activation": (Choice(ACTIVATIONS), "hidden activation"),
}
_WEIGHT_DECAY = (Float(0), "AdamW weight decay")
_DROPOUT = (Float(0, 1, hi_open=True), "dropout after each hidden activation")
_PATIENCE = (Int(0), "early stopping: epochs without a better validation MAE")

#: NeuralSurrogate keywords settable in train.<split>.fixed / search_space (plus width, depth).
SURROGATE_HYPERPARAMETERS: dict[str, tuple[Check, str]] = {
    **_NETWORK,
    "log_target": (Bool(), "model log RoM (RoM must then be > 0)"),
    "loss": (Choice(("l1", "l2")), "training loss on the scaled (log-)RoM"),
    "learning_rate": (Float(0, lo_open=True), "peak learning rate (AdamW, one-cycle)"),
    "weight_decay": _WEIGHT_DECAY,
    "batch_size": (Int(1), "configurations per optimisation step"),
    "max_epochs": (Int(1), "epochs per ensemble member"),
    "patience": _PATIENCE,
    "dropout": _DROPOUT,
    "val_fraction": (
        Float(0, 1, hi_open=True),
        "validation fraction when no validation set is given (train uses train.val_fraction)",
    ),
    "log_params": (Bool(), "parameters with positive bounds enter in log scale"),
    "lr_schedule": (Choice(("onecycle", "cosine", "constant")), "learning-rate schedule"),
    "moment_degree": (
        Nullable(Int(0, 8)),
        "degree of each curve's polynomial in log-moment (null: 3)",
    ),
}
_SURROGATE_REFUSED = {
    "n_members": "the ensemble size is train.<split>.final_members (trials train one member)",
    "seed": "set train.seed, or train.<split>.seed for one split",
    "space": "the parameter space comes from the prepared data",
    "warm_start": "training starts anew; the FE pipeline's adaptive sampling fine-tunes",
}

#: InverseModel keywords settable in inverse.fixed / search_space (plus width, depth).
INVERSE_HYPERPARAMETERS: dict[str, tuple[Check, str]] = {
    **_NETWORK,
    "learning_rate": (Float(0, lo_open=True), "initial AdamW learning rate"),
    "weight_decay": _WEIGHT_DECAY,
    "dropout": _DROPOUT,
    "batch_size": (Int(1), "samples per step"),
    "max_epochs": (Int(1), "upper bound on epochs"),
    "patience": _PATIENCE,
    "min_delta": (Float(0), "smallest validation-MAE improvement that counts"),
    "scheduler_patience": (Int(0), "ReduceLROnPlateau patience in epochs"),
    "scheduler_factor": (Float(0, 1, lo_open=True, hi_open=True), "ReduceLROnPlateau factor"),
    "log_input": (Bool(), "standardise log RoM rather than RoM"),
    "val_fraction": (Float(0, 1, hi_open=True), "fraction of samples held out for validation"),
}
_INVERSE_REFUSED = {
    "seed": "set inverse.seed",
    "space": "the parameter space comes from the surrogate",
}


def _no_hidden_and_width(kw: dict) -> Iterable[tuple[str, str]]:
    if "hidden" in kw and ("width" in kw or "depth" in kw):
        yield "hidden", "give either hidden or width and depth, not both (width/depth win)"


SURROGATE_FIXED = Keywords(
    SURROGATE_HYPERPARAMETERS,
    "NeuralSurrogate",
    refused=_SURROGATE_REFUSED,
    cross=_no_hidden_and_width,
)
INVERSE_FIXED = Keywords(
    INVERSE_HYPERPARAMETERS, "InverseModel", refused=_INVERSE_REFUSED, cross=_no_hidden_and_width
)


# ------------------------------------------------------------------ calibrator options
def _pgd_cross(kw: dict) -> Iterable[tuple[str, str]]:
    if kw.get("n_starts", 8) + kw.get("n_random_starts", 0) < 1:
        yield "n_starts", "n_starts + n_random_starts must be >= 1 (starts per specimen)"


#: The ga calibrator's defaults that the population check relies on.
GA_DEFAULTS = {"population": 20, "n_selected": 6, "n_crossover": 4, "n_mutation": 4}


def _ga_cross(kw: dict) -> Iterable[tuple[str, str]]:
    v = {**GA_DEFAULTS, "n_immigrants": 6, **kw}
    total = v["n_selected"] + v["n_crossover"] + v["n_mutation"] + v["n_immigrants"]
    if total != v["population"]:
        yield (
            "population",
            f"n_selected + n_crossover + n_mutation + n_immigrants = {v['n_selected']} + "
            f"{v['n_crossover']} + {v['n_mutation']} + {v['n_immigrants']} = {total} must equal "
            f"population = {v['population']} (defaults 6 + 4 + 4 + 6 = 20)",
        )
    if v["n_crossover"] > 0 and v["n_selected"] < 2:
        yield "n_selected", "crossover needs n_selected >= 2 (or n_crossover: 0)"


_RNG = {"rng": "set calibrate.seed"}  # every calibrator takes its seed from calibrate.seed

#: Keyword options of each calibrator (calibrate.options.<method>): name -> (check, doc).
CALIBRATOR_OPTIONS: dict[str, Keywords] = {
    "pgd": Keywords(
        {
            "optimizer": (Choice(("gauss-newton", "adam", "lbfgsb")), "the local optimiser"),
            "n_starts": (Int(0), "starts per specimen from the nearest bank entries"),
            "n_random_starts": (Int(0), "additional uniform random starts per specimen"),
            "n_bank_uniform": (Int(0), "uniform draws added to the start bank"),
            "max_iter": (Int(1), "Gauss-Newton iterations (L-BFGS-B's iteration cap)"),
            "keep_after": (Int(0), "successive halving: iterations before keeping the best"),
            "keep": (Int(0), "starts per specimen kept after keep_after (0 = all)"),
            "jacobian_members": (Int(0), "ensemble members of the early Jacobian (0 = exact)"),
            "exact_final": (Int(0), "last iterations with the exact Jacobian"),
            "tol": (Float(0, lo_open=True), "relative loss decrease that counts as converged"),
            "loss": (Choice(("l2", "l1")), "weighted squared or absolute error"),
            "select": (Choice(("mae", "r2")), "how the best start of a specimen is chosen"),
            "steps": (Int(0), "Adam's steps"),
            "lr": (Float(0, lo_open=True), "Adam's learning rate (unit coordinates)"),
            "noise_deg": (
                Float(0, lo_open=True),
                "error scale of one RoM value in degrees (default: the surrogate's error)",
            ),
            "fit_tolerance": (Float(0), "stop a start below fit_tolerance * noise_deg RMS"),
            "range_z": (Float(0, lo_open=True), "half-width of the ranges in sd"),
            "ranges": (Bool(), "compute the identifiability ranges"),
            "effect_levels": (
                ListOf(Float(0, 1), min_len=1),
                "unit-box levels of the start grid over each effect's parameters",
            ),
            "effect_bank_starts": (
                Int(0),
                "effect models: starts from the nearest disc-and-effect combinations",
            ),
            "effect_bank_samples": (Int(1), "disc-and-effect combinations drawn for those"),
            "effect_shape_starts": (
                Int(0),
                "effect models: Sobol starts over each effect's parameters, shape included",
            ),
            "effect_rounds": (
                Int(1),
                "effect models: rounds of starts (the second adds effects to the first's best)",
            ),
            "effect_keep": (
                Int(0),
                "effect models: starts per specimen kept after keep_after iterations (0: all)",
            ),
            "effect_max_iter": (
                Int(1),
                "effect models: Gauss-Newton iterations once effects join (max_iter: the disc)",
            ),
            "retry_alpha": (
                Float(0, 1, hi_open=True),
                "with a noise_deg: fit again from 4x the starts every specimen left beyond the "
                "noise (chi-square p below this; 0: off)",
            ),
        },
        "pgd calibrator",
        refused={
            "start_bank": "set calibrate.start_bank (a prepared table whose configurations "
            "are the starts)",
            **_RNG,
        },
        cross=_pgd_cross,
    ),
    "pgd-study": Keywords(
        {
            "n_starts": (Int(1), "random starts per specimen (the study's 500)"),
            "steps": (Int(0), "optimisation steps (the study's 2250)"),
            "lr": (Float(0, lo_open=True), "learning rate in the unit box (the study's 0.0971)"),
            "loss": (Choice(("l1", "l2")), "row loss (the study: l1)"),
            "projection": (Choice(("clip", "average")), "the study's projection or averaging"),
            "bounds_penalty": (Float(0), "weight of the bounds penalty (0 = off)"),
            "optimizer": (Choice(("adam", "lbfgs")), "Adam (the study) or torch's L-BFGS"),
            "select": (Choice(("r2", "mae")), "best start by mean R² or by MAE"),
        },
        "pgd-study calibrator",
        refused=_RNG,
    ),
    "ga": Keywords(
        {
            "population": (Int(1), "individuals per specimen and generation (study: 20)"),
            "n_selected": (Int(1), "best individuals kept as parents (study: 6)"),
            "n_crossover": (Int(0), "crossover children per generation (study: 4)"),
            "n_mutation": (Int(0), "mutated copies per generation (study: 4)"),
            "n_immigrants": (Int(0), "uniform random individuals per generation (study: 6)"),
            "restart_every": (Int(1), "generations between restarts (study: 10)"),
            "max_generations": (Int(1), "generations at most (study: 120)"),
            "target_r2": (Float(hi=1), "stop a specimen once its best mean R² reaches this"),
            "fitness": (Choice(("r2", "mae")), "ranking of the individuals"),
        },
        "ga calibrator",
        refused=_RNG,
        cross=_ga_cross,
    ),
    "inverse": Keywords(
        {"model_uri": (MODEL_URI, "the registered inverse model (train-inverse)")},
        "inverse calibrator",
        refused={
            "model": "give model_uri (a registered inverse model)",
            **_RNG,
        },
    ),
}

# ------------------------------------------------------------------ FE adapter settings
#: Fields of the disc geometry (femcal.fe.geometry.DiscGeometry), plus ``preset``.
GEOMETRY_FIELDS: dict[str, tuple[Check, str]] = {
    "preset": (Choice(MESH_PRESETS), "mesh density the other fields start from"),
    "width_mm": (Float(0, lo_open=True), "lateral axis of the ellipse, mm"),
    "depth_mm": (Float(0, lo_open=True), "anterior-posterior axis of the ellipse, mm"),
    "height_mm": (Float(0, lo_open=True), "disc height, mm"),
    "nucleus_fraction": (Float(0, 1, lo_open=True, hi_open=True), "nucleus volume fraction"),
    "n_rings": (Int(1), "annulus rings (material layers)"),
    "n_regions": (Int(3), "circumferential annulus regions per side"),
    "elements_per_region": (Int(1), "elements along the circumference per region"),
    "elements_per_ring": (Int(1), "elements across each annulus ring"),
    "elements_core": (Int(1), "elements between the nucleus block and its boundary"),
    "elements_height": (Int(1), "elements through the disc height"),
    "core_size": (Float(0, 1, lo_open=True, hi_open=True), "nucleus block corner radius"),
    "reference_height_mm": (Float(), "load reference point above the disc centre, mm"),
}
_GEOMETRY = Keywords(GEOMETRY_FIELDS, "DiscGeometry")


def _geometry(value: Any, path: tuple, ctx: Context) -> Any:
    if isinstance(value, str):
        return Choice(MESH_PRESETS)(value, path, ctx)
    if isinstance(value, Mapping):
        return _GEOMETRY(value, path, ctx)
    raise Invalid(
        f"expected a mesh preset ({', '.join(MESH_PRESETS)}) or a mapping of DiscGeometry "
        f"fields, got {got(value)}"
    )


#: Keyword arguments of each FE solver adapter (fe.settings).
SOLVER_SETTINGS: dict[str, Keywords] = {
    "calculix": Keywords(
        {
            "geometry": (
                FnCheck("a mesh preset or a mapping of DiscGeometry fields", _geometry),
                "disc geometry: a mesh preset (coarse, default, fine) or DiscGeometry fields",
            ),
            "kappa": (Choice(("scale", "ignore")), "how the fibre dispersion Kappa enters"),
            "executable": (NAME, "the CalculiX executable"),
            "initial_increment": (Float(0, 1, lo_open=True), "first load increment"),
            "max_attempts": (Int(1), "attempts per job (retries of a fibre-routine abort)"),
            "timeout_s": (Nullable(Float(0, lo_open=True)), "seconds per attempt (null = none)"),
            "max_increments": (Int(1), "load increments at most"),
            "retry_factor": (Float(0, 1, lo_open=True), "increment factor of a retry"),
            "nucleus_d1": (Float(0, lo_open=True), "compressibility of the nucleus"),
            "annulus_d1": (Float(0, lo_open=True), "compressibility of the annulus"),
        },
        "CalculixDisc",
    ),
}
