"""Stage ``validate`` (fe/dvc.yaml): calibrated parameters re-simulated in FE; the IDP check."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Unpack

import numpy as np

from femcal.config import settings_of
from femcal.errors import ConfigError
from femcal.fe.options import ValidateOptions
from femcal.fe.runtime import FeKeywords, FeRuntime
from femcal.paths import setting_path
from femcal.stages.common import (
    StageSettings,
    output_folder,
    path_setting,
    typed,
    write_metrics,
)
from femcal.stages.simulate import fe_runtime
from femcal.stages.store import tracking

#: The summary keys the stage's DVC metrics file holds.
METRICS_KEYS = (
    "n_specimens",
    "fe_fit_residual_deg",
    "fe_fit_residual_deg_before_refine",
    "target_noise_deg",
    "fe_predictive_mae_deg",
    "fe_predictive_mae_deg_noisy",
    "fe_predictive_idp_mae_mpa",
    "fe_predictive",
    "fe_runs_per_specimen_max",
    "fe_runs_per_specimen_max_validate",
    "fe_runs_per_specimen_adapt",
    "fe_runs_per_specimen_mean",
    "fe_mae_deg",
    "surrogate_mae_deg",
    "fe_vs_surrogate_mae_deg",
    "fe_mae_deg_per_load_case",
    "idp",
    "idp_published",
    "idp_head",
    "n_fe_failed_jobs",
)


@dataclass(frozen=True)
class ValidateSettings(StageSettings):
    """The ``validate`` and ``fe`` sections of fe/params.yaml, with the command line's overrides.

    :func:`run_validate` takes the FE runtime ``fe`` as its own keywords (solver, settings,
    store, ...; :meth:`call_args`).
    """

    calibration_dir: Path
    measurements: Path
    fe: FeRuntime
    forces: Sequence[float]
    literature: Mapping[str, Any]
    out_dir: Path
    model_uri: str | None = None
    refine: Mapping[str, Any] = field(default_factory=dict)
    published: Sequence[Mapping[str, Any]] = ()
    idp_model_uri: str | None = None
    target_noise_deg: float | None = None
    predictive_report: Path | None = None
    adapt_report: Path | None = None
    adapt_targets: Path | None = None

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> ValidateSettings:
        cfg = typed(params, "validate")
        out = output_folder(params, args, "validate")  # before the FE campaign
        refine = cfg.refine
        adapt = settings_of(params).adapt  # None without an adapt section
        return cls(
            calibration_dir=(
                Path(args["calibration"])
                if args.get("calibration")
                else path_setting(params, "validate", "calibration_dir")
            ),
            measurements=(
                Path(args["measurements"])
                if args.get("measurements")
                else path_setting(params, "validate", "measurements")
            ),
            fe=fe_runtime(params, args, "validate"),
            forces=list(cfg.forces),
            literature={force: r.model_dump() for force, r in cfg.idp_literature.items()},
            out_dir=out,
            metrics_file=args.get("metrics_file"),
            model_uri=refine.model_uri if refine else None,
            refine=refine.options() if refine else {},
            published=[p.model_dump() for p in cfg.idp_published],
            idp_model_uri=cfg.idp_model_uri,
            target_noise_deg=cfg.target_noise_deg,
            predictive_report=(
                setting_path(params, cfg.predictive_report) if cfg.predictive_report else None
            ),
            adapt_report=setting_path(params, cfg.adapt_report) if cfg.adapt_report else None,
            adapt_targets=setting_path(params, adapt.targets) if adapt else None,
            params=params,
        )

    def call_args(self) -> dict[str, Any]:
        """:func:`run_validate`'s keywords: the FE runtime's spread among the others (the
        reports of the other stages are read by :func:`run`)."""
        args = super().call_args()
        for key in ("target_noise_deg", "predictive_report", "adapt_report", "adapt_targets"):
            args.pop(key)
        return {**args.pop("fe").keywords(), **args}


def _read_report(path: Path | None, what: str) -> dict[str, Any] | None:
    """The JSON figures of another stage, or None when ``path`` is None: every figure, from
    the plain output beside its DVC metrics file (:func:`femcal.dvc_metrics.details_path`)
    when there is one."""
    from femcal.dvc_metrics import details_path

    if path is None:
        return None
    if details_path(path).is_file():
        path = details_path(path)
    if not path.is_file():
        raise ConfigError(
            f"validate.{what}: {path} does not exist. Run its stage first (dvc repro runs it "
            f"before validate), or set validate.{what}: null in params.yaml."
        )
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(
            f"validate.{what}: {path} is not valid JSON ({exc}). Re-run its stage to rewrite it."
        ) from exc


def honest_figures(
    summary: Mapping[str, Any],
    settings: ValidateSettings,
    predictive: Mapping[str, Any] | None,
    adapt: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """What the validation measures, each under its own name.

    ``fe_fit_residual_deg`` is in-sample (the calibration saw the curves scored);
    ``fe_predictive_mae_deg`` (and ``_noisy``) come from the predict stage: FE at parameters
    calibrated on the lower moments, scored at the upper ones the calibration never saw.
    ``fe_runs_per_specimen_max`` counts every FE run aimed at a specimen: the adapt stage's
    rounds when its targets are the specimens validated, plus the validation's own runs.

    Parameters
    ----------
    summary : mapping
        :attr:`ValidationResult.summary`.
    settings : ValidateSettings
        The stage's settings (the measurements validated, the adapt stage's targets).
    predictive, adapt : mapping or None
        The predict and adapt stages' figures (:func:`_read_report`), None when not given.

    Returns
    -------
    dict
        The keys above, ``target_noise_deg``, ``fe_predictive_idp_mae_mpa`` (FE's IDP under
        the moments at the predict stage's calibrated parameters, never fitted),
        ``fe_runs_per_specimen_max_validate``, ``fe_runs_per_specimen_adapt`` and
        ``fe_predictive`` (the predict stage's figures).
    """
    same = (
        adapt is not None
        and settings.adapt_targets is not None
        and settings.adapt_targets.resolve() == settings.measurements.resolve()
    )
    adapt_runs = int(adapt["n_rounds"]) if same else 0
    pred = predictive or {}
    return {
        "target_noise_deg": settings.target_noise_deg,
        "fe_predictive_mae_deg": pred.get("fe_predictive_mae_deg"),
        "fe_predictive_mae_deg_noisy": pred.get("fe_predictive_mae_deg_noisy"),
        "fe_predictive_idp_mae_mpa": (pred.get("clean") or {}).get("idp_mae_mpa"),
        "fe_predictive": predictive,
        "fe_runs_per_specimen_max_validate": summary["fe_runs_per_specimen_max"],
        "fe_runs_per_specimen_adapt": adapt_runs,
        "fe_runs_per_specimen_max": summary["fe_runs_per_specimen_max"] + adapt_runs,
    }


def run(settings: ValidateSettings) -> dict[str, Any]:
    """Re-simulate and compare; returns the validation summary."""
    from femcal.fe.validate import json_safe

    tracking(settings.params)
    predictive = _read_report(settings.predictive_report, "predictive_report")  # before FE
    adapt = _read_report(settings.adapt_report, "adapt_report")
    result = run_validate(**settings.call_args())
    s = {**result.summary, **honest_figures(result.summary, settings, predictive, adapt)}
    # only when asked (the DVC stage)
    # the headline; every figure of METRICS_KEYS in its details file (details_path)
    figures = json_safe({k: s[k] for k in METRICS_KEYS})
    write_metrics(settings.metrics_file, figures, "validate", details=True)
    return {"summary": s, "out": str(settings.out_dir)}


def describe(figures: Mapping[str, Any]) -> list[str]:
    s, out = figures["summary"], figures["out"]
    lines = []
    if s.get("refine"):
        r = s["refine"]
        lines.append(
            f"refined with FE in the loop: FE-evaluated MAE {r['fe_mae_deg_start']:.4f} -> "
            f"{r['fe_confirmed_mae_deg']:.4f} deg, {r['n_confirmed']}/{r['n_specimens']} "
            f"within {r['tol_deg']:g} deg, {r['fe_runs_per_specimen_max']} FE runs per "
            f"specimen at most ({r['fe_runs_per_specimen_mean']:.1f} on average)"
        )
    lines += [
        f"validated {s['n_specimens']} calibrated specimens with the FE model: MAE vs the "
        f"measurement {s['fe_mae_deg']:.4f} deg through FE, {s['surrogate_mae_deg']:.4f} deg "
        f"through the surrogate (FE vs surrogate {s['fe_vs_surrogate_mae_deg']:.4f} deg); "
        f"{s['n_fe_failed_jobs']} FE jobs failed"
    ]
    for row in s["idp"]:
        lit = row["literature"]
        verdict = (
            f", {row['n_in_range']}/{s['n_specimens']} in the literature range "
            f"[{lit['low_mpa']:g}, {lit['high_mpa']:g}] MPa"
            if lit
            else ""
        )
        lines.append(
            f"  IDP at {row['force_n']:g} N: {row['idp_mpa_min']:.3f}-{row['idp_mpa_max']:.3f} "
            f"MPa{verdict}"
        )
    for row in s.get("idp_published") or []:
        where = (
            f"at {row['force_n_min']:.0f}-{row['force_n_max']:.0f} N (median "
            f"{row['force_n_median']:.0f} N)"
            if row["n_reached"]
            else "by none"
        )
        beyond = (
            f"; {row['n_beyond']} stay below it up to {row['max_force_n']:g} N"
            if row["n_beyond"]
            else ""
        )
        lines.append(
            f"  {row['idp_mpa']:g} MPa, {row['condition']} ({row['kind']}, {row['source']}): "
            f"reached {where}{beyond}"
        )
    if s.get("idp_head"):
        h = s["idp_head"]
        lines.append(
            f"IDP head vs FE under the moments: MAE {h['mae_mpa']:.4f} MPa over {h['n_points']} "
            f"points (FE pressures {h['fe_idp_mpa_min']:.3f}..{h['fe_idp_mpa_max']:.3f} MPa)"
        )
    extra = f", {out}/refine.csv" if s.get("refine") else ""
    lines.append(f"outputs: {out}/validation.csv, {out}/validation.json, {out}/idp.csv{extra}")
    return lines


def run_validate(
    *,
    calibration_dir: Path,
    measurements: Path,
    forces: Sequence[float],
    literature: Mapping[Any, Any],
    out_dir: Path,
    model_uri: str | None = None,
    refine: Mapping[str, Any] | None = None,
    published: Sequence[Mapping[str, Any]] = (),
    idp_model_uri: str | None = None,
    **fe: Unpack[FeKeywords],
):
    """FE re-simulation of a calibration (the study's step 4); tables in ``out_dir``; MLflow.

    ``fe`` is the FE runtime's keywords (``solver``, ``settings``, ``store``,
    ``scheduler_address``, ``n_workers``, ``progress``; :meth:`FeRuntime.keywords`); the
    runtime they make and a :class:`~femcal.fe.options.ValidateOptions` of the forces, the
    literature, the published pressures and the refinement's budget ``refine``
    (``max_fe_runs``, ``tol_deg``; None: the defaults) go to
    :func:`femcal.fe.validate.validate_calibration`. With ``max_fe_runs > 1`` the
    calibration is first refined with FE in the loop, steered by the surrogate at
    ``model_uri`` (a model folder or a models:/ URI). ``published`` are the published
    pressures without a known force (``validate.idp_published``); ``idp_model_uri`` the IDP
    head compared with FE under the moments (None: not compared).

    Returns
    -------
    ValidationResult
        See :func:`femcal.fe.validate.validate_calibration`. ``out_dir`` is all or nothing,
        as for :func:`femcal.jobs.calibrate.run_calibration` (:mod:`femcal.outputs`).
    """
    from femcal.outputs import check_destination, staged_output

    check_destination(out_dir)  # before the FE campaign
    import mlflow

    from femcal.fe.idp import published_values
    from femcal.fe.validate import literature_ranges, validate_calibration

    ranges = literature_ranges(literature)
    values = published_values(published)
    options = ValidateOptions(forces=forces, literature=ranges, published=values, **(refine or {}))
    max_fe_runs = options.max_fe_runs
    idp_head = None
    if idp_model_uri:
        from femcal.tracking import load_surrogate, open_model

        idp_head = load_surrogate(open_model(idp_model_uri))
    surrogate = None
    if max_fe_runs > 1:
        if not model_uri:
            raise ConfigError(
                f"validate.refine.max_fe_runs is {max_fe_runs}: FE-in-the-loop refinement "
                "needs validate.refine.model_uri (the surrogate calibrated with, e.g. "
                "models/surrogate-large); or set max_fe_runs: 1 to validate only."
            )
        from femcal.tracking import load_surrogate, open_model

        surrogate = load_surrogate(open_model(model_uri))
    # The FE campaign runs before the MLflow run starts (a bad input makes no FAILED run);
    # its tables are staged, and move into place inside the run that logs them.
    with staged_output(out_dir, command="validate") as stage:
        result = validate_calibration(
            calibration_dir,
            measurements,
            FeRuntime(**fe),
            stage.path,
            options,
            surrogate=surrogate,
            idp_head=idp_head,
        )
        s = result.summary
        with mlflow.start_run(run_name="validate") as run:
            stage.note(mlflow_run_id=run.info.run_id)
            mlflow.set_tag("femcal.stage", "validate")
            mlflow.log_params(
                {
                    "calibration_dir": str(calibration_dir),
                    "measurements": str(measurements),
                    "solver": fe["solver"],
                    "settings": json.dumps(dict(fe["settings"]), sort_keys=True)[:500],
                    "forces_n": ",".join(f"{f:g}" for f in forces),
                    "solver_versions": ",".join(s["solver_versions"]),
                    "n_specimens": s["n_specimens"],
                }
            )
            metrics = {
                "fe_mae_deg": s["fe_mae_deg"],
                "fe_fit_residual_deg": s["fe_fit_residual_deg"],
                "fe_fit_residual_deg_before_refine": s["fe_fit_residual_deg_before_refine"],
                "fe_runs_per_specimen_max": s["fe_runs_per_specimen_max"],
                "surrogate_mae_deg": s["surrogate_mae_deg"],
                "fe_vs_surrogate_mae_deg": s["fe_vs_surrogate_mae_deg"],
                "n_fe_failed_jobs": s["n_fe_failed_jobs"],
                "fe_cpu_seconds_total": s["fe_cpu_seconds_total"],
            }
            for lc, v in s["fe_mae_deg_per_load_case"].items():
                metrics[f"fe_mae_deg_{lc}"] = v
            for row in s["idp"]:
                metrics[f"idp_mpa_mean_{row['force_n']:g}N"] = row["idp_mpa_mean"]
                if row["n_in_range"] is not None:
                    metrics[f"idp_n_in_range_{row['force_n']:g}N"] = row["n_in_range"]
            for row in s["idp_published"]:
                key = "".join(c if c.isalnum() else "_" for c in row["condition"])
                metrics[f"idp_implied_force_n_median_{key}"] = row["force_n_median"]
            if s["idp_head"]:
                metrics["idp_head_mae_mpa"] = s["idp_head"]["mae_mpa"]
            mlflow.log_metrics({k: float(v) for k, v in metrics.items() if np.isfinite(float(v))})
            mlflow.log_table(result.table, artifact_file="tables/validation.json")
            stage.finalize()
            mlflow.log_artifacts(str(stage.path), artifact_path="validation")  # this run's files
            stage.commit()
    return result
