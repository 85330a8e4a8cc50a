"""Stage ``diagnose``: where the disc model fails on a cohort, and which effect is missing.

The work is the library's :func:`femcal.jobs.diagnose.run_diagnosis`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from femcal.jobs.diagnose import ESTIMATED_NOISE, DiagnosisJob, run_diagnosis
from femcal.stages.common import (
    StageSettings,
    check_measurements,
    dropped_note,
    noise_setting,
    output_folder,
    path_setting,
    typed,
    write_metrics,
)
from femcal.stages.tracking_process import ImportCollector, TrackingProcess
from femcal.stages.user_effects import describe_user_effects, effect_modules, load_user_effects

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DiagnoseSettings(StageSettings, DiagnosisJob):
    """The ``diagnose`` and ``moments`` sections, and the command line's overrides.

    A :class:`~femcal.jobs.diagnose.DiagnosisJob` with the stage's own settings
    (:data:`~femcal.stages.common.STAGE_ONLY`). Built by :meth:`from_params`, which also checks
    the output folder, the metrics file and the measurement file before anything heavy is
    imported. ``options`` holds the keywords of :class:`femcal.diagnose.DiagnoseOptions` that
    params.yaml sets (its defaults apply to the others).
    """

    effect_modules: Sequence[Path] = ()

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
        given = {"model_uri": args["model_uri"]} if args.get("model_uri") else {}
        job = DiagnosisJob.from_params(
            params,
            measurements=measurements,
            out_dir=out,
            noise_deg=noise,
            noise_source=source or ESTIMATED_NOISE,
            **given,
        )
        return cls(
            **{f.name: getattr(job, f.name) for f in fields(DiagnosisJob)},
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

    MLflow (its imports, the store, the run) works in a child process started first
    (:class:`~femcal.stages.tracking_process.TrackingProcess`), beside the diagnosis' own
    imports and its work in this process before the diagnosis' workers start. Both import
    without the cyclic garbage collector (:class:`~femcal.stages.tracking_process.ImportCollector`):
    what the imports built is frozen before the workers fork, so neither they nor this process
    scan it again.

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
    with ImportCollector() as collector, TrackingProcess(settings.params) as tracker:
        _import_the_diagnosis()
        collector.resume()
        diag, summary = run_diagnosis(settings, tracker=tracker)
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


def _import_the_diagnosis() -> None:
    """Import what :func:`femcal.jobs.diagnose.run_diagnosis` runs in this process (torch,
    pandas, the search, the surrogate's loading, the reachability check, the outputs)."""
    import femcal.calibration  # noqa: F401
    import femcal.diagnose.report  # noqa: F401
    import femcal.diagnose.search  # noqa: F401
    import femcal.reachability  # noqa: F401
    import femcal.tracking  # noqa: F401


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
    check = diag.noise_check()
    if check and check["message"]:
        lines.append(check["message"])
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
