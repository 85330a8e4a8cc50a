"""What several stages share: settings read at the edge, the stores, checks before heavy work.

Relative paths in params.yaml start at its folder (the project root), paths typed on the
command line at the current folder, and the stores (``mlflow.store_dir``, ``train.storage``,
``fe.store``) at the repository's root (:mod:`femcal.paths`). Nothing here imports torch,
Lightning or MLflow at module level, so that a bad setting is the first error, within a second.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from femcal.config import section
from femcal.errors import ConfigError, InputDataError
from femcal.paths import setting_path, store_path, store_url
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

SPACE_FILE = "parameter_space.json"


def path_setting(params: Mapping[str, Any], *keys: str) -> Path:
    """A path setting of params.yaml, relative to the project root (:mod:`femcal.paths`)."""
    return setting_path(params, section(params, *keys))


def tracking(params: Mapping[str, Any]) -> None:
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


def check_outputs(out: str | Path, *, label: str, metrics_file: str | None = None) -> Path:
    """The output folder and the metrics file, checked before any heavy work."""
    from femcal.outputs import check_destination, check_file_destination

    path = check_destination(out, label=label)
    if metrics_file:
        check_file_destination(metrics_file, label="--metrics-file")
    return path


def out_label(given: str | None, setting: str) -> str:
    """How an output folder is named in messages: ``--out`` or the setting it comes from."""
    return "--out" if given else f"output folder ({setting})"


def check_measurements(path: Path) -> None:
    """A missing measurement file or folder, reported before any heavy import."""
    if not path.exists():
        raise InputDataError(
            f"Measurement file {path} does not exist; check the path (relative paths on the "
            f"command line start at the current folder {Path.cwd()}, in params.yaml at its "
            "folder)."
        )


def write_metrics(path: str | Path | None, figures: Mapping[str, Any]) -> None:
    """A stage's DVC metrics file (``--metrics-file``), written whole or not at all."""
    if path:
        from femcal.outputs import write_text_atomic

        write_text_atomic(path, json.dumps(figures, indent=2) + "\n")


def effect_modules(params: Mapping[str, Any], given: Sequence[str] | None) -> tuple[Path, ...]:
    """The user's effect files: ``effects.modules`` in params.yaml (relative to its folder, the
    project root), then every ``--effects-module`` (relative to the working directory)."""
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
    return tuple([root / m for m in modules or []] + [Path(m) for m in given or []])


def load_user_effects(paths: Sequence[Path]) -> list[str]:
    """Import the user's effect files before anything uses the effect registry; the names."""
    if not paths:
        return []
    from femcal.effects import load_effect_modules

    return load_effect_modules(list(paths))


def describe_user_effects(names: Sequence[str], paths: Sequence[Path]) -> list[str]:
    """The line that says which user effects were loaded (none: no line)."""
    if not names:
        return []
    return [f"user effects: {', '.join(names)} (from {', '.join(str(p) for p in paths)})"]


def optuna_storage(params: Mapping[str, Any]) -> str:
    """FEMCAL_OPTUNA_STORAGE as given, else train.storage (a relative SQLite file under the
    repository's root, :func:`femcal.paths.store_url`); a SQLite file's folder is created."""
    storage = os.environ.get("FEMCAL_OPTUNA_STORAGE") or store_url(
        params, section(params, "train", "storage")
    )
    file = storage[len("sqlite:///") :] if storage.startswith("sqlite:///") else ""
    if file and file != ":memory:":
        Path(file).parent.mkdir(parents=True, exist_ok=True)
    return storage


def moment_settings(params: Mapping[str, Any]) -> dict[str, float]:
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


def fe_runtime(params: Mapping[str, Any]) -> tuple[str | None, int]:
    """Scheduler address (fe.scheduler_address, else FEMCAL_DASK_ADDRESS) and worker count."""
    from femcal.fe.campaign import scheduler_address_from_env

    cfg = section(params, "fe")
    address = cfg.get("scheduler_address") or scheduler_address_from_env()
    return address, int(cfg.get("n_workers", 2))


def load_split(prepared_dir: Path, split: str):
    """Read a prepared split and the parameter space."""
    from femcal.prepare import load_tidy

    space = ParameterSpace.from_json(prepared_dir / SPACE_FILE)
    return load_tidy(prepared_dir / f"{split}.csv", space), space


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


def export_folder(result, out_dir: Path, registered_model: str | None) -> None:
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
