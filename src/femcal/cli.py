"""``femcal`` command line: reads params.yaml and the environment, calls the library, prints.

Every DVC stage is one sub-command, e.g. ``femcal train --split large``. ``-v`` logs femcal's
debug messages, ``-q`` only its warnings (and hides the progress bars, which are shown on a
terminal only); ``--version`` prints the installed version.

Relative paths typed on the command line start at the current folder; relative paths in
params.yaml start at its folder (the project root), and the stores' (``mlflow.store_dir``,
``train.storage``) at the repository's root, also in the temporary copy of ``dvc exp run
--temp/--queue`` (:mod:`femcal.paths`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from importlib import metadata
from pathlib import Path

from femcal.config import load_params, section
from femcal.errors import ConfigError, FemcalError, InputDataError
from femcal.paths import setting_path, setting_uri, store_path, store_url
from femcal.settings.keywords import BUILTIN_EFFECTS, CALIBRATORS, PLOT_CHOICES, SPLITS

#: Logging level of the ``femcal`` logger per verbosity option (none given: INFO).
LOG_LEVELS = {"verbose": logging.DEBUG, "default": logging.INFO, "quiet": logging.WARNING}


def version() -> str:
    """The installed femcal's version (the package metadata; the source's when not installed)."""
    try:
        return metadata.version("femcal")
    except metadata.PackageNotFoundError:  # pragma: no cover - run from a source tree
        from femcal import __version__

        return __version__


def configure_logging(level: int) -> None:
    """Route log records to stderr; femcal logs at ``level``, other libraries from WARNING.

    ``-v`` (DEBUG) also lets other libraries' INFO records through.
    """
    logging.basicConfig(
        level=logging.INFO if level <= logging.DEBUG else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("femcal").setLevel(level)


def _progress(args: argparse.Namespace) -> bool:
    """Progress bars: on a terminal (stderr) only, and not with ``-q``."""
    return sys.stderr.isatty() and args.log_level < LOG_LEVELS["quiet"]


def _path(params: dict, *keys: str) -> Path:
    """A path setting of params.yaml, relative to the project root (:mod:`femcal.paths`)."""
    return setting_path(params, section(params, *keys))


def _tracking(params: dict) -> None:
    """Point MLflow at the store; tag this process's runs; close runs of killed processes.

    ``mlflow.store_dir`` is relative to the repository's root (:func:`femcal.paths.store_path`).
    """
    from femcal.tracking import configure_tracking, ensure_experiment
    from femcal.tracking_runs import close_killed_runs, tag_runs_with_process

    store = store_path(params, section(params, "mlflow", "store_dir"))
    configure_tracking(store_dir=store)
    experiment = ensure_experiment(section(params, "mlflow", "experiment"), store_dir=store)
    tag_runs_with_process()  # pid + host on every run this command starts
    close_killed_runs([experiment])  # logs each run it closes as KILLED


def _check_outputs(args: argparse.Namespace, out: str | Path, setting: str) -> Path:
    """The output folder and ``--metrics-file``, checked before any heavy work.

    ``setting`` names where the folder comes from when ``--out`` is not given.
    """
    from femcal.outputs import check_destination, check_file_destination

    label = "--out" if getattr(args, "out", None) else f"output folder ({setting})"
    path = check_destination(out, label=label)
    if getattr(args, "metrics_file", None):
        check_file_destination(args.metrics_file, label="--metrics-file")
    return path


def _check_measurements(path: Path) -> None:
    """A missing measurement file or folder, reported before any heavy import."""
    if not path.exists():
        raise InputDataError(
            f"Measurement file {path} does not exist; check the path (relative paths on the "
            f"command line start at the current folder {Path.cwd()}, in params.yaml at its "
            "folder)."
        )


def _write_metrics(args: argparse.Namespace, figures: dict) -> None:
    """``--metrics-file`` (the stage's DVC metrics), written whole or not at all."""
    if getattr(args, "metrics_file", None):
        from femcal.outputs import write_text_atomic

        write_text_atomic(args.metrics_file, json.dumps(figures, indent=2) + "\n")


def _load_user_effects(args: argparse.Namespace, params: dict) -> list[str]:
    """Import the user's effect files before anything uses the effect registry.

    ``effects.modules`` in params.yaml (paths relative to its folder, the project root), then
    every ``--effects-module`` (relative to the working directory); returns the names loaded.
    """
    from femcal.effects import load_effect_modules

    where = params.get("_path", "params.yaml")
    cfg = params.get("effects") or {}
    modules = cfg.get("modules") if isinstance(cfg, dict) else None
    if (
        not isinstance(cfg, dict)
        or set(cfg) - {"modules"}
        or not isinstance(modules or [], list)
        or not all(isinstance(m, str) for m in modules or [])
    ):
        raise ConfigError(
            f"{where}: the effects section must be {{modules: [paths]}}, each path a .py file or "
            f"a folder of them relative to the project root; got effects: {cfg!r}. Write e.g. "
            "`effects: {modules: [my_effects.py]}` (the effects a calibration uses are listed "
            "under calibrate.datasets.<name>.effects)."
        )
    root = Path(where).parent
    paths = [root / m for m in modules or []] + [Path(m) for m in args.effects_module or []]
    if not paths:
        return []
    names = load_effect_modules(paths)
    print(f"user effects: {', '.join(names)} (from {', '.join(str(p) for p in paths)})")
    return names


def cmd_fetch(args: argparse.Namespace, params: dict) -> None:
    from femcal.fetch import fetch_dataset, mirror_from_env

    out = Path(args.out) if args.out else _path(params, "data", "raw_dir")
    mirror = mirror_from_env()
    paths = fetch_dataset(out, mirror=mirror, progress=_progress(args))
    src = f"mirror {mirror}" if mirror else "the study's pinned public address"
    print(f"fetched {len(paths)} files from {src} into {out} (SHA-256 verified)")


def cmd_prepare(args: argparse.Namespace, params: dict) -> None:
    from femcal.prepare import prepare_dataset

    data = section(params, "data")
    raw = setting_path(params, data.get("source_dir") or section(params, "data", "raw_dir"))
    out = _path(params, "data", "prepared_dir")
    limit = section(params, "data").get("limit_configs")
    written = prepare_dataset(raw, out, limit_configs=limit)
    for name, path in written.items():
        print(f"{name}: {path}")


def cmd_train(args: argparse.Namespace, params: dict) -> None:
    from femcal.pipeline import run_train

    _tracking(params)
    split = args.split
    settings = section(params, "train", split)
    storage = _optuna_storage(params)
    result = run_train(
        prepared_dir=_path(params, "data", "prepared_dir"),
        split=split,
        out_dir=setting_path(params, f"models/surrogate-{split}"),
        metrics_path=setting_path(params, f"reports/train-{split}.json"),
        settings=settings,
        storage=storage,
        study_name=section(params, "train", "study_name"),
        seed=int(settings.get("seed", section(params, "train", "seed"))),
        val_fraction=float(section(params, "train", "val_fraction")),
        model_name=settings.get("model_name") or section(params, "mlflow", "model_name"),
        progress=_progress(args),
        data_split=settings.get("split", split),
    )
    reg = (
        f"; registered as version {result.version} ("
        f"{'now champion' if result.promoted else 'champion unchanged'})"
        if result.version
        else ""
    )
    print(
        f"trained on {split}: validation MAE {result.val_mae_deg:.4f} deg after "
        f"{result.n_trials} Optuna trials in {result.seconds:.0f} s{reg}"
    )


def cmd_baselines(args: argparse.Namespace, params: dict) -> None:
    from femcal.pipeline import run_baselines

    _tracking(params)
    seconds = run_baselines(
        prepared_dir=_path(params, "data", "prepared_dir"),
        split=args.split,
        out_dir=setting_path(params, f"models/baselines-{args.split}"),
        models=section(params, "baselines", "models"),
        seed=int(section(params, "baselines", "seed")),
        n_jobs=int(section(params, "baselines", "n_jobs")),
    )
    for name, s in seconds.items():
        print(f"{name:>18} fitted on {args.split} in {s:6.1f} s")


def cmd_interpolate(args: argparse.Namespace, params: dict) -> None:
    from femcal.pipeline import run_interpolation

    _tracking(params)
    scores = run_interpolation(
        prepared_dir=_path(params, "data", "prepared_dir"),
        out_path=setting_path(params, "reports/interpolation.json"),
        train_moments=section(params, "interpolation", "train_moments"),
        test_moments=section(params, "interpolation", "test_moments"),
        fixed=section(params, "train", "large", "fixed"),
        final_members=int(section(params, "interpolation", "final_members")),
        baselines=section(params, "interpolation", "baselines"),
        seed=int(section(params, "train", "seed")),
        val_fraction=float(section(params, "train", "val_fraction")),
        n_jobs=int(section(params, "baselines", "n_jobs")),
    )
    for s in scores:
        print(f"{s.model:>18}: MAE {s.scores['mae']:.3f} deg at unseen moments")


def cmd_evaluate(args: argparse.Namespace, params: dict) -> None:
    from femcal.pipeline import run_evaluate

    _tracking(params)
    splits = ("large", "small")

    def at(path: str) -> Path:  # the project's layout, at the project root
        return setting_path(params, path)

    sections = run_evaluate(
        prepared_dir=_path(params, "data", "prepared_dir"),
        surrogate_dirs={s: at(f"models/surrogate-{s}") for s in splits},
        baseline_dirs={s: at(f"models/baselines-{s}") for s in splits},
        baseline_models=section(params, "baselines", "models"),
        interpolation_path=at("reports/interpolation.json"),
        markdown=at("reports/surrogates.md"),
        json_path=at("reports/surrogates.json"),
        table_path=at("reports/surrogates_table.json"),
        predictions_path=at("reports/plots/surrogate_test_predictions.csv"),
        curves_path=at("reports/plots/training_curves.csv"),
    )
    for title, rows in sections.items():
        print(title)
        for s in rows:
            print(
                f"  {s.model:>18} {s.train_split:>6}: MAE {s.scores['mae']:.3f} deg, "
                f"mean R² {s.scores['r2_mean']:.4f}"
            )
    print(
        "reports: reports/surrogates.md, reports/surrogates_table.json; plot data: "
        "reports/plots/ (dvc plots show)"
    )


def _optuna_storage(params: dict) -> str:
    """FEMCAL_OPTUNA_STORAGE as given, else train.storage (a relative SQLite file under the
    repository's root, :func:`femcal.paths.store_url`); a SQLite file's folder is created."""
    storage = os.environ.get("FEMCAL_OPTUNA_STORAGE") or store_url(
        params, section(params, "train", "storage")
    )
    file = storage[len("sqlite:///") :] if storage.startswith("sqlite:///") else ""
    if file and file != ":memory:":
        Path(file).parent.mkdir(parents=True, exist_ok=True)
    return storage


def cmd_train_inverse(args: argparse.Namespace, params: dict) -> None:
    from femcal.pipeline import run_train_inverse

    _tracking(params)
    cfg = section(params, "inverse")
    result = run_train_inverse(
        surrogate_uri=setting_uri(params, section(params, "inverse", "surrogate_uri")),
        moments=[float(m) for m in section(params, "inverse", "moments")],
        out_dir=setting_path(params, "models/inverse"),
        metrics_path=setting_path(params, "reports/train-inverse.json"),
        settings=cfg,
        storage=_optuna_storage(params),
        study_name=str(cfg.get("study_name", "ivd-inverse")),
        seed=int(cfg.get("seed", 0)),
        register_as=cfg.get("register_as"),
        progress=_progress(args),
    )
    reg = f"; registered as version {result.version}" if result.version else ""
    print(
        f"inverse model: validation MAE {result.val_mae:.4f} (unit box), "
        f"{result.val_rom_mae_deg:.4f} deg through the surrogate, {result.n_trials} trials in "
        f"{result.seconds:.0f} s{reg}"
    )


def _moment_settings(params: dict) -> dict[str, float]:
    """params.yaml's ``moments`` section (one moment policy for every command) as keywords."""
    out = {}
    for key in ("error_growth", "max_log_ratio"):
        value = section(params, "moments", key)
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{params.get('_path', 'params.yaml')}: moments.{key} must be a number >= 0; "
                f"got {value!r}. Use the value measured by benchmarks/bench_extrapolation.py "
                "(reports/extrapolation.md)."
            ) from None
    return out


