"""The DVC stages as library functions: explicit arguments in, files out.

``femcal.cli`` reads params.yaml and calls these; tests call them directly.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.evaluate import Score, score_model, write_reports
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

SPACE_FILE = "parameter_space.json"


def load_split(prepared_dir: Path, split: str):
    """Read a prepared split and the parameter space."""
    from femcal.prepare import load_tidy

    space = ParameterSpace.from_json(prepared_dir / SPACE_FILE)
    return load_tidy(prepared_dir / f"{split}.csv", space), space


def run_train(
    *,
    prepared_dir: Path,
    split: str,
    out_dir: Path,
    metrics_path: Path,
    settings: Mapping[str, Any],
    storage: str,
    study_name: str,
    seed: int,
    val_fraction: float,
    model_name: str | None,
    progress: bool = False,
    data_split: str | None = None,
):
    """Train (search + final ensemble) on one split; export the model folder, write the summary.

    ``split`` names the run (Optuna study, MLflow run); ``data_split`` is the prepared table
    trained on (default: ``split``), so that e.g. a held-out surrogate trains on "large" too.

    ``out_dir`` receives the logged MLflow model file for file (:func:`femcal.tracking.
    export_model`), with ``mlflow.json`` recording the run and the registered version: the
    folder DVC versions is a complete model that loads and serves without the tracking store.
    """

    from femcal.train import train_surrogate, write_summary

    table, space = load_split(prepared_dir, data_split or split)
    result = train_surrogate(
        table,
        space,
        search_space=settings.get("search_space") or {},
        fixed=settings.get("fixed") or {},
        n_trials=int(settings.get("n_trials", 0)),
        final_members=int(settings.get("final_members", 1)),
        storage=storage,
        study_name=f"{study_name}-{split}",
        seed=seed,
        val_fraction=val_fraction,
        register_as=model_name if settings.get("register") else None,
        run_name=f"train-{split}",
        progress=progress,
    )
    _export_folder(result, out_dir, model_name if settings.get("register") else None)
    write_summary(result, metrics_path)
    return result


def _export_folder(result, out_dir: Path, registered_model: str | None) -> None:
    """The logged MLflow model of a training ``result`` (``model_uri``, ``run_id``, ``version``,
    ``promoted``) exported to ``out_dir``, which appears complete or not at all."""
    import mlflow

    from femcal.tracking import export_model

    tmp = out_dir.with_name(out_dir.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    export_model(
        result.model_uri,
        tmp,
        record={
            "tracking_uri": mlflow.get_tracking_uri(),
            "run_id": result.run_id,
            "model_uri": result.model_uri,
            "registered_model": registered_model,
            "version": result.version,
            "promoted": result.promoted,
        },
    )
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)


def run_baselines(
    *,
    prepared_dir: Path,
    split: str,
    out_dir: Path,
    models: Sequence[str],
    seed: int,
    n_jobs: int,
) -> dict[str, float]:
    """Fit the study's model zoo on one split; save each fitted model; log each as a run."""
    import mlflow

    from femcal.surrogates import make_surrogate
    from femcal.train import ok_rows

    table, space = load_split(prepared_dir, split)
    data = ok_rows(table)
    out_dir.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    with mlflow.start_run(run_name=f"baselines-{split}"):
        mlflow.set_tag("femcal.stage", "baselines")
        for name in models:
            with mlflow.start_run(run_name=f"{name}-{split}", nested=True):
                model = make_surrogate(name, space=space, seed=seed, n_jobs=n_jobs)
                t0 = time.perf_counter()
                model.fit(data, data["rom_deg"].to_numpy())
                seconds[name] = time.perf_counter() - t0
                mlflow.log_params({"model": name, "train_split": split, "seed": seed})
                mlflow.log_metric("fit_seconds", seconds[name])
                model.save(out_dir / name)  # skops + LightGBM text: data, not a pickle
                logger.info("%s on %s fitted in %.1f s", name, split, seconds[name])
    (out_dir / "fit_seconds.json").write_text(json.dumps(seconds, indent=2) + "\n")
    return seconds


