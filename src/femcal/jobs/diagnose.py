"""Diagnose every specimen of a measurement file: :func:`run_diagnosis`.

:class:`DiagnosisJob` holds what one diagnosis needs (the file, the output folder, the
surrogate, the noise, the candidate effects, the start bank, the moment policy, the search's
options); :meth:`DiagnosisJob.from_params` fills it from a loaded params.yaml (``diagnose``,
``calibrate.model_uri`` and ``calibrate.start_bank``, ``moments``). ``femcal diagnose``
(:mod:`femcal.stages.diagnose`) builds one from the command line and calls
:func:`run_diagnosis`; so can any caller::

    from femcal.config import load_params
    from femcal.jobs.diagnose import DiagnosisJob, run_diagnosis

    job = DiagnosisJob.from_params(load_params("params.yaml"), out_dir=Path("out"))
    diagnosis, summary = run_diagnosis(job)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from femcal.config import settings_of
from femcal.datasets import training_configurations
from femcal.jobs.common import moment_policy, with_given
from femcal.jobs.mlflow_steps import (
    LocalTracking,
    Tracker,
    end_calibration_run,
    log_artifacts,
    log_run,
    start_diagnosis_run,
)
from femcal.paths import setting_path, setting_uri

#: The noise source of a diagnosis without a given noise.
ESTIMATED_NOISE = "estimated from the disc-alone residuals"


@dataclass(frozen=True)
class DiagnosisJob:
    """One diagnosis of a measurement file (:func:`run_diagnosis`).

    Attributes
    ----------
    measurements : Path
        The measurement file or folder (:func:`femcal.measurements.read_measurements`).
    out_dir : Path
        The output folder, written all or nothing (:mod:`femcal.outputs`).
    model_uri : str
        The disc-only surrogate: a model folder or an MLflow model URI.
    noise_deg : float or None
        The sd of one measurement, deg (None: estimated from the disc-alone residuals).
    candidates : sequence of str or None
        The candidate effects (None: every registered effect).
    start_bank : Path or None
        A prepared split whose training configurations are the fits' starts.
    error_growth, max_log_ratio : tuple of float
        The moment policy, ``(below, above)`` each (:class:`femcal.moments.MomentPolicy`).
    options : mapping
        Keywords of :class:`femcal.diagnose.DiagnoseOptions` (its defaults for the others).
    plots : bool
        Draw the per-specimen figures.
    max_plots : int or None
        The most per-specimen figures drawn.
    noise_source : str
        Where ``noise_deg`` comes from (logged beside it).
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
    noise_source: str = ESTIMATED_NOISE

    @classmethod
    def from_params(cls, params: Mapping[str, Any], **given: Any) -> DiagnosisJob:
        """The job params.yaml describes (``diagnose``, ``calibrate.model_uri`` and
        ``calibrate.start_bank``, ``moments``), ``given`` winning.

        Parameters
        ----------
        params : mapping
            A loaded params.yaml (:func:`femcal.config.load_params`); relative paths are under
            its folder.
        **given
            Fields of :class:`DiagnosisJob`: ``out_dir`` always, any other to override the
            file. A ``noise_deg`` given without ``noise_source`` is the caller's.

        Returns
        -------
        DiagnosisJob

        Raises
        ------
        ConfigError
            A key of ``given`` is not a field (:func:`femcal.jobs.common.with_given`).
        """
        settings = settings_of(params)
        keys = () if "measurements" in given else ("measurements",)
        cfg, calibrate = settings.require("diagnose", *keys), settings.require("calibrate")
        if "measurements" not in given:
            given = {"measurements": setting_path(params, cfg.measurements), **given}
        fields = {
            "model_uri": setting_uri(params, calibrate.model_uri),
            "noise_deg": cfg.noise_deg,
            "noise_source": (
                ESTIMATED_NOISE
                if cfg.noise_deg is None
                else f"diagnose.noise_deg in {Path(params.get('_path', 'params.yaml')).resolve()}"
            ),
            "candidates": cfg.candidates,
            "start_bank": (
                setting_path(params, calibrate.start_bank) if calibrate.start_bank else None
            ),
            **moment_policy(params),
            "options": cfg.options(),
            "plots": cfg.plots,
            "max_plots": cfg.max_plots,
        }
        if given.get("noise_deg") is not None and "noise_source" not in given:
            fields["noise_source"] = "given by the caller"
        return cls(**with_given(cls, fields, given))


