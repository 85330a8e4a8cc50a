"""Checks of single values with their own rules: URLs, addresses, names, paths, moments.

Each ``*_problem`` function says why a string is not usable (None when it is), in words that
name the fix; :data:`SQL_URL`, :data:`DASK_ADDRESS` and :data:`MODEL_URI` are the checks
built on them, and the environment variables (:mod:`femcal.settings.env`) use them too.
:data:`PATH`, :data:`NAME`, :data:`DATASET_NAME`, :data:`N_JOBS` and :data:`MOMENTS` are the
other value checks of the sections.
"""

from __future__ import annotations

import re
import urllib.parse
from collections.abc import Callable
from typing import Any

from femcal.settings._checks import Check, Float, FnCheck, ListOf, Str
from femcal.settings._messages import Context, Invalid, closest, got, yaml_repr

#: SQLAlchemy dialects (their common spellings), for suggestions.
_SQL_DIALECTS = ("sqlite", "postgresql", "mysql", "mariadb", "oracle", "mssql", "cockroachdb")
_SQL_URL = re.compile(r"^(?P<dialect>[A-Za-z][A-Za-z0-9_]*)(?:\+(?P<driver>[A-Za-z0-9_]+))?://")
_SQL_EXAMPLES = "e.g. sqlite:///mlruns/optuna.db or postgresql://user:password@host/optuna"


def sqlalchemy_url_problem(value: str) -> str | None:
    """Why ``value`` is not a usable SQLAlchemy database URL (None when it is)."""
    if value != value.strip():
        return f"it has spaces around it; write {value.strip()!r}"
    m = _SQL_URL.match(value)
    if m is None:
        if "://" not in value and (value.endswith((".db", ".sqlite", ".sqlite3")) or "/" in value):
            return f"not a SQLAlchemy URL; for a SQLite file write sqlite:///{value}"
        return f"not a SQLAlchemy URL (dialect[+driver]://...); {_SQL_EXAMPLES}"
    dialect, rest = m["dialect"].lower(), value[m.end() :]
    if dialect == "postgres":
        return f"SQLAlchemy names this dialect postgresql; write postgresql://{rest}"
    if dialect not in _SQL_DIALECTS:
        close = closest(dialect, _SQL_DIALECTS)
        if close is not None:
            return f"unknown database dialect {dialect!r}; did you mean {close}://{rest}?"
    if dialect == "sqlite":
        if not rest or rest in ("/", "/:memory:"):
            return (
                "an in-memory SQLite database forgets the study when the process ends; name a "
                "file, e.g. sqlite:///mlruns/optuna.db"
            )
        if not rest.startswith("/"):
            return f"a SQLite URL has three slashes before a relative path: sqlite:///{rest}"
    return None


_DASK_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")
_DASK_ADDRESS = re.compile(
    r"^(?P<scheme>[A-Za-z]+)://(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+)(?::(?P<port>\d+))?/?$"
)


def dask_address_problem(value: str) -> str | None:
    """Why ``value`` is not a Dask scheduler address ``tcp://host:port`` (None when it is)."""
    value = value.strip()
    if value.startswith("inproc://"):
        return None
    m = _DASK_ADDRESS.match(value)
    if m is None:
        if "://" not in value and re.match(r"^[^\s:/]+:\d+$", value):
            return f"no protocol; write tcp://{value}"
        return "not a Dask scheduler address; write tcp://host:port, e.g. tcp://login-node:8786"
    scheme, port = m["scheme"].lower(), m["port"]
    if scheme not in _DASK_SCHEMES:
        return (
            f"unknown protocol {scheme}://; use one of "
            f"{', '.join(s + '://' for s in _DASK_SCHEMES)}, e.g. tcp://{m['host']}:8786"
        )
    if port is None:
        return f"no port; write {scheme}://{m['host']}:8786 (the scheduler's default port)"
    if not 1 <= int(port) <= 65535:
        return f"port {port} is not in 1..65535"
    return None


_MLFLOW_SCHEMES = ("http", "https", "file", "databricks", "databricks-uc", "uc")


