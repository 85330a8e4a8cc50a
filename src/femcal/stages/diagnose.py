"""Stage ``diagnose``: where the disc model fails on a cohort, and which effect is missing."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from femcal.datasets import training_configurations
from femcal.paths import setting_path, setting_uri
from femcal.stages.common import (
    ESTIMATED_NOISE,
    StageSettings,
    check_measurements,
    dropped_note,
    moment_policy,
    noise_setting,
    output_folder,
    path_setting,
    typed,
    write_metrics,
)
from femcal.stages.store import tracking
from femcal.stages.user_effects import describe_user_effects, effect_modules, load_user_effects

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DiagnoseSettings(StageSettings):
    """The ``diagnose`` and ``moments`` sections, and the command line's overrides.

    Built by :meth:`from_params`, which also checks the output folder, the metrics file and
    the measurement file before anything heavy is imported. ``options`` holds the keywords
    of :class:`femcal.diagnose.DiagnoseOptions` that params.yaml sets (its defaults apply to
    the others).
    """

    measurements: Path
    out_dir: Path
    model_uri: str
    noise_deg: float | None
    candidates: Sequence[str] | None
    start_bank: Path | None
    error_growth: tuple[float, float]
    max_log_ratio: tuple[float, float]
    options: Mapping[str, Any] = field(default_factory=dict)
    plots: bool = True
    max_plots: int | None = None
    effect_modules: Sequence[Path] = ()
    noise_source: str = ESTIMATED_NOISE

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> DiagnoseSettings:
        cfg = typed(params, "diagnose")
        noise, source = noise_setting(
            params, args.get("noise_deg"), cfg.noise_deg, "diagnose.noise_deg"
        )
        out = output_folder(params, args, "diagnose")  # before anything heavy is imported
        measurements = (
            Path(args["measurements"])
            if args.get("measurements")
            else path_setting(params, "diagnose", "measurements")
        )
        check_measurements(measurements)
        _warn_foreign_noise(params, measurements, noise, source)
        calibrate = typed(params, "calibrate")
        bank = calibrate.start_bank
        return cls(
            measurements=measurements,
            out_dir=out,
            model_uri=args.get("model_uri") or setting_uri(params, calibrate.model_uri),
            noise_deg=noise,
            noise_source=source or ESTIMATED_NOISE,
            candidates=cfg.candidates,
            start_bank=setting_path(params, bank) if bank else None,
            **moment_policy(params),
            options=cfg.options(),
            plots=cfg.plots,
            max_plots=cfg.max_plots,
            effect_modules=effect_modules(params, args.get("effects_module")),
            metrics_file=args.get("metrics_file"),
            params=params,
        )


def _warn_foreign_noise(
    params: Mapping[str, Any], measurements: Path, noise: float | None, source: str
) -> None:
    """Warn where params.yaml's ``diagnose.noise_deg`` is applied to another file than
    ``diagnose.measurements``, the file it was stated for."""
    if noise is None or source == "--noise-deg":
        return
    own = path_setting(params, "diagnose", "measurements")
    if own.resolve() == measurements.resolve():
        return
    logger.warning(
        "The measurement noise %g deg is %s, stated for %s, not for %s: give --noise-deg SD, "
        "the sd of one measurement of this file, or set diagnose.noise_deg: null to estimate "
        "it from the disc-alone residuals.",
        noise,
        source,
        own,
        measurements,
    )


def noise_line(diag: Any, source: str) -> str:
    """Where the diagnosis' measurement noise comes from: the value (with its uncertainty
    when estimated) and the source."""
    if source == ESTIMATED_NOISE:
        return (
            f"measurement noise {diag.noise_deg:.4f} ± {diag.noise_sd_deg:.4f} deg, {source} "
            "(pooled, the surrogate's share taken out; physics the disc lacks counts in it: "
            "give --noise-deg where the noise is known)"
        )
    return f"measurement noise {diag.noise_deg:g} deg: {source}"


def run(settings: DiagnoseSettings) -> dict[str, Any]:
    """Load the user's effects, diagnose, write the outputs and the DVC metrics (when asked).

    Returns ``summary.json``'s figures with the :class:`~femcal.diagnose.Diagnosis`.
    """
    from femcal.headlines import diagnosis_headline

    names = load_user_effects(settings.effect_modules)
    if settings.noise_deg is None:
        logger.info(
            "measurement noise: %s (--noise-deg or diagnose.noise_deg gives it)", ESTIMATED_NOISE
        )
    else:
        logger.info("measurement noise %g deg: %s", settings.noise_deg, settings.noise_source)
    tracking(settings.params)
    diag, summary = run_diagnose(settings)
    # Only when asked (the DVC stage): never ad hoc. The headline; summary.json holds all.
    write_metrics(settings.metrics_file, diagnosis_headline(summary))
    return dict(
        summary,
        out_dir=str(settings.out_dir),
        diagnosis=diag,
        user_effects=names,
        user_effect_paths=[str(p) for p in settings.effect_modules],
        noise_source=settings.noise_source,
    )


#: Specimens ``describe`` names with a practical next measurement (the rest are counted).
SHOWN = 5


def describe(figures: Mapping[str, Any]) -> list[str]:
    from femcal.diagnose.outside import cohort_note
    from femcal.diagnose.report import practical_next

    diag = figures["diagnosis"]
    lines = describe_user_effects(figures["user_effects"], figures["user_effect_paths"])
    lines.append(
        f"diagnosed {figures['n_specimens']} specimens in {diag.seconds:.1f} s (noise sigma "
        f"{diag.sigma_deg:.4f} deg): verdicts {diag.verdicts()}; cohort verdict "
        f"{diag.cohort_verdict()}"
    )
    lines.append(noise_line(diag, figures.get("noise_source", ESTIMATED_NOISE)))
    counts = diag.effect_counts()
    found = diag.found_effects()
    forms = diag.found_forms()
    if found:
        lines.append(
            f"effects found: {', '.join(f'{k} ({counts[k]})' for k in found)}; to add them, list "
            f"[{', '.join(forms)}] under calibrate.datasets.<name>.effects in params.yaml (and "
            f"noise_deg: {diag.noise_deg:.3g}, the noise counted here) and run `dvc repro` (or: "
            f"femcal calibrate --measurements FILE --effects {','.join(forms)} --noise-deg "
            f"{diag.noise_deg:.3g})"
        )
    close = [(sp.specimen, p) for sp in diag.specimens if (p := practical_next(sp)) is not None]
    if close:
        shown = "; ".join(
            f"{name}: {p['load_case']} at {p['moment_nm']:.2g} Nm, {p['repeats_to_settle']}x"
            for name, p in close[:SHOWN]
        )
        more = f" and {len(close) - SHOWN} more" if len(close) > SHOWN else ""
        lines.append(
            f"close calls a few measurements would settle: {shown}{more} (summary.md says "
            "between which models, plots/ marks the point)"
        )
    if figures.get("n_dropped_points"):
        lines.append(dropped_note(figures["n_dropped_points"], str(figures["out_dir"])))
    if counts.get("unexplained"):
        lines.append(
            f"unexplained: {counts['unexplained']} specimens are not explained within the noise "
            "by the disc and the registered effects; summary.md and plots/ describe what is "
            "missing (load cases, laxity or stiffening, from which moment, how large). Write "
            "it as an effect (docs/how-to/effect-plugin.md) and pass --effects-module FILE."
        )
    box = [s.outside_box for s in diag.specimens if s.outside_box and s.outside_box["named"]]
    if box:
        lines.append(cohort_note(box))
    return lines


def run_diagnose(settings: DiagnoseSettings):
    """Diagnose every specimen of a measurement file; write DIR; log one MLflow run.

    ``settings`` (:class:`DiagnoseSettings`) names the measurements, the output folder, the
    surrogate, the noise, the candidate effects, the start bank, the moment policy and the
    :class:`~femcal.diagnose.DiagnoseOptions` keywords.

    The moments are screened with the moment policy (:class:`femcal.moments.MomentPolicy` of
    ``error_growth`` and ``max_log_ratio``, ``(below, above)`` each, params.yaml ``moments``):
    points beyond its limits are dropped with a warning and listed in
    ``out_dir/dropped_points.csv`` (``n_dropped_points`` in the returned summary). The
    surrogate's own error at each moment (shape (m,), larger beyond the trained range) is
    part of the noise.

    ``out_dir`` is all or nothing, as for :func:`run_calibrate` (:mod:`femcal.outputs`).
    ``model_uri`` is a model folder (``models/surrogate-large``) or an MLflow model URI; the
    run's tags ``femcal.model.*`` name it (URI, SHA-256 of its files, registered version).
    """
    from femcal.outputs import check_destination

    s = settings
    measurements, out_dir, model_uri, noise_deg = (
        s.measurements,
        s.out_dir,
        s.model_uri,
        s.noise_deg,
    )
    candidates, start_bank = s.candidates, s.start_bank
    check_destination(out_dir)  # a bad output folder is the first error, not the last
    import mlflow

    from femcal.calibration import SurrogateCurveModel
    from femcal.diagnose import DiagnoseOptions, diagnose
    from femcal.diagnose.report import write_diagnosis
    from femcal.effects import available_effects
    from femcal.effects.composite import EffectModel
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.outputs import staged_output
    from femcal.reachability import assess_reachability
    from femcal.tracking import load_surrogate, open_model

    options = DiagnoseOptions(**s.options)
    meas = read_measurements(measurements, noise_deg=noise_deg)  # repeats checked against it
    source = open_model(model_uri)
    surrogate = load_surrogate(source)
    policy = MomentPolicy.for_surrogate(
        surrogate, growth=s.error_growth, max_log_ratio=s.max_log_ratio
    )
    screened = policy.screen(meas)  # points beyond the measured limits dropped, with a warning
    meas = screened.measurements
    # Before the fit: can the disc, with every candidate effect, produce these curves at all?
    assess_reachability(
        meas,
        EffectModel(
            SurrogateCurveModel(surrogate, meas.moments), list(candidates or available_effects())
        ),
        sigma_model=policy.sigma_surrogate(meas.moments),
        reference=start_bank,
        noise_deg=noise_deg,
    )
    diag = diagnose(
        SurrogateCurveModel(surrogate, meas.moments),
        meas.rom_deg,
        specimens=meas.specimens,
        noise_deg=noise_deg,
        surrogate_error_deg=policy.sigma_surrogate(meas.moments, meas.rom_deg),  # each point's
        point_weight=meas.weight,
        candidates=candidates,
        start_bank=training_configurations(start_bank) if start_bank else None,
        moment_policy=policy,
        options=options,
    )
    with (
        staged_output(out_dir, command="diagnose") as stage,
        mlflow.start_run(run_name="diagnose") as run,
    ):
        stage.note(mlflow_run_id=run.info.run_id)
        mlflow.set_tag("femcal.stage", "diagnose")
        mlflow.set_tags(source.tags("model"))
        summary = write_diagnosis(
            diag, meas.rom_deg, stage.path, plots=s.plots, max_plots=s.max_plots
        )
        screened.write(stage.path)
        summary = dict(summary, n_dropped_points=len(screened.dropped))
        mlflow.log_params(
            {
                "measurements": str(measurements),
                "model_uri": model_uri,
                "noise_deg": "estimated" if noise_deg is None else noise_deg,
                "noise_source": s.noise_source,
                "candidates": ",".join(candidates or []) or "all",
                "min_delta": options.min_delta,
                "alpha": options.alpha,
                "max_effects": options.max_effects,
                "cohort_verdict": diag.cohort_verdict(),
                **policy.as_params(),
            }
        )
        mlflow.log_metrics(
            {
                "sigma_deg": diag.sigma_deg,
                "noise_deg": diag.noise_deg,
                "seconds": diag.seconds,
                # MLflow metric names take no "+": one count per effect (and "unexplained"),
                # and one per verdict with "+" spelt "__".
                **{f"n_{k}": float(v) for k, v in diag.effect_counts().items()},
                **{
                    f"n_verdict_{k.replace('+', '__')}": float(v)
                    for k, v in diag.verdicts().items()
                },
            }
        )
        stage.finalize()
        mlflow.log_artifacts(str(stage.path), artifact_path="diagnosis")  # this run's files
        stage.commit()
    return diag, summary