def _fit_warnings(figures: dict, out: str) -> str:
    """The calibration line's tail for fits that are no plain success ("" for none)."""
    n = figures["n_specimens"]
    parts = []
    if figures.get("n_r2_negative"):
        parts.append(
            f"WARNING: {figures['n_r2_negative']} of {n} specimens fit worse than their mean "
            f"(R² < 0): see {out}/metrics.csv (column flag)"
        )
    if figures.get("n_outside_envelope"):
        parts.append(
            f"WARNING: {figures['n_outside_envelope']} of {n} specimens have points outside "
            f"every curve the model can produce: see {out}/metrics.csv (column reachability)"
        )
    return "".join(f"\n{p}" for p in parts)


def cmd_calibrate(args: argparse.Namespace, params: dict) -> None:
    cfg = section(params, "calibrate")
    method = args.method or section(params, "calibrate", "method")
    model_uri = args.model_uri or setting_uri(params, section(params, "calibrate", "model_uri"))
    if args.model_version or args.model_alias:
        name = section(params, "mlflow", "model_name")
        ref = f"/{args.model_version}" if args.model_version else f"@{args.model_alias}"
        model_uri = f"models:/{name}{ref}"
    holdout_uri = None
    if not args.no_holdout:
        holdout_uri = args.holdout_uri or (
            setting_uri(params, cfg["holdout_uri"]) if cfg.get("holdout_uri") else None
        )
    options = dict((cfg.get("options") or {}).get(method) or {})
    if isinstance(options.get("model_uri"), str):  # the inverse network's folder or URI
        options["model_uri"] = setting_uri(params, options["model_uri"])
    bank = setting_path(params, cfg["start_bank"]) if cfg.get("start_bank") else None
    max_plots = cfg.get("max_plots")
    datasets = cfg.get("datasets") or {}
    if args.dataset and args.dataset not in datasets:
        raise ConfigError(
            f"Unknown dataset '{args.dataset}'; calibrate.datasets in {args.params} has "
            f"{sorted(datasets)}."
        )
    name = args.dataset or (None if args.measurements else next(iter(datasets), None))
    if not args.measurements and name is None:
        raise ConfigError("Give --measurements FILE, or list calibrate.datasets in params.yaml.")
    entry = datasets.get(name) if name else None
    if isinstance(entry, dict):
        if "measurements" not in entry:
            raise ConfigError(
                f"calibrate.datasets.{name} in {args.params} has no 'measurements'; give the "
                "file or folder, e.g. {measurements: data/planted/measurements.csv, effects: []}."
            )
        entry_path, entry_effects = entry["measurements"], list(entry.get("effects") or [])
    else:
        entry_path, entry_effects = entry, []
    if args.effects is not None:
        effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    elif args.measurements:
        effects = []
    else:
        effects = entry_effects
    measurements = (
        Path(args.measurements) if args.measurements else setting_path(params, entry_path)
    )
    out = args.out or str(_path(params, "calibrate", "out_dir") / (name or "custom"))
    _check_outputs(args, out, "calibrate.out_dir")  # before anything heavy is imported
    _check_measurements(measurements)
    _load_user_effects(args, params)
    _tracking(params)
    from femcal.headlines import calibration_headline
    from femcal.pipeline import run_calibrate

    result, figures = run_calibrate(
        measurements=measurements,
        out_dir=Path(out),
        method=method,
        model_uri=model_uri,
        holdout_uri=holdout_uri,
        start_bank=bank,
        options=options,
        seed=int(args.seed if args.seed is not None else cfg.get("seed", 0)),
        **_moment_settings(params),
        chunk_size=cfg.get("chunk_size"),
        plots=args.plots or ("all" if cfg.get("plots", True) else "none"),
        max_plots=None if max_plots is None else int(max_plots),
        progress=_progress(args),
        effects=effects,
    )
    held = (
        f", held-out surrogate MAE {figures['holdout_mae_deg']:.4f} deg"
        if "holdout_mae_deg" in figures
        else ""
    )
    print(
        f"calibrated {figures['n_specimens']} specimens with {method} against {model_uri} in "
        f"{figures['seconds']:.2f} s: MAE {figures['mae_deg']:.4f} deg, mean R² "
        f"{figures['r2_mean']:.4f}, {figures['n_outside_bounds']} outside the bounds{held}"
        + _fit_warnings(figures, out)
    )
    if figures["n_plotted"] < figures["n_specimens"]:
        print(f"plotted {figures['n_plotted']} of {figures['n_specimens']} specimens (max_plots)")
    # Only when asked (the DVC stage): never ad hoc. The headline; summary.json holds all.
    _write_metrics(args, calibration_headline(figures))
    print(f"outputs: {out}/parameters.csv, {out}/metrics.csv, {out}/summary.md")