def run_diagnosis(job: DiagnosisJob, *, tracker: Tracker | None = None):
    """Diagnose every specimen of a measurement file; write DIR; log one MLflow run.

    ``job`` (:class:`DiagnosisJob`) names the measurements, the output folder, the
    surrogate, the noise, the candidate effects, the start bank, the moment policy and the
    :class:`~femcal.diagnose.DiagnoseOptions` keywords.

    The moments are screened with the moment policy (:class:`femcal.moments.MomentPolicy` of
    ``error_growth`` and ``max_log_ratio``, ``(below, above)`` each, params.yaml ``moments``):
    points beyond its limits are dropped with a warning and listed in
    ``out_dir/dropped_points.csv`` (``n_dropped_points`` in the returned summary). The
    surrogate's own error at each moment (shape (m,), larger beyond the trained range) is
    part of the noise.

    ``out_dir`` is all or nothing, as for :func:`femcal.jobs.calibrate.run_calibration`
    (:mod:`femcal.outputs`).
    ``model_uri`` is a model folder (``models/surrogate-large``) or an MLflow model URI; the
    run's tags ``femcal.model.*`` name it (URI, SHA-256 of its files, registered version).
    ``tracker`` makes the MLflow calls: None (:class:`~femcal.jobs.mlflow_steps.LocalTracking`)
    in this process, in the store and experiment MLflow is pointed at; ``femcal diagnose``
    passes a :class:`femcal.stages.tracking_process.TrackingProcess`, which logs from a child
    process set up meanwhile.
    """
    from femcal.outputs import check_destination

    s = job
    measurements, out_dir, model_uri, noise_deg = (
        s.measurements,
        s.out_dir,
        s.model_uri,
        s.noise_deg,
    )
    candidates, start_bank = s.candidates, s.start_bank
    check_destination(out_dir)  # a bad output folder is the first error, not the last
    tracker = LocalTracking() if tracker is None else tracker
    from femcal.calibration import SurrogateCurveModel
    from femcal.diagnose import DiagnoseOptions, diagnose
    from femcal.effects import available_effects
    from femcal.effects.composite import EffectModel
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.outputs import staged_output
    from femcal.reachability import assess_reachability
    from femcal.tracking import is_local_model, load_surrogate, open_model

    options = DiagnoseOptions(**s.options)
    meas = read_measurements(measurements, noise_deg=noise_deg)  # repeats checked against it
    if not is_local_model(model_uri):
        tracker.use_store_here()  # models:/ URIs are resolved in the tracking store
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
    tracker.check()  # a tracking store that failed: its error before the diagnosis
    with staged_output(out_dir, command="diagnose") as stage:
        with _figures_in_workers(s, meas, stage.path):
            diag = diagnose(
                SurrogateCurveModel(surrogate, meas.moments),
                meas.rom_deg,
                specimens=meas.specimens,
                noise_deg=noise_deg,
                surrogate_error_deg=policy.sigma_surrogate(meas.moments, meas.rom_deg),
                point_weight=meas.weight,
                candidates=candidates,
                start_bank=training_configurations(start_bank) if start_bank else None,
                moment_policy=policy,
                options=options,
            )
        tracker.submit(start_diagnosis_run, run_name="diagnose")
        try:
            summary = _write_and_log(s, diag, screened, (policy, options, source), stage, tracker)
        except BaseException:
            tracker.abort()  # the run ends FAILED (started or not)
            raise
        tracker.call(end_calibration_run, status="FINISHED")
    return diag, summary


def _figures_in_workers(job: DiagnosisJob, meas, folder: Path):
    """A context manager within which each worker process of the diagnosis draws its group's
    figures into ``folder/plots`` as soon as the group is diagnosed
    (:func:`femcal.diagnose.workers.each_group`, :func:`femcal.diagnose.report.draw_group`),
    while the other worker still diagnoses its own; one that does nothing without plots.
    ``meas``: the cohort's measurements (its specimens and RoM), the figures' names decided
    over the whole cohort here, before the groups are drawn."""
    import contextlib
    import functools

    from femcal.diagnose.report import draw_group, figure_paths
    from femcal.diagnose.workers import each_group

    if not job.plots:
        return contextlib.nullcontext()
    (folder / "plots").mkdir(exist_ok=True)
    return each_group(
        functools.partial(
            draw_group,
            measured=meas.rom_deg,
            paths=figure_paths(meas.specimens, folder / "plots"),
            n=job.max_plots,
        )
    )


def _write_and_log(
    job: DiagnosisJob, diag, screened, setup: tuple, stage, tracker: Tracker
) -> dict[str, Any]:
    """Write the diagnosis into the open output ``stage``, log it to the run ``tracker``
    started, and commit the stage; the summary (``summary.json``'s figures and
    ``n_dropped_points``). ``setup``: the moment policy, the search's options and the model's
    source."""
    from femcal.diagnose.report import drawn_figures, write_diagnosis

    (policy, options, source), s = setup, job
    summary = write_diagnosis(
        diag,
        screened.measurements.rom_deg,
        stage.path,
        plots=s.plots,
        max_plots=s.max_plots,
        # the figures the workers drew into the new staging folder
        drawn=drawn_figures(diag, stage.path / "plots") if s.plots else (),
    )
    screened.write(stage.path)
    summary = dict(summary, n_dropped_points=len(screened.dropped))
    tracker.submit(
        log_run,
        tags=source.tags("model"),
        params={
            "measurements": str(s.measurements),
            "model_uri": s.model_uri,
            "noise_deg": "estimated" if s.noise_deg is None else s.noise_deg,
            "noise_source": s.noise_source,
            "candidates": ",".join(s.candidates or []) or "all",
            "min_delta": options.min_delta,
            "alpha": options.alpha,
            "max_effects": options.max_effects,
            "cohort_verdict": diag.cohort_verdict(),
            **policy.as_params(),
        },
        metrics={
            "sigma_deg": diag.sigma_deg,
            "noise_deg": diag.noise_deg,
            "seconds": diag.seconds,
            **(
                {"median_final_chi2_per_dof": check["median_chi2_per_dof"]}
                if (check := diag.noise_check())
                else {}
            ),
            # MLflow metric names take no "+": one count per effect (and "unexplained"),
            # and one per verdict with "+" spelt "__".
            **{f"n_{k}": float(v) for k, v in diag.effect_counts().items()},
            **{f"n_verdict_{k.replace('+', '__')}": float(v) for k, v in diag.verdicts().items()},
        },
    )
    stage.note(mlflow_run_id=tracker.result(), seconds=diag.seconds)
    tracker.result()  # the tags, parameters and metrics logged
    stage.finalize()
    tracker.call(log_artifacts, folder=stage.path, artifact_path="diagnosis")  # the run's files
    stage.commit()
    return summary
