"""The environment variables femcal reads (:data:`ENVIRONMENT`), and :func:`check_environment`."""

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from femcal.errors import ConfigError
from femcal.settings.values import dask_address_problem as _dask
from femcal.settings.values import mlflow_tracking_uri_problem as _mlflow
from femcal.settings.values import sqlalchemy_url_problem as _sql


def _mirror_problem(value: str) -> str | None:
    path = Path(value.strip()).expanduser()
    if not path.is_dir():
        return (
            f"{path.resolve()} {'is a file, not a folder' if path.exists() else 'does not exist'}"
        )
    if not any((path / split).is_dir() for split in ("Large", "Small", "Test")):
        return f"{path.resolve()} holds none of Large/, Small/, Test/"
    return None


@dataclass(frozen=True)
class EnvVar:
    """An environment variable femcal reads: its doc, the commands reading it, and why a
    value is unusable (None when it is)."""

    name: str
    doc: str
    commands: tuple[str, ...]
    problem: Callable[[str], str | None] = field(repr=False)


_TRACKING = ("train", "baselines", "interpolate", "evaluate", "train-inverse", "calibrate")
_MIRROR = "a local folder holding the study's Large/, Small/ and Test/ (instead of the download)"
#: The environment variables femcal reads, by name.
ENVIRONMENT: dict[str, EnvVar] = {
    var.name: var
    for var in (
        EnvVar(
            "FEMCAL_DATA_MIRROR",
            f"{_MIRROR}; set it to that folder (the study's datasets/), or unset it to download",
            ("fetch",),
            _mirror_problem,
        ),
        EnvVar(
            "FEMCAL_OPTUNA_STORAGE",
            "the Optuna storage, a SQLAlchemy URL (overrides train.storage); e.g. "
            "postgresql://user:password@host/optuna, or unset it to use train.storage",
            ("train", "train-inverse"),
            _sql,
        ),
        EnvVar(
            "FEMCAL_DASK_ADDRESS",
            "the Dask scheduler of the FE campaign, tcp://host:port (when fe.scheduler_address "
            "is null); e.g. tcp://login-node:8786, or unset it for a local cluster",
            ("simulate", "validate"),
            _dask,
        ),
        EnvVar(
            "MLFLOW_TRACKING_URI",
            "the MLflow tracking server or database (overrides mlflow.store_dir); e.g. "
            "http://mlflow-server:5000, or unset it to use the project's store",
            (*_TRACKING, "diagnose", "validate"),
            _mlflow,
        ),
    )
}


def check_environment(
    command: str | None = None, environ: Mapping[str, str] | None = None
) -> dict[str, str]:
    """The variables (name -> value) that the sub-command ``command`` reads (None: all of
    femcal's) set in ``environ`` (default: the process's), each checked; an empty or blank
    variable counts as unset, as where it is read. ConfigError: every bad variable, its value,
    what is wrong and the fix."""
    environ = os.environ if environ is None else environ
    found, problems = {}, []
    for name, var in ENVIRONMENT.items():
        value = environ.get(name, "")
        if (command is not None and command not in var.commands) or not value.strip():
            continue
        why = var.problem(value)
        if why is None:
            found[name] = value
        else:
            problems.append(f"{name}={value!r}: {why}. {name} is {var.doc}.")
    if len(problems) == 1:
        raise ConfigError(f"Environment variable {problems[0]}")
    if problems:
        listing = "\n".join(f"  {p}" for p in problems)
        raise ConfigError(f"Invalid environment variables:\n{listing}")
    return found