def cmd_plant(args: argparse.Namespace, params: dict) -> None:
    cfg = section(params, "plant")
    out = _check_outputs(args, _path(params, "plant", "out_dir"), "plant.out_dir")
    from femcal.pipeline import run_plant

    path = run_plant(
        prepared_dir=_path(params, "data", "prepared_dir"),
        out_dir=out,
        n_per_class=int(section(params, "plant", "n_per_class")),
        moments=[float(m) for m in section(params, "plant", "moments")],
        noise_deg=float(section(params, "plant", "noise_deg")),
        seed=int(cfg.get("seed", 0)),
    )
    print(f"planted cohort: {path} (truth beside it)")


def cmd_diagnose(args: argparse.Namespace, params: dict) -> None:
    cfg = section(params, "diagnose")
    noise = args.noise_deg if args.noise_deg is not None else cfg.get("noise_deg")
    bank = section(params, "calibrate").get("start_bank")
    out = args.out or _path(params, "diagnose", "out_dir")
    _check_outputs(args, out, "diagnose.out_dir")  # before anything heavy is imported
    measurements = (
        Path(args.measurements) if args.measurements else _path(params, "diagnose", "measurements")
    )
    _check_measurements(measurements)
    _load_user_effects(args, params)
    _tracking(params)
    from femcal.headlines import diagnosis_headline
    from femcal.pipeline import run_diagnose

    diag, summary = run_diagnose(
        measurements=measurements,
        out_dir=Path(out),
        model_uri=args.model_uri or setting_uri(params, section(params, "calibrate", "model_uri")),
        noise_deg=None if noise is None else float(noise),
        candidates=cfg.get("candidates"),
        start_bank=setting_path(params, bank) if bank else None,
        min_delta=float(cfg.get("min_delta", 10.0)),
        alpha=float(cfg.get("alpha", 0.01)),
        max_effects=int(cfg.get("max_effects", 3)),
        seed=int(cfg.get("seed", 0)),
        **_moment_settings(params),
        plots=bool(cfg.get("plots", True)),
        max_plots=cfg.get("max_plots"),
    )
    # Only when asked (the DVC stage): never ad hoc. The headline; summary.json holds all.
    _write_metrics(args, diagnosis_headline(summary))
    print(
        f"diagnosed {summary['n_specimens']} specimens in {diag.seconds:.1f} s (noise sigma "
        f"{diag.sigma_deg:.4f} deg): verdicts {diag.verdicts()}; cohort verdict "
        f"{diag.cohort_verdict()}"
    )
    counts = diag.effect_counts()
    found = diag.found_effects()
    if found:
        print(
            f"effects found: {', '.join(f'{k} ({counts[k]})' for k in found)}; to add them, list "
            f"[{', '.join(found)}] under calibrate.datasets.<name>.effects in params.yaml and run "
            "`dvc repro` (or: femcal calibrate --measurements FILE --effects "
            f"{','.join(found)})"
        )
    if counts.get("unexplained"):
        print(
            f"unexplained: {counts['unexplained']} specimens are not explained within the noise "
            "by the disc and the registered effects; summary.md and plots/ describe what is "
            "missing (load cases, laxity or stiffening, from which moment, how large). Write "
            "it as an effect (README: 'a new effect') and pass --effects-module FILE."
        )