def _load_nn(path: Path):
    """The surrogate in a model folder of the train stage (through its trusted loader)."""
    from femcal.tracking import load_surrogate

    return load_surrogate(str(path))


def run_evaluate(
    *,
    prepared_dir: Path,
    surrogate_dirs: Mapping[str, Path],
    baseline_dirs: Mapping[str, Path],
    baseline_models: Sequence[str],
    interpolation_path: Path | None,
    markdown: Path,
    json_path: Path,
    table_path: Path,
    predictions_path: Path | None = None,
    curves_path: Path | None = None,
    plot_split: str = "large",
) -> dict[str, list[Score]]:
    """Score every model on the Test split; write the reports and plot data; log to MLflow.

    ``json_path`` gets the headline figures (the stage's DVC metrics), ``table_path`` every
    model x training set x load case, ``markdown`` the tables for people. For the network
    trained on ``plot_split`` (the one calibrate uses), ``predictions_path`` gets its
    predicted vs FE RoM of every Test row and ``curves_path`` its training and validation
    loss per member and epoch (from the model folder): the data of ``dvc plots``.
    """
    import mlflow

    from femcal.evaluate import prediction_table, training_curves
    from femcal.surrogates.baselines import load_baseline

    test, _ = load_split(prepared_dir, "test")
    sections: dict[str, list[Score]] = {}
    for split in surrogate_dirs:
        rows: list[Score] = []
        nn_dir = surrogate_dirs[split]
        info = (
            json.loads((nn_dir / "mlflow.json").read_text())
            if (nn_dir / "mlflow.json").exists()
            else {}
        )
        nn = _load_nn(nn_dir)
        if split == plot_split and predictions_path is not None:
            predictions_path.parent.mkdir(parents=True, exist_ok=True)
            prediction_table(nn, test).to_csv(predictions_path, index=False)
        if split == plot_split and curves_path is not None:
            curves_path.parent.mkdir(parents=True, exist_ok=True)
            training_curves(nn).to_csv(curves_path, index=False)
        rows.append(
            score_model(
                nn,
                test,
                name="nn",
                train_split=split,
                extra={"registered_version": info.get("version")},
            )
        )
        for name in baseline_models:
            model = load_baseline(baseline_dirs[split] / name)
            rows.append(score_model(model, test, name=name, train_split=split))
        rows.sort(key=lambda s: s.scores["mae"])
        sections[f"Trained on {split.capitalize()}"] = rows
    if interpolation_path is not None and interpolation_path.exists():
        sections["Interpolation: trained on 1, 3, 5 Nm, tested at 2 and 4 Nm"] = [
            Score(r["model"], r["train_split"], r["scores"], r["n_rows"], {})
            for r in json.loads(interpolation_path.read_text())
        ]
    preamble = (
        "MAE in degrees over all rows; mean R² = R² per load case pooled over configurations "
        "and moments, averaged over load cases; curve R² = the study's per-specimen R² across "
        "the moments of a curve, averaged. Study figures: Atad et al., 4-fold CV means."
    )
    write_reports(
        sections,
        markdown=markdown,
        json_path=json_path,
        table_path=table_path,
        preamble=preamble,
    )
    with mlflow.start_run(run_name="evaluate"):
        mlflow.set_tag("femcal.stage", "evaluate")
        for title, rows in sections.items():
            for s in rows:
                with mlflow.start_run(run_name=f"eval-{s.model}-{s.train_split}", nested=True):
                    mlflow.log_params(
                        {"model": s.model, "train_split": s.train_split, "section": title[:200]}
                    )
                    mlflow.log_metrics({k: float(v) for k, v in s.scores.items() if np.isfinite(v)})
        mlflow.log_artifact(str(markdown))
        for path in (json_path, table_path, predictions_path, curves_path):
            if path is not None:
                mlflow.log_artifact(str(path))
    return sections


