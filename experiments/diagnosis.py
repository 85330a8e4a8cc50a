"""The diagnosis benchmarks' shared harness: cohorts, setup, one diagnosis, verdicts.

Used by :mod:`experiments.bench_diagnose` and the benchmarks built on it
(:mod:`experiments.bench_next_measurement`, :mod:`experiments.bench_selection_ceiling`,
:mod:`experiments.bench_measurement_design`, :mod:`experiments.bench_postfit_error`).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from experiments.common import REPO
from experiments.hidden_cohorts import CLASSES as HIDDEN_CLASSES
from experiments.hidden_cohorts import (
    CRITERION_SEEDS,
    ELIMINATION_SEEDS,
    FRESH_SEEDS,
    HOLDOUT_SEEDS,
    POLISH_SEEDS,
    TUNING_SEEDS,
    expected_effects,
    make_hidden_cohort,
    stratified,
)
from femcal.calibration import SurrogateCurveModel
from femcal.config import load_params, section
from femcal.datasets import load_split, training_configurations
from femcal.diagnose import DiagnoseOptions, Diagnosis, diagnose
from femcal.diagnose.report import practical_next
from femcal.effects.planted import NONE, make_cohort
from femcal.jobs.calibrate import calibration_options
from femcal.tidy import wide_rom
from femcal.tracking import configure_tracking, load_surrogate, resolve_model_version

UNEXPLAINED = "unexplained"
#: The bars of bench_diagnose: (a) right, (b) none given an effect, (d) MAE ratio, (e) seconds.
BAR_RIGHT, BAR_NONE, BAR_RATIO, BAR_SECONDS = 0.90, 0.10, 1.5, 60.0


THREE_CLASSES = (NONE, "facet_contact", "ligament_tension", "neutral_zone")


#: The thorough calibration behind the ceiling (:func:`truth_preferred`): four times the
#: nearest starts, every effect start kept to the end, more rounds and iterations than the
#: diagnosis affords.
THOROUGH = {
    "n_starts": 32,
    "keep": 4,
    "max_iter": 40,
    "effect_keep": 0,
    "effect_rounds": 5,
    "effect_shape_starts": 32,
}


def three_class_cohort(seed: int, fe_moments, fe_rom, plant: dict[str, Any]) -> dict[str, Any]:
    """The closed-world cohort of issue 4 as plain arrays and truth."""
    c = make_cohort(
        fe_moments,
        fe_rom,
        classes=THREE_CLASSES,
        n_per_class=plant["n_per_class"],
        moments=plant["moments"],
        noise_deg=plant["noise_deg"],
        rng=np.random.default_rng(seed),
    )
    truth = c.truth.set_index("specimen").loc[c.specimens].reset_index()
    labels = truth["effect"].to_numpy(dtype=object)
    return {
        "kind": "three",
        "seed": seed,
        "classes": THREE_CLASSES,
        "specimens": list(c.specimens),
        "moments": np.asarray(c.moments, dtype=float),
        "rom_deg": c.rom_deg,
        "noise_deg": float(c.noise_deg),
        "labels": labels,
        "expected": [frozenset() if lab == NONE else frozenset([lab]) for lab in labels],
        "out_of_library": np.zeros(len(labels), dtype=bool),
        "protocol": np.array(["1-5 Nm x 0.5"] * len(labels), dtype=object),
        "truth": truth,
    }


def hidden_cohort(seed: int, fe_moments, fe_rom, noise_deg: float) -> dict[str, Any]:
    """An open-world cohort of :mod:`experiments.hidden_cohorts` as plain arrays and truth."""
    c = make_hidden_cohort(fe_moments, fe_rom, seed=seed, noise_deg=noise_deg)
    labels = c.labels.astype(object)
    return {
        "kind": "hidden",
        "seed": seed,
        "classes": HIDDEN_CLASSES,
        "specimens": list(c.specimens),
        "moments": c.moments,
        "rom_deg": c.rom_deg,
        "noise_deg": float(c.noise_deg),
        "labels": labels,
        "expected": [expected_effects(lab) for lab in labels],
        "out_of_library": labels == UNEXPLAINED,
        "protocol": c.truth["protocol"].to_numpy(dtype=object),
        "truth": c.truth,
        # each hidden component alone on the specimen's disc, with the specimen's own noise
        "alone_deg": c.component_clean_deg + (c.rom_deg - c.clean_deg)[:, None],
    }


def restrict(cohort: dict[str, Any], n: int | None) -> dict[str, Any]:
    """The cohort cut to ``n`` specimens taken in turn from each class (moments kept where
    any remaining specimen was measured)."""
    if n is None or n >= len(cohort["specimens"]):
        return cohort
    idx = stratified(cohort["labels"], n)
    out = dict(cohort)
    rom = cohort["rom_deg"][idx]
    keep = np.isfinite(rom).any(axis=(0, 1))
    out.update(
        specimens=[cohort["specimens"][i] for i in idx],
        rom_deg=rom[..., keep],
        moments=cohort["moments"][keep],
        labels=cohort["labels"][idx],
        expected=[cohort["expected"][i] for i in idx],
        out_of_library=cohort["out_of_library"][idx],
        protocol=cohort["protocol"][idx],
        truth=cohort["truth"].iloc[idx].reset_index(drop=True),
    )
    if "alone_deg" in cohort:
        out["alone_deg"] = cohort["alone_deg"][idx][..., keep]
    return out


def hidden_seeds(ap: argparse.ArgumentParser, text: str, holdout: bool) -> list[int]:
    """The ``--seeds`` of a benchmark; a held-out seed only with ``--holdout``."""
    seeds = [int(s) for s in text.split(",") if s.strip()]
    held = sorted(set(HOLDOUT_SEEDS) & set(seeds))
    if held and not holdout:
        ap.error(f"seed {held[0]} is a held-out cohort: run it with --holdout")
    return seeds


def setup(
    model_uri: str | None = None,
    options: dict[str, Any] | None = None,
    in_range: float | None = None,
) -> dict[str, Any]:
    """What every diagnosis of a benchmark cohort needs, as ``femcal diagnose`` sets it up
    from params.yaml: the surrogate (``model_uri``, default ``calibrate.model_uri``), its
    moment policy and error, the start bank, the diagnosis' settings (``options``: keywords
    of :func:`femcal.diagnose.diagnose` beyond them), the calibration options of the
    recalibrations, and the Test split's FE curves (``fe_moments``, ``fe_rom``) with the
    planted cohorts' settings (``plant``)."""
    params = load_params(REPO / "params.yaml")
    configure_tracking(store_dir=REPO / section(params, "mlflow", "store_dir"))
    modules = (params.get("effects") or {}).get("modules") or []
    if modules:
        from femcal.effects import load_effect_modules

        load_effect_modules([REPO / m for m in modules])
    model_uri = model_uri or section(params, "calibrate", "model_uri")
    surrogate = load_surrogate(model_uri)
    version = resolve_model_version(model_uri)
    val = float(getattr(surrogate, "best_val_mae_deg_", float("nan")))
    sur_err = val * float(np.sqrt(np.pi / 2)) if np.isfinite(val) else 0.0
    try:
        from femcal.moments import MomentPolicy
    except ImportError:  # a tree without the moment policy: one scalar surrogate error
        policy = None
    else:
        policy = MomentPolicy.for_surrogate(
            surrogate,
            growth=float(section(params, "moments", "error_growth")),
            max_log_ratio=float(section(params, "moments", "max_log_ratio")),
        )
    noise = float(section(params, "plant", "noise_deg"))
    weight_sd = None if policy is None else policy.unit_sd(noise)
    prepared = REPO / section(params, "data", "prepared_dir")
    test, _ = load_split(prepared, "test")
    _, fe_moments, fe_rom = wide_rom(test)
    bank_path = REPO / section(params, "calibrate", "start_bank")
    return {
        "surrogate": surrogate,
        "surrogate_name": f"{version['name']}/{version['version']}" if version else model_uri,
        "policy": policy,
        "sur_err": sur_err,
        "start_bank": training_configurations(bank_path),
        "candidates": section(params, "diagnose", "candidates"),
        "min_delta": float(section(params, "diagnose", "min_delta")),
        "options": dict(options or {}),
        "in_range": in_range,
        "cal_opts": calibration_options(
            "pgd",
            section(params, "calibrate", "options", "pgd"),
            surrogate=surrogate,
            start_bank=bank_path,
            point_sd_deg=weight_sd,
        ),
        # the error sd of a point of fit weight 1: one measurement inside the trained moments
        "weight_sd": weight_sd,
        "fe_moments": fe_moments,
        "fe_rom": fe_rom,
        "plant": {
            "n_per_class": section(params, "plant", "n_per_class"),
            "moments": [float(m) for m in section(params, "plant", "moments")],
            "noise_deg": section(params, "plant", "noise_deg"),
        },
    }