def _fe_runtime(params: dict) -> tuple[str | None, int]:
    """Scheduler address (fe.scheduler_address, else FEMCAL_DASK_ADDRESS) and worker count."""
    from femcal.fe.campaign import scheduler_address_from_env

    cfg = section(params, "fe")
    address = cfg.get("scheduler_address") or scheduler_address_from_env()
    return address, int(cfg.get("n_workers", 2))


def cmd_simulate(args: argparse.Namespace, params: dict) -> None:
    cfg = section(params, "fe")
    out = Path(args.out) if args.out else _path(params, "fe", "out_dir")
    _check_outputs(args, out, "fe.out_dir")  # before the campaign
    address, n_workers = _fe_runtime(params)
    from femcal.pipeline import run_simulate

    scratch = cfg.get("scratch_dir")
    result, summary = run_simulate(
        solver=section(params, "fe", "solver"),
        settings=dict(cfg.get("settings") or {}),
        bounds=section(params, "fe", "bounds"),
        splits=section(params, "fe", "splits"),
        seed=int(section(params, "fe", "seed")),
        load_cases=list(section(params, "fe", "load_cases")),
        moments=[float(m) for m in section(params, "fe", "moments")],
        store=Path(args.store)
        if args.store
        else store_path(params, section(params, "fe", "store")),
        out_dir=out,
        scheduler_address=address,
        n_workers=n_workers,
        scratch_dir=setting_path(params, scratch) if scratch else None,
        progress=_progress(args),
    )
    cpu = summary["cpu_seconds_per_configuration"]
    print(
        f"FE campaign: {result.n_jobs} jobs ({summary['n_configurations']} configurations x 4 "
        f"load cases), {result.n_skipped} already in {result.store}, {result.n_run} run now on "
        f"{result.n_workers or 0} workers in {result.wall_seconds:.1f} s"
    )
    print(
        f"failure rate {summary['failure_rate']:.3f} ({summary['n_failed']} failed); CPU "
        f"seconds per configuration: mean {cpu['mean']:.2f}, max {cpu['max']:.2f}; solver "
        f"{', '.join(summary['solver_versions'])}"
    )
    for f in summary["failures"]:
        print(
            f"  failed: config {f['config_id']} ({f['split']} row {f['row']}) {f['load_case']}: "
            f"{f['reason']}"
        )
    keys = (
        "n_configurations",
        "n_jobs",
        "n_ok",
        "n_failed",
        "failure_rate",
        "cpu_seconds_per_configuration",
        "cpu_seconds_total",
        "failure_reasons",
    )
    _write_metrics(args, {k: summary[k] for k in keys})  # only when asked (the DVC stage)
    print(f"dataset: {out} (the study's layout; runs.csv, campaign.json)")