def mlflow_tracking_uri_problem(value: str) -> str | None:
    """Why ``value`` is not an MLflow tracking URI MLflow can use (None when it is)."""
    if value != value.strip():
        return f"it has spaces around it; write {value.strip()!r}"
    if value in ("databricks", "databricks-uc", "uc"):
        return None
    if "://" not in value:
        if re.match(r"^[A-Za-z0-9.-]+:\d+(/.*)?$", value):
            return f"no scheme, so MLflow would read it as a folder; write http://{value}"
        return None  # a local folder (a file store)
    scheme = urllib.parse.urlsplit(value).scheme.lower()
    base = scheme.split("+", 1)[0]
    if scheme in ("http", "https"):
        if not urllib.parse.urlsplit(value).netloc:
            return f"no host; write {scheme}://host:5000"
        return None
    if scheme in _MLFLOW_SCHEMES:
        return None
    if base in _SQL_DIALECTS or base == "postgres":
        return sqlalchemy_url_problem(value)
    close = closest(scheme, [*_MLFLOW_SCHEMES, *_SQL_DIALECTS])
    fix = f"; did you mean {close}://?" if close else ""
    return (
        f"unknown scheme {scheme}://{fix} (a tracking server http(s)://host:port, a database "
        "sqlite:///path/mlflow.db or postgresql://..., or a folder)"
    )


def model_uri_problem(value: str) -> str | None:
    """Why ``value`` is not an MLflow model URI (None when it looks like one)."""
    if value.startswith("models:"):
        if re.match(r"^models:/[^/@\s]+(@[^/@\s]+|/[^/@\s]+)$", value):
            return None
        return (
            "expected models:/NAME@ALIAS or models:/NAME/VERSION, e.g. "
            "models:/ivd-rom-surrogate@champion"
        )
    if value.startswith("runs:"):
        if re.match(r"^runs:/[0-9A-Za-z]+/.+$", value):
            return None
        return "expected runs:/RUN_ID/ARTIFACT_PATH"
    if re.match(r"^(model|modles|modells):/", value):
        return f"did you mean models:/{value.split(':/', 1)[1]}?"
    if "@" in value and "/" not in value and "://" not in value:
        return f"did you mean models:/{value}?"
    return None  # a path or another artifact URI


def _url_check(describe: str, problem: Callable[[str], str | None]) -> Check:
    def check(value: Any, path: tuple, ctx: Context) -> str:
        if not isinstance(value, str):
            raise Invalid(f"expected {describe}, got {got(value)}")
        why = problem(value)
        if why is not None:
            raise Invalid(f"expected {describe}, got {yaml_repr(value)}: {why}")
        return value

    return FnCheck(describe, check)


SQL_URL = _url_check("a SQLAlchemy database URL", sqlalchemy_url_problem)
DASK_ADDRESS = _url_check("a Dask scheduler address tcp://host:port", dask_address_problem)
MODEL_URI = _url_check("an MLflow model URI (models:/NAME@ALIAS)", model_uri_problem)
PATH = Str("a path (a non-empty string)")
NAME = Str("a non-empty name")
#: A list of moments in Nm (positive, each once).
MOMENTS = ListOf(Float(0, lo_open=True), min_len=1, unique=True)


def _dataset_name(value: Any, path: tuple, ctx: Context) -> str:
    if not isinstance(value, str) or not _DATASET_NAME.match(value):
        raise Invalid(
            f"dataset name {yaml_repr(value)} must start with a letter or digit and hold only "
            "letters, digits, '_', '.' and '-' (it names the stage calibrate@<name> and "
            "reports/calibrate-<name>.json)"
        )
    return value


def _n_jobs(value: Any, path: tuple, ctx: Context) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not (value >= 1 or value == -1):
        raise Invalid(f"expected an integer >= 1, or -1 (all cores), got {got(value)}")
    return value


_DATASET_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: A dataset name: it names the stage calibrate@<name> and reports/calibrate-<name>.json.
DATASET_NAME = FnCheck("a dataset name", _dataset_name)
#: Parallel jobs: an integer >= 1, or -1 for all cores.
N_JOBS = FnCheck("an integer >= 1, or -1 (all cores)", _n_jobs)