def named_effects_of(label: str) -> list[str]:
    """Registered effects of a model label (``facet_contact+neutral_zone``; ``none`` -> [])."""
    return [p for p in str(label).split("+") if p not in (NONE, UNEXPLAINED)]


def named_effects(s: Any) -> list[str]:
    """Registered effects a specimen's diagnosis names (``effects``; else parsed from the
    verdict, for diagnoses without that field)."""
    effects = getattr(s, "effects", None)
    if effects is not None:
        return [str(e) for e in effects]
    return named_effects_of(s.verdict)


def judge(verdict: str, named: Sequence[str], expected: frozenset[str], out_of_library: bool):
    """(right, right with an extra ``+unexplained``) for one specimen."""
    flagged = UNEXPLAINED in verdict.split("+")
    if out_of_library:
        return flagged and not named, False
    if not expected:
        return verdict == NONE, False
    right = set(named) == set(expected)
    return right, right and flagged


def run_diagnosis(cohort: dict[str, Any], ctx: dict[str, Any]):
    """``diagnose`` a cohort as ``femcal diagnose`` would; returns the diagnosis, its wall and
    CPU seconds, the curve model and the points' weights (the moment policy's)."""
    surrogate, policy = ctx["surrogate"], ctx["policy"]
    moments, rom = cohort["moments"], cohort["rom_deg"]
    model = SurrogateCurveModel(surrogate, moments)
    if policy is not None:
        sur_err = policy.sigma_surrogate(moments)
        if ctx.get("in_range") is not None:  # --surrogate-error-in-range
            sur_err = np.sqrt(ctx["in_range"] ** 2 + sur_err**2 - policy.error_deg**2)
        # As `femcal calibrate --noise-deg` weighs them: inverse variances noise^2 / w + sd(M)^2
        own = cohort.get("point_weight")
        own = np.ones(rom.shape) if own is None else own
        weight = policy.point_weights(moments, own, cohort["noise_deg"])
    else:
        sur_err, weight = ctx["sur_err"], None
    cpu0, t0 = time.process_time(), time.perf_counter()
    diag = diagnose(
        model,
        rom,
        specimens=cohort["specimens"],
        noise_deg=cohort["noise_deg"],
        surrogate_error_deg=sur_err,
        candidates=ctx["candidates"],
        start_bank=ctx["start_bank"],
        point_weight=cohort.get("point_weight"),
        moment_policy=policy,
        options=DiagnoseOptions(
            **{"min_delta": ctx["min_delta"], "seed": cohort["seed"], **ctx["options"]}
        ),
    )
    return diag, time.perf_counter() - t0, time.process_time() - cpu0, model, weight