def cmd_validate(args: argparse.Namespace, params: dict) -> None:
    cfg = section(params, "validate")
    fe = section(params, "fe")
    out = Path(args.out) if args.out else _path(params, "validate", "out_dir")
    _check_outputs(args, out, "validate.out_dir")  # before the FE campaign
    address, n_workers = _fe_runtime(params)
    _tracking(params)
    from femcal.pipeline import run_validate

    result = run_validate(
        calibration_dir=(
            Path(args.calibration)
            if args.calibration
            else _path(params, "validate", "calibration_dir")
        ),
        measurements=(
            Path(args.measurements)
            if args.measurements
            else _path(params, "validate", "measurements")
        ),
        solver=section(params, "fe", "solver"),
        settings=dict(fe.get("settings") or {}),
        forces=[float(f) for f in cfg.get("forces") or []],
        literature=cfg.get("idp_literature") or {},
        store=(
            Path(args.store)
            if args.store
            else store_path(params, section(params, "validate", "store"))
        ),
        out_dir=out,
        scheduler_address=address,
        n_workers=n_workers,
        progress=_progress(args),
    )
    s = result.summary
    print(
        f"validated {s['n_specimens']} calibrated specimens with the FE model: MAE vs the "
        f"measurement {s['fe_mae_deg']:.4f} deg through FE, {s['surrogate_mae_deg']:.4f} deg "
        f"through the surrogate (FE vs surrogate {s['fe_vs_surrogate_mae_deg']:.4f} deg); "
        f"{s['n_fe_failed_jobs']} FE jobs failed"
    )
    for row in s["idp"]:
        lit = row["literature"]
        verdict = (
            f", {row['n_in_range']}/{s['n_specimens']} in the literature range "
            f"[{lit['low_mpa']:g}, {lit['high_mpa']:g}] MPa"
            if lit
            else ""
        )
        print(
            f"  IDP at {row['force_n']:g} N: {row['idp_mpa_min']:.3f}-{row['idp_mpa_max']:.3f} "
            f"MPa{verdict}"
        )
    from femcal.fe.validate import json_safe

    keys = (
        "n_specimens",
        "fe_mae_deg",
        "surrogate_mae_deg",
        "fe_vs_surrogate_mae_deg",
        "fe_mae_deg_per_load_case",
        "idp",
        "n_fe_failed_jobs",
    )
    _write_metrics(args, json_safe({k: s[k] for k in keys}))  # only when asked (DVC stage)
    print(f"outputs: {out}/validation.csv, {out}/validation.json, {out}/idp.csv")


