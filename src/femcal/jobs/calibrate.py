"""Calibrate every specimen of a measurement file against a surrogate: :func:`run_calibration`.

:class:`CalibrationJob` holds what one calibration needs (the file, the output folder, the
calibrator and its options, the surrogates, the moment policy, the effects, the noise);
:meth:`CalibrationJob.from_params` fills it from a loaded params.yaml (``calibrate`` and
``moments``). ``femcal calibrate`` (:mod:`femcal.stages.calibrate`) builds one from the
command line and calls :func:`run_calibration`; so can any caller::

    from femcal.config import load_params
    from femcal.jobs.calibrate import CalibrationJob, run_calibration

    job = CalibrationJob.from_params(
        load_params("params.yaml"), measurements=Path("data/raw/Test"), out_dir=Path("out")
    )
    result, figures = run_calibration(job)
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.config import settings_of
from femcal.datasets import training_configurations
from femcal.jobs.common import moment_policy, with_given
from femcal.jobs.mlflow_steps import (
    LocalTracking,
    Tracker,
    end_calibration_run,
    log_artifacts,
    log_calibration,
    start_calibration_run,
)
from femcal.paths import setting_path, setting_uri

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationJob:
    """One calibration of a measurement file (:func:`run_calibration`).

    Attributes
    ----------
    measurements : Path
        The measurement file or folder (:func:`femcal.measurements.read_measurements`).
    out_dir : Path
        The output folder, written all or nothing (:mod:`femcal.outputs`).
    method : str
        The calibrator (``pgd``, ``pgd-study``, ``ga``, ``inverse`` or a plugin's name).
    model_uri : str
        The surrogate: a model folder or an MLflow model URI.
    holdout_uri : str or None
        The held-out surrogate that re-evaluates the result (None: none).
    start_bank : Path or None
        A prepared split whose training configurations are pgd's starts.
    options : mapping
        The calibrator's keywords (params.yaml ``calibrate.options.<method>``).
    seed : int
        The calibrator's seed.
    error_growth, max_log_ratio : tuple of float
        The moment policy, ``(below, above)`` each (:class:`femcal.moments.MomentPolicy`).
    chunk_size : int or None
        Specimens per calibration batch (None: all at once).
    plots : str
        ``all``, ``summary`` or ``none`` (:func:`femcal.calibration.report.plot_mode`).
    max_plots : int or None
        The most per-specimen figures drawn.
    progress : bool
        Progress bars on the terminal.
    effects : sequence of str
        The effect terms added to the disc (:mod:`femcal.effects.terms`).
    noise_deg : float or None
        The sd of one measurement, deg (None: the surrogate's error alone).
    noise_source : str
        Where ``noise_deg`` comes from (logged beside it).
    compare_to : str or None
        A run id or folder to compare with (None: the default baseline,
        :data:`femcal.compare.BASELINE_RULE`).
    """

    measurements: Path
    out_dir: Path
    method: str
    model_uri: str
    holdout_uri: str | None
    start_bank: Path | None
    options: Mapping[str, Any]
    seed: int
    error_growth: tuple[float, float]
    max_log_ratio: tuple[float, float]
    chunk_size: int | None = None
    plots: str = "all"
    max_plots: int | None = None
    progress: bool = False
    effects: Sequence[str] = ()
    noise_deg: float | None = None
    noise_source: str = ""
    compare_to: str | None = None

    @classmethod
    def from_params(cls, params: Mapping[str, Any], **given: Any) -> CalibrationJob:
        """The job params.yaml's ``calibrate`` and ``moments`` sections describe, ``given`` winning.

        Parameters
        ----------
        params : mapping
            A loaded params.yaml (:func:`femcal.config.load_params`); relative paths are under
            its folder.
        **given
            Fields of :class:`CalibrationJob`: ``measurements`` and ``out_dir`` always (the
            file has no default for them), any other to override the file.

        Returns
        -------
        CalibrationJob

        Raises
        ------
        ConfigError
            A key of ``given`` is not a field (:func:`femcal.jobs.common.with_given`).
        """
        settings = settings_of(params)
        cfg = settings.require("calibrate")
        method = given.get("method", cfg.method)
        options = cfg.method_options(method)
        if isinstance(options.get("model_uri"), str):  # the inverse network's folder or URI
            options["model_uri"] = setting_uri(params, options["model_uri"])
        fields = {
            "method": method,
            "model_uri": setting_uri(params, cfg.model_uri),
            "holdout_uri": setting_uri(params, cfg.holdout_uri) if cfg.holdout_uri else None,
            "start_bank": setting_path(params, cfg.start_bank) if cfg.start_bank else None,
            "options": options,
            "seed": cfg.seed,
            **moment_policy(params),
            "chunk_size": cfg.chunk_size,
            "plots": "all" if cfg.plots else "none",
            "max_plots": cfg.max_plots,
        }
        return cls(**with_given(cls, fields, given))


def run_calibration(job: CalibrationJob, *, tracker: Tracker | None = None):
    """Calibrate every specimen of a measurement file against the registered surrogate.

    ``job`` (:class:`CalibrationJob`): the file, the output folder, the method, its
    options, the surrogates, the start bank, the seed, the moment policy, effects and noise.

    ``plots``: "all" (True) writes the per-specimen PNGs and the summary page, "summary" the
    summary page only, "none" (False) no figure
    (:func:`femcal.calibration.report.write_outputs`). The time of each phase (reading and
    loading, calibration, outputs, MLflow logging) is logged at DEBUG level (``femcal -v``).

    ``effects`` lists physical effects (:mod:`femcal.effects`) added to the disc: their
    parameters are calibrated jointly with the material parameters.

    ``noise_deg`` is the sd of one measurement in degrees (params.yaml
    ``calibrate.datasets.<name>.noise_deg``, ``--noise-deg``): each point then weighs its
    inverse variance ``noise^2 / w + sd(M)^2`` (``w`` its weight, the mean of ``w`` repeats;
    the surrogate's error sd(M) is not averaged by repeats), as in ``femcal diagnose``, and
    pgd's ranges count each specimen's own sd of a point of average weight (``hypot(noise,
    sd)`` for single measurements in the trained range; :attr:`femcal.calibration.base.
    CalibrationProblem.point_sd`); the option ``noise_deg`` logged is the file's average.
    None counts the surrogate's error alone, each point's weight scaling its inverse variance
    (:meth:`femcal.moments.MomentPolicy.point_weights`).

    Reads the measurements, loads the surrogate (and the held-out surrogate): a model folder
    (``models/surrogate-large``, the one ``dvc.lock`` pins) or an MLflow model URI. Screens the
    moments with the moment policy (:class:`femcal.moments.MomentPolicy` of ``error_growth``
    and ``max_log_ratio``, ``(below, above)`` each, params.yaml ``moments``): points beyond
    its limits are dropped with a warning and listed in ``out_dir/dropped_points.csv``
    (``n_dropped_points`` in the figures). Calibrates the batch with each point weighted by its
    inverse variance (the surrogate's error sd(M) at its moment, the measurement noise when
    given, the measurement's own weight), writes ``out_dir`` (see
    :func:`femcal.calibration.report.write_outputs`) and logs one MLflow run with the
    per-specimen tables and every output file as artifacts. The run's tags
    ``femcal.model.*`` and ``femcal.holdout.*`` name each surrogate: its URI, the SHA-256 of its
    files and its registered version when known (:class:`femcal.tracking.ModelSource`).
    ``tracker`` makes the MLflow calls: None (:class:`~femcal.jobs.mlflow_steps.LocalTracking`)
    in this process, in the store and experiment MLflow is pointed at; ``femcal calibrate``
    passes a :class:`femcal.stages.tracking_process.TrackingProcess`, which logs from a child
    process set up meanwhile.

    ``out_dir`` is all or nothing (:mod:`femcal.outputs`): it is checked before anything
    else, the files are written into a staging folder beside it, only those are logged to
    MLflow, and the folder moves into place when complete (an earlier femcal output there is
    moved aside; a folder with files femcal did not write is refused).

    Returns
    -------
    result : CalibrationResult
    figures : dict
        The summary figures (also in ``out_dir/summary.json``).
    """
    from femcal.outputs import check_destination

    s = job
    measurements, out_dir, method, model_uri = s.measurements, s.out_dir, s.method, s.model_uri
    holdout_uri, start_bank, seed, effects = s.holdout_uri, s.start_bank, s.seed, s.effects
    chunk_size, progress, noise_deg = s.chunk_size, s.progress, s.noise_deg
    check_destination(out_dir)  # a bad output folder is the first error, not the last
    tracker = LocalTracking() if tracker is None else tracker
    lap = _Laps()
    from femcal.calibration import calibrate
    from femcal.calibration.report import plot_mode
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.reachability import assess_reachability
    from femcal.tracking import is_local_model, load_surrogate, open_model

    plots = plot_mode(s.plots)  # a wrong value before the calibration
    meas = read_measurements(measurements, noise_deg=noise_deg)  # repeats checked against it
    if not all(is_local_model(uri) for uri in (model_uri, holdout_uri) if uri):
        tracker.use_store_here()  # models:/ URIs are resolved in the tracking store
    source = open_model(model_uri)
    surrogate = load_surrogate(source)
    policy = MomentPolicy.for_surrogate(
        surrogate, growth=s.error_growth, max_log_ratio=s.max_log_ratio
    )
    screened = policy.screen(meas)  # points beyond the measured limits dropped, with a warning
    meas = screened.measurements
    # (n, 4, m): relative inverse variances (noise^2 / w + sd(M)^2, or w / sd(M)^2 without noise)
    weight = policy.point_weights(meas.moments, meas.weight, noise_deg, meas.rom_deg)
    model = _curve_model(surrogate, meas.moments, effects)
    # Before the fit: can the model produce these curves at all? (raises or warns)
    reach = assess_reachability(
        meas, model, sigma_model=policy.sigma_surrogate(meas.moments), reference=start_bank
    )
    # the error scale of a point of average weight (pgd's ranges)
    point_sd = noise_deg and policy.average_sd(
        meas.moments, meas.weight, noise_deg, meas.mask(), meas.rom_deg
    )
    opts = calibration_options(
        method, s.options, surrogate=surrogate, start_bank=start_bank, point_sd_deg=point_sd
    )
    holdout_source = open_model(holdout_uri) if holdout_uri else None
    holdout = holdout_source and _curve_model(load_surrogate(holdout_source), meas.moments, effects)
    tracker.check()  # a tracking store that failed: its error before the calibration
    lap("imports, reading, models, reachability")
    result = calibrate(
        model,
        meas.rom_deg,
        specimens=meas.specimens,
        weight=weight,
        method=method,
        seed=seed,
        chunk_size=chunk_size,
        progress=progress,
        options=opts,
        # each specimen's own error scale for pgd's ranges: the weights are inverse variances
        weight_sd=None if noise_deg is None else policy.unit_sd(noise_deg),
    )
    lap("calibration")
    logged, tags = _run_record(s, meas, policy, opts, source, holdout_source)
    # Outputs staged beside out_dir (a kill leaves nothing at out_dir); the MLflow run covers
    # writing them, gets exactly the staged files, and the move into place happens inside it.
    outputs = (holdout, plots, reach, screened, lap, (surrogate, policy))
    figures = _write_and_log(s, result, tracker, (logged, tags), outputs=outputs)
    lap("MLflow logging")
    logger.debug("calibrate timings: %s", lap)
    return result, figures


class _Laps:
    """The seconds of each phase of a run: ``lap(name)`` ends one."""

    def __init__(self) -> None:
        self.clock, self.timings = time.perf_counter(), {}

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = round(now - self.clock, 3)
        self.clock = now

    def __str__(self) -> str:
        return ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items())


def _curve_model(surrogate: Any, moments: Any, effects: Sequence[str]) -> Any:
    """The surrogate's curves on the measured moments, with ``effects`` added when any."""
    from femcal.calibration import SurrogateCurveModel
    from femcal.effects.composite import EffectModel

    model = SurrogateCurveModel(surrogate, moments)
    return EffectModel(model, list(effects)) if effects else model


def _figure_curves(s: CalibrationJob, result: Any, plots: str, holdout: Any, models: tuple) -> Any:
    """The per-specimen figures' continuous curves (calibrated and held-out model) and the sd
    of one measurement (the noise and the surrogate's error), when those figures are drawn.
    ``models``: the surrogate and the moment policy."""
    if plots != "all":
        return None
    from femcal.calibration.plots import dense_curves

    (surrogate, policy), noise = models, s.noise_deg
    # the held-out surrogate of the held-out curve model (with effects or without)
    held = getattr(getattr(holdout, "base", holdout), "surrogate", None)
    return dense_curves(
        result,
        lambda m: _curve_model(surrogate, m, s.effects),
        holdout_at=None if held is None else (lambda m: _curve_model(held, m, s.effects)),
        sigma_at=None if noise is None else (lambda m: np.hypot(noise, policy.sigma_surrogate(m))),
        n=s.max_plots,
    )


def _run_record(
    s: CalibrationJob, meas: Any, policy: Any, opts: Mapping[str, Any], *sources: Any
) -> tuple[dict[str, Any], dict[str, str]]:
    """The MLflow run's params and tags: the settings, the options and both surrogates."""
    logged = {
        "method": s.method,
        "effects": ",".join(s.effects) or "none",
        "measurements": str(s.measurements),
        "n_specimens": meas.n_specimens,
        "moments": ",".join(f"{m:g}" for m in meas.moments),
        "model_uri": s.model_uri,
        "holdout_uri": s.holdout_uri or "",
        "seed": s.seed,
        "chunk_size": s.chunk_size or 0,
        **policy.as_params(),
        "noise_deg": "none" if s.noise_deg is None else s.noise_deg,
        "noise_source": s.noise_source or "none",
    }
    for key, value in opts.items():
        if key != "start_bank" and not hasattr(value, "predict"):
            logged[f"option.{key}"] = value
    if "start_bank" in opts:
        logged["option.start_bank"] = f"{s.start_bank} ({len(opts['start_bank'])} configs)"
    tags: dict[str, str] = {}
    for tag, src in zip(("model", "holdout"), sources):
        if src is not None:
            tags.update(src.tags(tag))
            if src.version:
                logged[f"{tag}_version"] = src.version
    missing = meas.missing_load_cases()
    if missing:
        tags["femcal.missing_load_cases"] = json.dumps(missing)[:5000]
    return logged, tags


def _write_and_log(
    s: CalibrationJob,
    result: Any,
    tracker: Tracker,
    record: tuple[dict[str, Any], dict[str, str]],
    outputs: tuple,
) -> dict[str, Any]:
    """Write the outputs into a staging folder inside one MLflow run, log them, move them
    into place (the run's tables and comparison are logged while the figures are drawn:
    :func:`~femcal.calibration.report.write_outputs`' ``before_figures``). ``outputs``: the
    held-out model, the plot mode, the reachability, the screened measurements, the timer,
    the surrogate and the moment policy (the figures' curves). Returns the summary figures."""
    from femcal.calibration.report import write_outputs
    from femcal.outputs import staged_output

    (logged, tags), (holdout, plots, reach, screened, lap, models) = record, outputs
    curves = _figure_curves(s, result, plots, holdout, models)
    label = "+".join([s.method, *s.effects])
    with staged_output(s.out_dir, command="calibrate") as stage:
        tracker.submit(start_calibration_run, run_name=f"calibrate-{label}")

        def log_tables(figures: dict[str, Any]) -> None:
            # the run's tables and comparison logged while the figures are drawn
            screened.write(stage.path)
            figures["n_dropped_points"] = len(screened.dropped)
            tracker.submit(
                log_calibration,
                tags=tags,
                params=logged,
                metrics={k: float(v) for k, v in figures.items() if isinstance(v, (int, float))},
                parameters=result.parameters_frame(),
                measurements=s.measurements,
                figures=dict(figures),
                out_dir=stage.path,
                compare_to=s.compare_to,
            )

        try:
            figures = write_outputs(
                result,
                stage.path,
                holdout=holdout,
                plots=plots,
                max_plots=s.max_plots,
                reachability=reach.notes(),
                progress=s.progress,
                curves=curves,
                before_figures=log_tables,
            )
            lap(f"outputs (tables, plots: {plots})")
            stage.note(mlflow_run_id=tracker.result(), seconds=figures["seconds"])
            compared = tracker.result()
            stage.finalize()
            tracker.call(
                log_artifacts, folder=stage.path, artifact_path="calibration", progress=s.progress
            )  # this run's files
            stage.commit()
        except BaseException:
            tracker.abort()  # the run ends FAILED (started or not)
            raise
        tracker.call(end_calibration_run, status="FINISHED")
    _log_comparison(compared, s.out_dir)
    figures["envelope_model"] = reach.envelope.model  # whose envelope was checked (describe)
    return figures


def _log_comparison(compared: Mapping[str, str], out_dir: Path) -> None:
    """Say what the run was compared with, naming ``comparison.md`` in its final folder."""
    if "none" in compared:
        logger.info(
            "No comparison.md: %s; --compare-to RUN_OR_FOLDER chooses one.", compared["none"]
        )
    else:
        logger.info(
            "Compared with %s (%s): %s",
            compared["source"],
            compared["chosen"],
            Path(out_dir) / "comparison.md",
        )


def calibration_options(
    method: str,
    options: Mapping[str, Any],
    *,
    surrogate: Any,
    start_bank: Path | None,
    point_sd_deg: float | None = None,
) -> dict[str, Any]:
    """A calibrator's options completed from the data and the surrogate.

    For ``pgd``: the training configurations of ``start_bank`` (a prepared split) as starts,
    and ``noise_deg`` (the error scale of a RoM value of average weight: its ranges, its
    near-optimal starts and its fit tolerance) from ``point_sd_deg`` when given (the
    measurement noise and the surrogate's error, :meth:`femcal.moments.MomentPolicy.
    average_sd`), else from the surrogate's validation error alone (for Gaussian errors
    sd = MAE * sqrt(pi / 2)).
    """
    opts = dict(options)
    if method == "pgd":
        if start_bank is not None and "start_bank" not in opts:
            opts["start_bank"] = training_configurations(start_bank)
        val = float(getattr(surrogate, "best_val_mae_deg_", float("nan")))
        scale = point_sd_deg if point_sd_deg is not None else val * float(np.sqrt(np.pi / 2))
        if "noise_deg" not in opts and np.isfinite(scale) and scale > 0:
            opts["noise_deg"] = float(scale)
    return opts