def judge_cohort(cohort: dict[str, Any], diag: Diagnosis) -> dict[str, np.ndarray]:
    """Per specimen (arrays of shape (n,)): the verdict, the effects it names, whether it is
    right (and right with an extra ``+unexplained``), whether the specimen is a ``none`` one,
    and whether it is eligible for bar (a) (not ``none``, the disc alone misses by > 2σ)."""
    verdicts = np.array([s.verdict for s in diag.specimens], dtype=object)
    named = [named_effects(s) for s in diag.specimens]
    judged = [
        judge(v, nm, ex, ool)
        for v, nm, ex, ool in zip(verdicts, named, cohort["expected"], cohort["out_of_library"])
    ]
    base_mae = np.array([s.baseline_mae_deg for s in diag.specimens])
    is_none = cohort["labels"] == NONE
    # The rival that next_measurement names (None without a close one): the true model?
    rivals = [
        None if not s.next_measurement else s.next_measurement["between"][1] for s in diag.specimens
    ]
    rival_right = np.array(
        [
            r is not None and not ool and set(named_effects_of(r)) == set(ex)
            for r, ex, ool in zip(rivals, cohort["expected"], cohort["out_of_library"])
        ]
    )
    practical = np.array([practical_next(s) is not None for s in diag.specimens])
    return {
        "verdicts": verdicts,
        "named": named,
        "rivals": rivals,
        "rival_right": rival_right,
        "rival_practical": practical,
        "right": np.array([j[0] for j in judged]),
        "extra_unexplained": np.array([j[1] for j in judged]),
        "base_mae": base_mae,
        "is_none": is_none,
        "eligible": ~is_none & (base_mae > 2 * cohort["noise_deg"]),
    }


def rival_counts(j: dict[str, np.ndarray]) -> dict[str, int]:
    """Eligible specimens whose verdict is wrong but whose ``next_measurement`` names the true
    model as the rival (and within ``PRACTICAL_REPEATS`` measurements), and those right or so
    named: what the ranking tells a user beyond the verdict."""
    wrong = j["eligible"] & ~j["right"]
    return {
        "n_wrong_rival_right": int((wrong & j["rival_right"]).sum()),
        "n_wrong_rival_right_practical": int(
            (wrong & j["rival_right"] & j["rival_practical"]).sum()
        ),
        "n_right_or_rival_eligible": int((j["eligible"] & (j["right"] | j["rival_right"])).sum()),
    }


#: The hidden cohorts' report groups after the held-out ones, in order: seeds, label.
SEED_GROUPS = (
    (TUNING_SEEDS, "hidden, tuning"),
    (CRITERION_SEEDS, "hidden, criterion seeds (first run)"),
    (POLISH_SEEDS, "hidden, polish seeds (first run)"),
    (ELIMINATION_SEEDS, "hidden, elimination seeds (first run)"),
    (FRESH_SEEDS, "hidden, fresh (first run)"),
)


def cohort_name(r: dict[str, Any]) -> str:
    """A report row's cohort, e.g. ``hidden 67740 (held out)``."""
    return f"{r['kind']} {r['seed']}" + (" (held out)" if r["holdout"] else "")


def cohort_group(r: dict[str, Any]) -> str:
    if r["kind"] != "hidden":
        return f"{r['kind']}-class cohorts" if r["kind"] == "three" else r["kind"]
    if r["holdout"]:
        return "hidden, held out"
    labels = (label for seeds, label in SEED_GROUPS if r["seed"] in seeds)
    return next(labels, "hidden, other seeds")