def run_interpolation(
    *,
    prepared_dir: Path,
    out_path: Path,
    train_moments: Sequence[float],
    test_moments: Sequence[float],
    fixed: Mapping[str, Any],
    final_members: int,
    baselines: Sequence[str],
    seed: int,
    val_fraction: float,
    n_jobs: int = 1,
) -> list[Score]:
    """Train on some moments of Large, test at others on Test (NN and chosen baselines)."""
    import mlflow

    from femcal.surrogates import make_surrogate
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.train import ok_rows, surrogate_kwargs, validation_split

    large, space = load_split(prepared_dir, "large")
    test, _ = load_split(prepared_dir, "test")
    data = ok_rows(large)
    data = data[data["moment_nm"].isin(list(train_moments))].reset_index(drop=True)
    tr, va = validation_split(data, fraction=val_fraction, seed=seed)
    scores: list[Score] = []
    with mlflow.start_run(run_name="interpolation"):
        mlflow.set_tag("femcal.stage", "interpolation")
        mlflow.log_params(
            {"train_moments": list(train_moments), "test_moments": list(test_moments)}
        )
        nn = NeuralSurrogate(space, **surrogate_kwargs(fixed), n_members=final_members, seed=seed)
        nn.fit(tr, tr["rom_deg"].to_numpy(), X_val=va, y_val=va["rom_deg"].to_numpy())
        label = "large, " + ",".join(f"{m:g}" for m in train_moments) + " Nm"
        scores.append(score_model(nn, test, name="nn", train_split=label, moments=test_moments))
        for name in baselines:
            model = make_surrogate(name, space=space, seed=seed, n_jobs=n_jobs)
            model.fit(data, data["rom_deg"].to_numpy())
            scores.append(
                score_model(model, test, name=name, train_split=label, moments=test_moments)
            )
        for s in scores:
            mlflow.log_metrics(
                {f"{s.model}.{k}": float(v) for k, v in s.scores.items() if np.isfinite(v)}
            )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(
        json.dumps(
            [
                {
                    "model": s.model,
                    "train_split": s.train_split,
                    "scores": s.scores,
                    "n_rows": s.n_rows,
                }
                for s in scores
            ],
            indent=2,
        )
        + "\n"
    )
    return scores


def training_configurations(path: Path) -> np.ndarray:
    """Distinct converged configurations (physical units) of a prepared split, shape (N, d)."""
    from femcal.prepare import load_tidy
    from femcal.train import ok_rows

    space = ParameterSpace.from_json(path.parent / SPACE_FILE)
    table = ok_rows(load_tidy(path, space))
    return table.drop_duplicates("config_id")[list(space.names)].to_numpy(dtype=float)


def calibration_options(
    method: str, options: Mapping[str, Any], *, surrogate: Any, start_bank: Path | None
) -> dict[str, Any]:
    """A calibrator's options completed from the data and the surrogate.

    For ``pgd``: the training configurations of ``start_bank`` (a prepared split) as starts,
    and ``noise_deg`` from the surrogate's validation error (the surrogate's own error is part
    of the noise of every RoM value; for Gaussian errors sd = MAE * sqrt(pi / 2)).
    """
    opts = dict(options)
    if method == "pgd":
        if start_bank is not None and "start_bank" not in opts:
            opts["start_bank"] = training_configurations(start_bank)
        val = float(getattr(surrogate, "best_val_mae_deg_", float("nan")))
        if "noise_deg" not in opts and np.isfinite(val):
            opts["noise_deg"] = val * float(np.sqrt(np.pi / 2))
    return opts


