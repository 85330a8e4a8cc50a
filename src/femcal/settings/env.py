"""The environment variables femcal reads (:class:`Environment`), and :func:`check_environment`."""

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator, Field, TypeAdapter, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from femcal.errors import ConfigError
from femcal.settings.values import (
    dask_address_problem,
    mlflow_tracking_uri_problem,
    sqlalchemy_url_problem,
)


def _mirror_problem(value: str) -> str | None:
    path = Path(value.strip()).expanduser()
    if not path.exists():
        return f"{path.resolve()} does not exist"
    if not path.is_dir():
        return f"{path.resolve()} is a file, not a folder"
    if not any((path / split).is_dir() for split in ("Large", "Small", "Test")):
        return f"{path.resolve()} holds none of Large/, Small/, Test/"
    return None


def _checked(problem: Any) -> Any:
    def check(value: str | None) -> str | None:
        why = problem(value) if value is not None and value.strip() else None
        if why is not None:
            raise ValueError(why)
        return value if value is None or value.strip() else None

    return Annotated[str | None, AfterValidator(check)]


def _var(doc: str, *commands: str) -> Any:
    return Field(None, description=doc, json_schema_extra={"commands": commands})


_TRACKING = (
    *("train", "baselines", "interpolate", "evaluate", "train-inverse", "calibrate"),
    *("diagnose", "validate"),
)


class Environment(BaseSettings):
    """The environment variables femcal reads (each None when unset or blank)."""

    model_config = SettingsConfigDict(case_sensitive=True, extra="ignore", frozen=True)

    FEMCAL_DATA_MIRROR: _checked(_mirror_problem) = _var(
        "a local folder holding the study's Large/, Small/ and Test/ (instead of the download); "
        "set it to that folder (the study's datasets/), or unset it to download",
        "fetch",
    )
    FEMCAL_OPTUNA_STORAGE: _checked(sqlalchemy_url_problem) = _var(
        "the Optuna storage, a SQLAlchemy URL (overrides train.storage); e.g. "
        "postgresql://user:password@host/optuna, or unset it to use train.storage",
        "train",
        "train-inverse",
    )
    FEMCAL_DASK_ADDRESS: _checked(dask_address_problem) = _var(
        "the Dask scheduler of the FE campaign, tcp://host:port (when fe.scheduler_address is "
        "null); e.g. tcp://login-node:8786, or unset it for a local cluster",
        "simulate",
        "validate",
    )
    MLFLOW_TRACKING_URI: _checked(mlflow_tracking_uri_problem) = _var(
        "the MLflow tracking server or database (overrides mlflow.store_dir); e.g. "
        "http://mlflow-server:5000, or unset it to use the project's store",
        *_TRACKING,
    )


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
        The environment (default: the process's, read by :class:`Environment`).

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
    for name, info in Environment.model_fields.items():
        value = environ.get(name, "")
        if (command is not None and command not in ENVIRONMENT[name].commands) or not value.strip():
            continue
        try:  # this variable alone, as given (a BaseSettings would read the process's too)
            TypeAdapter(info.rebuild_annotation()).validate_python(value)
        except ValidationError as exc:
            why = exc.errors(include_url=False)[0]["ctx"]["error"]
            problems.append(f"{name}={value!r}: {why}. {name} is {info.description}.")
            continue
        found[name] = value
    if len(problems) == 1:
        raise ConfigError(f"Environment variable {problems[0]}")
    if problems:
        listing = "\n".join(f"  {p}" for p in problems)
        raise ConfigError(f"Invalid environment variables:\n{listing}")
    return found


@dataclass(frozen=True)
class EnvVar:
    """An environment variable femcal reads: its doc and the commands reading it."""

    name: str
    doc: str
    commands: tuple[str, ...]


#: The environment variables femcal reads, by name.
ENVIRONMENT: dict[str, EnvVar] = {
    name: EnvVar(name, f.description, f.json_schema_extra["commands"])
    for name, f in Environment.model_fields.items()
}