def _add_metrics_file(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--metrics-file",
        metavar="PATH",
        help="also write the summary figures to this JSON file (the DVC stage passes its "
        "metrics file, e.g. reports/diagnose.json; an ad-hoc run leaves those untouched)",
    )


def _add_effects_module(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--effects-module",
        action="append",
        metavar="PATH",
        help="a .py file (or folder of them) that registers effects; repeatable (also: "
        "effects.modules in params.yaml)",
    )


def _add_verbosity(p: argparse.ArgumentParser, *, default: object) -> None:
    """``-v/--verbose`` and ``-q/--quiet``, exclusive; given before or after the sub-command."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "-v",
        "--verbose",
        dest="log_level",
        action="store_const",
        const=LOG_LEVELS["verbose"],
        default=default,
        help="also log femcal's debug messages (and other libraries' info)",
    )
    group.add_argument(
        "-q",
        "--quiet",
        dest="log_level",
        action="store_const",
        const=LOG_LEVELS["quiet"],
        default=default,
        help="log warnings and errors only; no progress bars",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="femcal", description=__doc__.splitlines()[0].replace("``", "")
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    parser.add_argument(
        "--params",
        default="params.yaml",
        help="settings file (default: params.yaml). Relative paths in it start at its folder "
        "(the project root), whatever the current folder; the stores (mlflow.store_dir, "
        "train.storage, fe.store) at the repository's root, also from the temporary copy of "
        "`dvc exp run --temp/--queue` (DVC_ROOT); MLFLOW_TRACKING_URI and FEMCAL_OPTUNA_STORAGE "
        "override them. Relative paths given on the command line start at the current folder",
    )
    _add_verbosity(parser, default=LOG_LEVELS["default"])
    # The sub-commands take -v/-q too; given there, they win (absent, they leave the top's).
    common = argparse.ArgumentParser(add_help=False)
    _add_verbosity(common, default=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, **kwargs) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], **kwargs)

    p = command("fetch", help="get the study's FE data (mirror or pinned download)")
    p.add_argument("--out", help="destination folder (default: data.raw_dir)")
    p.set_defaults(func=cmd_fetch)
    command("prepare", help="tidy tables + parameter space").set_defaults(func=cmd_prepare)
    for name, func, helptext in (
        ("train", cmd_train, "Optuna search + final surrogate, logged and registered in MLflow"),
        ("baselines", cmd_baselines, "fit the study's model zoo"),
    ):
        p = command(name, help=helptext)
        p.set_defaults(func=func)
    sub.choices["train"].add_argument(
        "--split",
        required=True,
        help="a section of train in params.yaml (large, small, holdout, ...); it names the run, "
        "and its `split` setting the prepared table trained on (one of "
        f"{', '.join(SPLITS)}; default: the section's name)",
    )
    sub.choices["baselines"].add_argument(
        "--split", required=True, choices=SPLITS, help="the prepared table to fit on"
    )
    command("interpolate", help="train on 1,3,5 Nm, test at 2,4 Nm").set_defaults(
        func=cmd_interpolate
    )
    command("evaluate", help="Test-set table for every surrogate").set_defaults(func=cmd_evaluate)
    command(
        "train-inverse", help="the study's inverse network on surrogate samples (Optuna, MLflow)"
    ).set_defaults(func=cmd_train_inverse)
    p = command("calibrate", help="calibrate measured specimens (registered surrogate)")
    p.add_argument("--dataset", help="a name under calibrate.datasets (default: the first)")
    p.add_argument(
        "--effects",
        metavar="EFFECT[,EFFECT...]",
        help="comma-separated physical effects added to the disc (default: the dataset's "
        "effects in params.yaml; none for --measurements); '' = the disc alone. Built in: "
        f"{', '.join(BUILTIN_EFFECTS)}; installed plugins and --effects-module files add more",
    )
    p.add_argument("--measurements", help="long or wide CSV, or a folder of the study's files")
    p.add_argument("--out", help="output folder (default: calibrate.out_dir/<dataset>)")
    p.add_argument(
        "--method", choices=CALIBRATORS, help="calibration method (default: calibrate.method)"
    )
    p.add_argument("--model-uri", help="MLflow model URI (default: calibrate.model_uri)")
    p.add_argument("--model-version", help="version of the registered surrogate")
    p.add_argument("--model-alias", help="alias of the registered surrogate")
    p.add_argument("--holdout-uri", help="held-out surrogate URI (default: calibrate.holdout_uri)")
    p.add_argument("--no-holdout", action="store_true", help="skip the held-out re-evaluation")
    p.add_argument("--seed", type=int, help="seed (default: calibrate.seed)")
    p.add_argument(
        "--plots",
        choices=PLOT_CHOICES,
        help="figures to write: all (plots/<specimen>.png for the first calibrate.max_plots "
        "specimens, and summary.png), summary (summary.png only) or none; the tables, "
        "curves.csv and summary.md/json are always written (default: calibrate.plots, "
        "true = all, false = none)",
    )
    _add_metrics_file(p)
    _add_effects_module(p)
    p.set_defaults(func=cmd_calibrate)
    command("plant", help="a cohort with hidden effects from FE curves").set_defaults(
        func=cmd_plant
    )
    p = command("diagnose", help="where the model fails; which effect is missing")
    p.add_argument("--measurements", help="measurement file (default: diagnose.measurements)")
    p.add_argument("--out", help="output folder (default: diagnose.out_dir)")
    p.add_argument("--noise-deg", type=float, help="measurement noise sd (default: estimated)")
    p.add_argument("--model-uri", help="MLflow model URI (default: calibrate.model_uri)")
    _add_metrics_file(p)
    _add_effects_module(p)
    p.set_defaults(func=cmd_diagnose)
    p = command("simulate", help="FE campaign on Dask -> dataset in the study's layout")
    p.add_argument("--out", help="dataset folder (default: fe.out_dir)")
    p.add_argument("--store", help="campaign store, JSON lines (default: fe.store)")
    _add_metrics_file(p)
    p.set_defaults(func=cmd_simulate)
    p = command("validate", help="FE re-simulation of calibrated parameters; IDP check")
    p.add_argument("--calibration", help="calibration folder (default: validate.calibration_dir)")
    p.add_argument("--measurements", help="measurements calibrated to (validate.measurements)")
    p.add_argument("--out", help="output folder (default: validate.out_dir)")
    p.add_argument("--store", help="campaign store of the FE runs (default: validate.store)")
    _add_metrics_file(p)
    p.set_defaults(func=cmd_validate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.log_level)
    try:
        params = load_params(args.params)  # validated against femcal.settings' schema
        from femcal.settings import check_environment

        check_environment(args.command)  # the variables this command reads
        args.func(args, params)
    except FemcalError as exc:
        print(f"femcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
