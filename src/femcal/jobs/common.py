"""What both jobs read alike from a loaded params.yaml."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any

from femcal.config import settings_of
from femcal.errors import ConfigError


def with_given(job: type, read: Mapping[str, Any], given: Mapping[str, Any]) -> dict[str, Any]:
    """The keywords of the dataclass ``job``: those read from params.yaml, ``given`` winning.

    Raises
    ------
    ConfigError
        A key of ``given`` is not a field of ``job``.
    """
    known = [f.name for f in fields(job)]
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ConfigError(
            f"{job.__name__}.from_params: {', '.join(unknown)} is not a field of "
            f"{job.__name__}; its fields are {', '.join(known)}. Fix the keyword's name."
        )
    return {**read, **given}


def moment_policy(params: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
    """params.yaml's ``moments`` section as keywords: ``error_growth`` and ``max_log_ratio``,
    ``(below, above)`` each."""
    moments = settings_of(params).require("moments")
    return {k: getattr(moments, k).pair() for k in ("error_growth", "max_log_ratio")}


def use_project_store(params: Mapping[str, Any]) -> None:
    """Point MLflow at params.yaml's store and experiment, as femcal's commands do.

    The store is ``mlflow.store_dir`` (:func:`femcal.paths.store_path`;
    ``MLFLOW_TRACKING_URI`` wins, :func:`femcal.tracking.configure_tracking`). Runs started
    from now on are tagged with this process, and runs of killed processes are closed
    (:mod:`femcal.tracking_runs`).
    """
    from femcal.paths import store_path
    from femcal.tracking import configure_tracking, ensure_experiment
    from femcal.tracking_runs import close_killed_runs, tag_runs_with_process

    mlflow = settings_of(params).require("mlflow", "store_dir", "experiment")
    store = store_path(params, mlflow.store_dir)
    configure_tracking(store_dir=store)
    experiment = ensure_experiment(mlflow.experiment, store_dir=store)
    tag_runs_with_process()  # pid + host on every run this process starts
    close_killed_runs([experiment])  # logs each run it closes as KILLED


def use_project(params: Mapping[str, Any]) -> list[str]:
    """Set this process up as ``femcal calibrate`` and ``femcal diagnose`` are: MLflow pointed
    at params.yaml's store and experiment (:func:`use_project_store`), the user's effect
    modules (``effects.modules``, relative to params.yaml's folder) imported.

    Returns
    -------
    list of str
        The effects the user's modules registered.
    """
    use_project_store(params)
    effects = settings_of(params).effects
    modules = effects.modules if effects is not None else ()
    if not modules:
        return []
    from femcal.effects import load_effect_modules

    root = Path(params.get("_path", "params.yaml")).parent
    return load_effect_modules([root / m for m in modules])
