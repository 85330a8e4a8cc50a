"""The sections only ``fe/params.yaml`` has: the FE campaign (``fe``) and ``validate``.

The adapter's keyword arguments (``fe.settings``) depend on ``fe.solver``; they are checked
against :data:`~femcal.settings.keywords.SOLVER_SETTINGS` once both are known (see
:mod:`femcal.settings.params`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.settings._checks import Choice, Float, FnCheck, Int, KeyChoice, ListOf
from femcal.settings._messages import BAD, Context, Invalid, got, unknown_message, yaml_repr
from femcal.settings._validate import MapOf, Section, optional, setting
from femcal.settings.keywords import CALIBRATOR_OPTIONS, SOLVERS, SPLITS, SURROGATE_FIXED
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
