"""The environment variables femcal reads, and :func:`check_environment`."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from femcal.errors import ConfigError
from femcal.settings.values import (
    dask_address_problem,
    mlflow_tracking_uri_problem,
    sqlalchemy_url_problem,
)


@dataclass(frozen=True)
class EnvVar:
    """An environment variable femcal reads: its doc, its check and the commands reading it."""

    name: str
    doc: str
    problem: Callable[[str], str | None]
    commands: tuple[str, ...]


def _mirror_problem(value: str) -> str | None:
    path = Path(value.strip()).expanduser()
    if not path.exists():
        return f"{path.resolve()} does not exist"
    if not path.is_dir():
        return f"{path.resolve()} is a file, not a folder"
    if not any((path / split).is_dir() for split in ("Large", "Small", "Test")):
        return f"{path.resolve()} holds none of Large/, Small/, Test/"
    return None


_TRACKING = (
    "train",
    "baselines",
    "interpolate",
    "evaluate",
    "train-inverse",
    "calibrate",
    "diagnose",
    "validate",
)

#: The environment variables femcal reads, by name.
ENVIRONMENT: dict[str, EnvVar] = {
    v.name: v
    for v in (
        EnvVar(
            "FEMCAL_DATA_MIRROR",
            "a local folder holding the study's Large/, Small/ and Test/ (instead of the "
            "download); set it to that folder (the study's datasets/), or unset it to download",
            _mirror_problem,
            ("fetch",),
        ),
        EnvVar(
            "FEMCAL_OPTUNA_STORAGE",
            "the Optuna storage, a SQLAlchemy URL (overrides train.storage); e.g. "
            "postgresql://user:password@host/optuna, or unset it to use train.storage",
            sqlalchemy_url_problem,
            ("train", "train-inverse"),
        ),
        EnvVar(
            "FEMCAL_DASK_ADDRESS",
            "the Dask scheduler of the FE campaign, tcp://host:port (when fe.scheduler_address "
            "is null); e.g. tcp://login-node:8786, or unset it for a local cluster",
            dask_address_problem,
            ("simulate", "validate"),
        ),
        EnvVar(
            "MLFLOW_TRACKING_URI",
            "the MLflow tracking server or database (overrides mlflow.store_dir); e.g. "
            "http://mlflow-server:5000, or unset it to use the project's store",
            mlflow_tracking_uri_problem,
            _TRACKING,
        ),
    )
}


def check_environment(
    command: str | None = None, environ: Mapping[str, str] | None = None
) -> dict[str, str]:
    """Validate the environment variables ``command`` reads (all of femcal's when None).

    An empty or blank variable counts as unset, as where it is read.

    Parameters
    ----------
    command : str, optional
        A ``femcal`` sub-command, e.g. ``"fetch"``.
    environ : mapping, optional
        The environment (default: :data:`os.environ`).

    Returns
    -------
    dict
        The variables that are set, name -> value.

    Raises
    ------
    ConfigError
        Naming every bad variable, its value, what is wrong and the fix.
    """
    environ = os.environ if environ is None else environ
    found, problems = {}, []
    for var in ENVIRONMENT.values():
        if command is not None and command not in var.commands:
            continue
        value = environ.get(var.name, "")
        if not value.strip():
            continue
        why = var.problem(value)
        if why is None:
            found[var.name] = value
        else:
            problems.append(f"{var.name}={value!r}: {why}. {var.name} is {var.doc}.")
    if len(problems) == 1:
        raise ConfigError(f"Environment variable {problems[0]}")
    if problems:
        raise ConfigError(
            "Invalid environment variables:\n" + "\n".join(f"  {p}" for p in problems)
        )
    return found
