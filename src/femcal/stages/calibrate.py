"""Stage ``calibrate@<dataset>``: every specimen of a measurement file against the pinned surrogate.

The surrogate ``dvc.lock`` pins (``calibrate.model_uri``: ``models/surrogate-large``)
calibrates each ``calibrate.datasets`` entry, with the effects listed there; the held-out
surrogate re-evaluates the result. ``femcal calibrate`` outside DVC takes the same settings
with command-line overrides (another file, model, method, effects, output folder). The work is
the library's :func:`femcal.jobs.calibrate.run_calibration`.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from femcal.compare import check_compare_to
from femcal.errors import ConfigError
from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.paths import setting_path
from femcal.settings.keywords import CALIBRATORS
from femcal.stages.common import (
    StageSettings,
    check_measurements,
    dropped_note,
    noise_setting,
    output_folder,
    typed,
    write_metrics,
)
from femcal.stages.tracking_process import ImportCollector, TrackingProcess
from femcal.stages.user_effects import describe_user_effects, effect_modules, load_user_effects

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrateSettings(StageSettings, CalibrationJob):
    """The ``calibrate`` and ``moments`` sections, one dataset, and the command line's overrides.

    A :class:`~femcal.jobs.calibrate.CalibrationJob` with the stage's own settings
    (:data:`~femcal.stages.common.STAGE_ONLY`). Built by :meth:`from_params`, which also checks
    the output folder, the metrics file and the measurement file (the first errors, before
    anything heavy is imported).
    """

    effect_modules: Sequence[Path] = ()

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> CalibrateSettings:
        where = args.get("params") or params.get("_path", "params.yaml")
        cfg = typed(params, "calibrate")
        given: dict[str, Any] = {}  # the command line's values over params.yaml's
        if args.get("model_uri"):
            given["model_uri"] = args["model_uri"]
        if args.get("model_version") or args.get("model_alias"):
            name = typed(params, "mlflow").model_name
            ref = (
                f"/{args['model_version']}"
                if args.get("model_version")
                else f"@{args['model_alias']}"
            )
            given["model_uri"] = f"models:/{name}{ref}"
        if args.get("no_holdout"):
            given["holdout_uri"] = None
        elif args.get("holdout_uri"):
            given["holdout_uri"] = args["holdout_uri"]
        if cfg.method not in CALIBRATORS:  # --method and the other settings: merged in params
            plugin_options(cfg.method, cfg.method_options(cfg.method), where)
        dataset, measured = args.get("dataset"), args.get("measurements")
        if dataset and dataset not in cfg.datasets:
            raise ConfigError(
                f"Unknown dataset '{dataset}'; calibrate.datasets in {where} has "
                f"{sorted(cfg.datasets)}."
            )
        name = dataset or (None if measured else next(iter(cfg.datasets), None))
        if not measured and name is None:
            raise ConfigError(
                "Give --measurements FILE, or list calibrate.datasets in params.yaml."
            )
        entry = cfg.datasets.get(name) if name else None
        if entry is not None and "measurements" not in entry.model_fields_set:
            raise ConfigError(
                f"calibrate.datasets.{name} in {where} has no 'measurements'; give the file or "
                "folder, e.g. {measurements: data/planted/measurements.csv, effects: []}."
            )
        if args.get("effects") is not None:
            from femcal.effects.terms import split_terms

            effects = split_terms(args["effects"])
        else:  # another file than the dataset's: not the dataset's effects nor noise
            effects = [] if measured or entry is None else list(entry.effects)
        measurements = Path(measured) if measured else setting_path(params, entry.measurements)
        noise, noise_source = noise_setting(  # another file than the dataset's: not its noise
            params,
            args.get("noise_deg"),
            None if measured or entry is None else entry.noise_deg,
            f"calibrate.datasets.{name}.noise_deg",
        )
        # before anything heavy is imported
        out = output_folder(params, args, "calibrate", subfolder=name or "custom")
        check_measurements(measurements)
        if args.get("plots"):
            given["plots"] = args["plots"]
        job = CalibrationJob.from_params(
            params,
            measurements=measurements,
            out_dir=out,
            progress=bool(args.get("progress")),
            effects=tuple(effects),
            noise_deg=noise,
            noise_source=noise_source,
            compare_to=check_compare_to(args.get("compare_to")),
            **given,
        )
        return cls(
            **{f.name: getattr(job, f.name) for f in fields(CalibrationJob)},
            effect_modules=effect_modules(params, args.get("effects_module")),
            metrics_file=args.get("metrics_file"),
            params=params,
        )


def run(settings: CalibrateSettings) -> dict[str, Any]:
    """Load the user's effects, calibrate, write the outputs and the DVC metrics (when asked).

    MLflow (its imports, the store, the run) works in a child process started first
    (:class:`TrackingProcess`), beside the calibration's own imports and work: the second
    core does it meanwhile. Both import without the cyclic garbage collector
    (:class:`ImportCollector`). Returns the summary figures (``summary.json``) with the method,
    model and output folder.
    """
    from femcal.headlines import calibration_headline

    names = load_user_effects(settings.effect_modules)
    with ImportCollector() as collector, TrackingProcess(settings.params) as tracker:
        leave_a_core_to_mlflow()  # torch imported
        collector.resume()
        _, figures = run_calibration(settings, tracker=tracker)
    # Only when asked (the DVC stage): never ad hoc. The headline; summary.json holds all.
    write_metrics(settings.metrics_file, calibration_headline(figures))
    return dict(
        figures,
        method=settings.method,
        model_uri=settings.model_uri,
        out=str(settings.out_dir),
        user_effects=names,
        user_effect_paths=[str(p) for p in settings.effect_modules],
        noise_deg=settings.noise_deg,
        noise_source=settings.noise_source,
    )


def leave_a_core_to_mlflow() -> int:
    """torch's threads in this process: one fewer than the command's (at least one), the
    MLflow process (:class:`TrackingProcess`) working on a core of its own meanwhile; returns
    the count.

    Two torch threads beside a busy process on two cores wait for each other's core: the
    calibration then takes several times its CPU time. The figures' worker processes still
    take every free core (:func:`femcal.figures.plot_workers`): they are drawn once the
    calibration is done.
    """
    import torch

    threads = max(1, torch.get_num_threads() - 1)
    torch.set_num_threads(threads)
    return threads


def describe(figures: Mapping[str, Any]) -> list[str]:
    out = figures["out"]
    held = (
        f", held-out surrogate MAE {figures['holdout_mae_deg']:.4f} deg"
        if "holdout_mae_deg" in figures
        else ""
    )
    lines = describe_user_effects(figures["user_effects"], figures["user_effect_paths"])
    lines.append(
        f"calibrated {figures['n_specimens']} specimens with {figures['method']} against "
        f"{figures['model_uri']} in {figures['seconds']:.2f} s{_noise_note(figures)}: "
        f"MAE {figures['mae_deg']:.4f} deg, "
        f"mean R² {figures['r2_mean']:.4f}, {figures['n_outside_bounds']} outside the bounds"
        f"{held}" + fit_warnings(figures, out)
    )
    lines += noise_line(figures)
    if figures["n_plotted"] < figures["n_specimens"]:
        lines.append(
            f"plotted {figures['n_plotted']} of {figures['n_specimens']} specimens (max_plots)"
        )
    lines.append(f"outputs: {out}/parameters.csv, {out}/metrics.csv, {out}/summary.md")
    if figures.get("n_dropped_points"):
        lines.append(dropped_note(figures["n_dropped_points"], out))
    return lines


def _noise_note(figures: Mapping[str, Any]) -> str:
    """`` (measurement noise 0.05 deg counted)`` when the calibration counted one."""
    noise = figures.get("noise_deg")
    return "" if noise is None else f" (measurement noise {noise:g} deg counted)"


def noise_line(figures: Mapping[str, Any]) -> list[str]:
    """The line naming where the measurement noise comes from (none when none is counted)."""
    if figures.get("noise_deg") is None:
        return []
    return [f"measurement noise {figures['noise_deg']:g} deg: {figures['noise_source']}"]


def fit_warnings(figures: dict, out: str) -> str:
    """The calibration line's tail for fits that are no plain success ("" for none)."""
    n = figures["n_specimens"]
    parts = []
    if figures.get("n_r2_negative"):
        parts.append(
            f"WARNING: {figures['n_r2_negative']} of {n} specimens fit worse than their mean "
            f"(R² < 0): see {out}/metrics.csv (column flag)"
        )
    if figures.get("n_outside_envelope"):
        model = figures.get("envelope_model", "the model")
        parts.append(
            f"WARNING: {figures['n_outside_envelope']} of {n} specimens have points outside "
            f"every curve {model} can produce: see {out}/metrics.csv (column reachability)"
            + (
                "; `femcal diagnose` checks them against the disc with effects"
                if model == "the disc alone"
                else ""
            )
        )
    if figures.get("n_beyond_noise"):
        parts.append(
            f"NOTE: {figures['n_beyond_noise']} of {n} specimens are not explained within the "
            f"noise (median residual {figures['rms_z_median']:.2f} sd): see {out}/metrics.csv "
            "(columns flag, rms_z, p_value); `femcal diagnose` asks which effect is missing"
        )
    return "".join(f"\n{p}" for p in parts)


def plugin_options(method: str, options: Mapping[str, Any], where: str) -> None:
    """Check a plugin calibrator's options (``calibrate.options.<method>``) against the
    keywords its function takes after the problem (all of them if it takes ``**kwargs``).

    Raises
    ------
    ConfigError
        Naming the file, each keyword it does not take, and those it does.
    """
    from femcal.calibration import get_calibrator
    from femcal.settings import closest

    parameters = list(inspect.signature(get_calibrator(method)).parameters.values())
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return
    named = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    takes = [p.name for p in parameters[1:] if p.kind in named and p.name != "rng"]
    problems = []
    for key in (k for k in options if k not in takes):
        close = closest(str(key), takes)
        fix = "set calibrate.seed" if key == "rng" else f"did you mean {close}?" if close else ""
        problems.append(
            f"calibrate.options.{method}.{key}: not a keyword of the {method} calibrator"
            + (f" ({fix})" if fix else "")
        )
    if problems:
        raise ConfigError(
            f"{where}: {'; '.join(problems)}. It takes: {', '.join(takes) or 'no options'}; fix "
            "or remove the others."
        )