def run_calibrate(
    *,
    measurements: Path,
    out_dir: Path,
    method: str,
    model_uri: str,
    holdout_uri: str | None,
    start_bank: Path | None,
    options: Mapping[str, Any],
    seed: int,
    error_growth: float,
    max_log_ratio: float,
    chunk_size: int | None = None,
    plots: bool | str = True,
    max_plots: int | None = None,
    progress: bool = False,
    effects: Sequence[str] = (),
):
    """Calibrate every specimen of a measurement file against the registered surrogate.

    ``plots``: "all" (True) writes the per-specimen PNGs and the summary page, "summary" the
    summary page only, "none" (False) no figure
    (:func:`femcal.calibration.report.write_outputs`). The time of each phase (reading and
    loading, calibration, outputs, MLflow logging) is logged at DEBUG level (``femcal -v``).

    ``effects`` lists physical effects (:mod:`femcal.effects`) added to the disc: their
    parameters are calibrated jointly with the material parameters.

    Reads the measurements, loads the surrogate (and the held-out surrogate): a model folder
    (``models/surrogate-large``, the one ``dvc.lock`` pins) or an MLflow model URI. Checks the
    moments with the moment policy (:class:`femcal.moments.MomentPolicy` of ``error_growth``
    and ``max_log_ratio``, params.yaml ``moments``), calibrates the batch
    with each point weighted by ``1 / sd(M)^2`` of the surrogate's error at its moment (times
    the measurement's own weight), writes ``out_dir`` (see
    :func:`femcal.calibration.report.write_outputs`) and logs one MLflow run with the
    per-specimen tables and every output file as artifacts. The run's tags
    ``femcal.model.*`` and ``femcal.holdout.*`` name each surrogate: its URI, the SHA-256 of its
    files and its registered version when known (:class:`femcal.tracking.ModelSource`).

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

    check_destination(out_dir)  # a bad output folder is the first error, not the last
    from femcal.calibration.report import plot_mode

    plots = plot_mode(plots)  # a wrong value before the calibration
    clock = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 3)
        clock = now

    import mlflow

    from femcal.calibration import SurrogateCurveModel, calibrate
    from femcal.calibration.report import write_outputs
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.outputs import staged_output
    from femcal.reachability import assess_reachability
    from femcal.tracking import load_surrogate, open_model

    meas = read_measurements(measurements)
    source = open_model(model_uri)
    surrogate = load_surrogate(source)
    policy = MomentPolicy.for_surrogate(surrogate, growth=error_growth, max_log_ratio=max_log_ratio)
    policy.check(meas)
    weight = meas.weight * policy.weights(meas.moments)  # (n, 4, m): 1 / sd(M)^2, relative
    from femcal.effects.composite import EffectModel

    model = SurrogateCurveModel(surrogate, meas.moments)
    if effects:
        model = EffectModel(model, list(effects))
    # Before the fit: can the model produce these curves at all? (raises or warns)
    reach = assess_reachability(
        meas, model, sigma_model=policy.sigma_surrogate(meas.moments), reference=start_bank
    )
    opts = calibration_options(method, options, surrogate=surrogate, start_bank=start_bank)
    holdout = None
    holdout_source = open_model(holdout_uri) if holdout_uri else None
    if holdout_source is not None:
        holdout = SurrogateCurveModel(load_surrogate(holdout_source), meas.moments)
        if effects:
            holdout = EffectModel(holdout, list(effects))
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
    )
    lap("calibration")
    missing = meas.missing_load_cases()
    label = "+".join([method, *effects])
    # Outputs staged beside out_dir (a kill leaves nothing at out_dir); the MLflow run covers
    # writing them, gets exactly the staged files, and the move into place happens inside it.
    with (
        staged_output(out_dir, command="calibrate") as stage,
        mlflow.start_run(run_name=f"calibrate-{label}") as run,
    ):
        stage.note(mlflow_run_id=run.info.run_id)
        mlflow.set_tag("femcal.stage", "calibrate")
        figures = write_outputs(
            result,
            stage.path,
            holdout=holdout,
            plots=plots,
            max_plots=max_plots,
            reachability=reach.notes(),
            progress=progress,
        )
        lap(f"outputs (tables, plots: {plots})")
        logged = {
            "method": method,
            "effects": ",".join(effects) or "none",
            "measurements": str(measurements),
            "n_specimens": meas.n_specimens,
            "moments": ",".join(f"{m:g}" for m in meas.moments),
            "model_uri": model_uri,
            "holdout_uri": holdout_uri or "",
            "seed": seed,
            "chunk_size": chunk_size or 0,
            "moments.error_growth": error_growth,
            "moments.max_log_ratio": max_log_ratio,
        }
        for key, value in opts.items():
            if key != "start_bank" and not hasattr(value, "predict"):
                logged[f"option.{key}"] = value
        if "start_bank" in opts:
            logged["option.start_bank"] = f"{start_bank} ({len(opts['start_bank'])} configs)"
        for tag, src in (("model", source), ("holdout", holdout_source)):
            if src is not None:
                mlflow.set_tags(src.tags(tag))
                if src.version:
                    logged[f"{tag}_version"] = src.version
        mlflow.log_params(logged)
        mlflow.log_metrics({k: float(v) for k, v in figures.items() if isinstance(v, (int, float))})
        if missing:
            mlflow.set_tag("femcal.missing_load_cases", json.dumps(missing)[:5000])
        metrics_df = pd.read_csv(stage.path / "metrics.csv")
        metrics_df["missing_load_cases"] = metrics_df["missing_load_cases"].fillna("")
        mlflow.log_table(metrics_df, artifact_file="tables/metrics.json")
        mlflow.log_table(result.parameters_frame(), artifact_file="tables/parameters.json")
        _compare_with_previous(measurements, logged, figures, stage.path)
        stage.finalize()
        _log_artifacts(stage.path, "calibration", progress=progress)  # this run's files
        stage.commit()
    lap("MLflow logging")
    logger.debug("calibrate timings: %s", ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()))
    return result, figures


def _log_artifacts(folder: Path, artifact_path: str, *, progress: bool = False) -> None:
    """``mlflow.log_artifacts(folder, artifact_path)`` file by file, with a progress bar.

    The same artifact layout: ``<artifact_path>/<path of the file in folder>``.
    """
    import mlflow

    files: Any = sorted(p for p in Path(folder).rglob("*") if p.is_file())
    if progress and len(files) > 1:
        from tqdm.auto import tqdm

        files = tqdm(files, desc="MLflow artifacts", unit="file")
    for path in files:
        parent = path.parent.relative_to(folder).as_posix()
        mlflow.log_artifact(
            str(path), f"{artifact_path}/{parent}" if parent != "." else artifact_path
        )


def _compare_with_previous(
    measurements: Path, logged: Mapping[str, Any], figures: Mapping[str, Any], out_dir: Path
) -> None:
    """Before and after: the latest earlier calibration of the same file with other effects."""
    import mlflow

    from femcal.compare import comparison_frame, previous_calibration, write_comparison

    this = mlflow.active_run().info.run_id
    prev = previous_calibration(
        measurements=str(measurements), effects=logged["effects"], exclude_run_id=this
    )
    if prev is None:
        return
    after = {k: v for k, v in figures.items() if isinstance(v, (int, float))}
    frame = comparison_frame(prev.data.metrics, after)
    write_comparison(
        frame,
        out_dir,
        before={
            "run_id": prev.info.run_id,
            "effects": prev.data.params.get("effects", ""),
            "model": prev.data.params.get("model_version", ""),
        },
        after={
            "run_id": this,
            "effects": logged["effects"],
            "model": logged.get("model_version", ""),
        },
    )
    mlflow.set_tag("femcal.compared_to", prev.info.run_id)
    logger.info("Compared with run %s: %s", prev.info.run_id, out_dir / "comparison.md")


def run_train_inverse(
    *,
    surrogate_uri: str,
    moments: Sequence[float],
    out_dir: Path,
    metrics_path: Path,
    settings: Mapping[str, Any],
    storage: str,
    study_name: str,
    seed: int,
    register_as: str | None,
    progress: bool = False,
):
    """Train the study's inverse network on samples of the surrogate; register it.

    ``surrogate_uri`` is a model folder (``models/surrogate-large``) or an MLflow model URI;
    the training run's tags ``femcal.surrogate.*`` name it (URI, SHA-256, registered
    version). ``out_dir`` receives the logged MLflow model file for file, as for
    :func:`run_train`.
    """
    import mlflow

    from femcal.calibration import SurrogateCurveModel
    from femcal.inverse import train_inverse
    from femcal.tracking import load_surrogate, open_model

    source = open_model(surrogate_uri)
    surrogate = load_surrogate(source)
    result = train_inverse(
        SurrogateCurveModel(surrogate, moments),
        n_samples=int(settings.get("n_samples", 50_000)),
        search_space=settings.get("search_space") or {},
        fixed=settings.get("fixed") or {},
        n_trials=int(settings.get("n_trials", 0)),
        storage=storage,
        study_name=study_name,
        seed=seed,
        register_as=register_as,
        run_name="train-inverse",
        progress=progress,
    )
    client = mlflow.MlflowClient()
    for key, value in source.tags("surrogate").items():
        client.set_tag(result.run_id, key, value)
    _export_folder(result, out_dir, register_as)
    metrics_path.parent.mkdir(parents=True, exist_ok=True)
    metrics_path.write_text(
        json.dumps(
            {
                "val_mae_unit": result.val_mae,
                "val_rom_mae_deg": result.val_rom_mae_deg,
                "n_trials": result.n_trials,
                "seconds": round(result.seconds, 1),
                "mlflow_run_id": result.run_id,
                "registered_version": result.version,
                "promoted": result.promoted,
                "surrogate_uri": surrogate_uri,
                "surrogate_sha256": source.sha256,
                "surrogate_version": source.version,
                "best_params": result.best_params,
            },
            indent=2,
            default=str,
        )
        + "\n"
    )
    return result


def run_plant(
    *,
    prepared_dir: Path,
    out_dir: Path,
    n_per_class: int,
    moments: Sequence[float],
    noise_deg: float,
    seed: int,
) -> Path:
    """A planted cohort from the FE curves of the Test set: measurements.csv + truth.csv.

    ``out_dir`` is all or nothing (:mod:`femcal.outputs`).
    """
    from femcal.outputs import check_destination, staged_output

    check_destination(out_dir)
    from femcal.effects.planted import make_cohort
    from femcal.prepare import wide_rom

    test, _ = load_split(prepared_dir, "test")
    _, fe_moments, fe_rom = wide_rom(test)
    cohort = make_cohort(
        fe_moments,
        fe_rom,
        n_per_class=n_per_class,
        moments=moments,
        noise_deg=noise_deg,
        rng=np.random.default_rng(seed),
    )
    with staged_output(out_dir, command="plant") as stage:  # all or nothing
        cohort.to_long().to_csv(stage.path / "measurements.csv", index=False)
        cohort.truth.to_csv(stage.path / "truth.csv", index=False)
    return out_dir / "measurements.csv"


def run_diagnose(
    *,
    measurements: Path,
    out_dir: Path,
    model_uri: str,
    noise_deg: float | None,
    candidates: Sequence[str] | None,
    start_bank: Path | None,
    min_delta: float,
    seed: int,
    error_growth: float,
    max_log_ratio: float,
    alpha: float = 0.01,
    max_effects: int = 3,
    plots: bool = True,
    max_plots: int | None = None,
):
    """Diagnose every specimen of a measurement file; write DIR; log one MLflow run.

    The moments are checked with the moment policy (:class:`femcal.moments.MomentPolicy` of
    ``error_growth`` and ``max_log_ratio``, params.yaml ``moments``), and the surrogate's own
    error at each moment (shape (m,), larger beyond the trained range) is part of the noise.

    ``out_dir`` is all or nothing, as for :func:`run_calibrate` (:mod:`femcal.outputs`).
    ``model_uri`` is a model folder (``models/surrogate-large``) or an MLflow model URI; the
    run's tags ``femcal.model.*`` name it (URI, SHA-256 of its files, registered version).
    """
    from femcal.outputs import check_destination

    check_destination(out_dir)  # a bad output folder is the first error, not the last
    import mlflow

    from femcal.calibration import SurrogateCurveModel
    from femcal.diagnose import diagnose
    from femcal.diagnose_report import write_diagnosis
    from femcal.effects import available_effects
    from femcal.effects.composite import EffectModel
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.outputs import staged_output
    from femcal.reachability import assess_reachability
    from femcal.tracking import load_surrogate, open_model

    meas = read_measurements(measurements)
    source = open_model(model_uri)
    surrogate = load_surrogate(source)
    policy = MomentPolicy.for_surrogate(surrogate, growth=error_growth, max_log_ratio=max_log_ratio)
    policy.check(meas)
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
        surrogate_error_deg=policy.sigma_surrogate(meas.moments),
        candidates=candidates,
        start_bank=training_configurations(start_bank) if start_bank else None,
        min_delta=min_delta,
        alpha=alpha,
        max_effects=max_effects,
        seed=seed,
    )
    with (
        staged_output(out_dir, command="diagnose") as stage,
        mlflow.start_run(run_name="diagnose") as run,
    ):
        stage.note(mlflow_run_id=run.info.run_id)
        mlflow.set_tag("femcal.stage", "diagnose")
        mlflow.set_tags(source.tags("model"))
        summary = write_diagnosis(diag, meas.rom_deg, stage.path, plots=plots, max_plots=max_plots)
        mlflow.log_params(
            {
                "measurements": str(measurements),
                "model_uri": model_uri,
                "noise_deg": "estimated" if noise_deg is None else noise_deg,
                "candidates": ",".join(candidates or []) or "all",
                "min_delta": min_delta,
                "alpha": alpha,
                "max_effects": max_effects,
                "cohort_verdict": diag.cohort_verdict(),
                "moments.error_growth": error_growth,
                "moments.max_log_ratio": max_log_ratio,
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


def fe_space(bounds: Any) -> ParameterSpace:
    """The sampling box of an FE campaign from ``fe.bounds``.

    Parameters
    ----------
    bounds : str, Path or mapping
        A ParameterBounds.csv file (the study's layout), or a mapping ``name -> [lower,
        upper]`` in physical units (the study's 13 parameters, in the study's order).
    """
    from femcal.errors import ConfigError

    if isinstance(bounds, (str, Path)):
        return ParameterSpace.from_bounds_csv(Path(bounds))
    if not isinstance(bounds, Mapping) or not bounds:
        raise ConfigError(
            "fe.bounds must be a ParameterBounds.csv path or a mapping name -> [lower, upper]; "
            f"got {bounds!r}."
        )
    try:
        lower = [float(v[0]) for v in bounds.values()]
        upper = [float(v[1]) for v in bounds.values()]
    except (TypeError, ValueError, IndexError, KeyError):
        raise ConfigError(
            "fe.bounds: every entry must be [lower, upper] (two numbers); fix the bounds."
        ) from None
    return ParameterSpace(list(bounds), lower, upper)


def run_simulate(
    *,
    solver: str,
    settings: Mapping[str, Any],
    bounds: Any,
    splits: Mapping[str, int],
    seed: int,
    load_cases: Sequence[str],
    moments: Sequence[float],
    store: Path,
    out_dir: Path,
    scheduler_address: str | None = None,
    n_workers: int = 2,
    scratch_dir: Path | None = None,
    progress: bool = False,
):
    """The FE campaign (Dask, durable store, resume) and its dataset in the study's layout.

    Returns
    -------
    result : CampaignResult
    summary : dict
        The dataset's ``campaign.json`` (counts, failure rate and reasons, CPU seconds per
        configuration, solver version, wall seconds, workers).

    ``out_dir`` is all or nothing (:func:`femcal.fe.dataset.write_dataset`), and checked
    before the campaign runs.
    """
    from femcal.outputs import check_destination

    check_destination(out_dir)
    from femcal.errors import ConfigError
    from femcal.fe.campaign import run_campaign, settings_hash, split_design
    from femcal.fe.dataset import write_dataset
    from femcal.schema import LOAD_CASES

    if sorted(load_cases) != sorted(LOAD_CASES):
        raise ConfigError(
            f"fe.load_cases is {list(load_cases)}; a dataset in the study's layout needs all "
            f"four load cases {list(LOAD_CASES)}."
        )
    space = fe_space(bounds)
    design_df = split_design(space, splits, seed)
    result = run_campaign(
        solver,
        settings,
        design_df,
        store=store,
        names=space.names,
        load_cases=LOAD_CASES,
        moments=moments,
        scheduler_address=scheduler_address,
        n_workers=n_workers,
        scratch_dir=scratch_dir,
        progress=progress,
    )
    summary = write_dataset(
        design_df,
        result.records.to_dict(orient="records"),
        out_dir,
        space=space,
        moments=moments,
        campaign_info={
            "solver": solver,
            "settings": dict(settings),
            "settings_hash": settings_hash(solver, settings),
            "seed": int(seed),
            "splits": {k: int(v) for k, v in splits.items()},
            "store": str(store),
            "jobs_run_now": result.n_run,
            "jobs_resumed_from_store": result.n_skipped,
            "wall_seconds_this_run": round(result.wall_seconds, 2),
            "n_workers": result.n_workers,
        },
    )
    return result, summary


def run_validate(
    *,
    calibration_dir: Path,
    measurements: Path,
    solver: str,
    settings: Mapping[str, Any],
    forces: Sequence[float],
    literature: Mapping[Any, Any],
    store: Path,
    out_dir: Path,
    scheduler_address: str | None = None,
    n_workers: int = 2,
    progress: bool = False,
):
    """FE re-simulation of a calibration (the study's step 4); tables in ``out_dir``; MLflow.

    Returns
    -------
    ValidationResult
        See :func:`femcal.fe.validate.validate_calibration`. ``out_dir`` is all or nothing,
        as for :func:`run_calibrate` (:mod:`femcal.outputs`).
    """
    from femcal.outputs import check_destination, staged_output

    check_destination(out_dir)  # before the FE campaign
    import mlflow

    from femcal.fe.validate import literature_ranges, validate_calibration

    ranges = literature_ranges(literature)
    # The FE campaign runs before the MLflow run starts (a bad input makes no FAILED run);
    # its tables are staged, and move into place inside the run that logs them.
    with staged_output(out_dir, command="validate") as stage:
        result = validate_calibration(
            calibration_dir=calibration_dir,
            measurements=measurements,
            solver=solver,
            settings=settings,
            forces=forces,
            literature=ranges,
            store=store,
            out_dir=stage.path,
            scheduler_address=scheduler_address,
            n_workers=n_workers,
            progress=progress,
        )
        s = result.summary
        with mlflow.start_run(run_name="validate") as run:
            stage.note(mlflow_run_id=run.info.run_id)
            mlflow.set_tag("femcal.stage", "validate")
            mlflow.log_params(
                {
                    "calibration_dir": str(calibration_dir),
                    "measurements": str(measurements),
                    "solver": solver,
                    "settings": json.dumps(dict(settings), sort_keys=True)[:500],
                    "forces_n": ",".join(f"{f:g}" for f in forces),
                    "solver_versions": ",".join(s["solver_versions"]),
                    "n_specimens": s["n_specimens"],
                }
            )
            metrics = {
                "fe_mae_deg": s["fe_mae_deg"],
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
            mlflow.log_metrics({k: float(v) for k, v in metrics.items() if np.isfinite(float(v))})
            mlflow.log_table(result.table, artifact_file="tables/validation.json")
            stage.finalize()
            mlflow.log_artifacts(str(stage.path), artifact_path="validation")  # this run's files
            stage.commit()
    return result
