"""Value types (numbers with bounds, lists, names, paths, URLs: each ``*_problem`` says why
a string is unusable and the fix), the environment variables femcal reads (:data:`ENVIRONMENT`,
:func:`check_environment`), the bases :class:`Section` and :class:`Keywords`, and the options
of options dataclasses (:func:`option`, :func:`check_options`, :func:`with_options`)."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import importlib.util
import os
import re
import sys
import urllib.parse
from collections import ChainMap
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    PrivateAttr,
    Strict,
    StrictBool,
    TypeAdapter,
    ValidationError,
    WrapValidator,
    create_model,
    model_validator,
)

from femcal.errors import ConfigError
from femcal.settings import _format as fmt
from femcal.settings._format import fail

#: SQLAlchemy dialects (their common spellings), for suggestions.
_SQL_DIALECTS = ("sqlite", "postgresql", "mysql", "mariadb", "oracle", "mssql", "cockroachdb")
_SQL_URL = re.compile(r"^(?P<dialect>[A-Za-z][A-Za-z0-9_]*)(?:\+(?P<driver>[A-Za-z0-9_]+))?://")


def sqlalchemy_url_problem(value: str) -> str | None:
    """Why ``value`` is not a usable SQLAlchemy database URL (None when it is)."""
    if value != value.strip():
        return f"it has spaces around it; write {value.strip()!r}"
    m = _SQL_URL.match(value)
    if m is None:
        if "://" not in value and (value.endswith((".db", ".sqlite", ".sqlite3")) or "/" in value):
            return f"not a SQLAlchemy URL; for a SQLite file write sqlite:///{value}"
        e_g = "e.g. sqlite:///mlruns/optuna.db or postgresql://user:password@host/optuna"
        return f"not a SQLAlchemy URL (dialect[+driver]://...); {e_g}"
    dialect, rest = m["dialect"].lower(), value[m.end() :]
    if dialect == "postgres":
        return f"SQLAlchemy names this dialect postgresql; write postgresql://{rest}"
    close = fmt.closest(dialect, _SQL_DIALECTS) if dialect not in _SQL_DIALECTS else None
    if close is not None:
        return f"unknown database dialect {dialect!r}; did you mean {close}://{rest}?"
    if dialect == "sqlite" and (not rest or rest in ("/", "/:memory:")):
        memory = "an in-memory SQLite database forgets the study when the process ends"
        return f"{memory}; name a file, e.g. sqlite:///mlruns/optuna.db"
    if dialect == "sqlite" and not rest.startswith("/"):
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
        schemes = ", ".join(s + "://" for s in _DASK_SCHEMES)
        return f"unknown protocol {scheme}://; use one of {schemes}, e.g. tcp://{m['host']}:8786"
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
    if "://" not in value:  # a local folder (a file store) or databricks, unless host:port
        if re.match(r"^[A-Za-z0-9.-]+:\d+(/.*)?$", value):
            return f"no scheme, so MLflow would read it as a folder; write http://{value}"
        return None
    scheme = urllib.parse.urlsplit(value).scheme.lower()
    base = scheme.split("+", 1)[0]
    if scheme in ("http", "https") and not urllib.parse.urlsplit(value).netloc:
        return f"no host; write {scheme}://host:5000"
    if scheme in _MLFLOW_SCHEMES:
        return None
    if base in _SQL_DIALECTS or base == "postgres":
        return sqlalchemy_url_problem(value)
    close = fmt.closest(scheme, [*_MLFLOW_SCHEMES, *_SQL_DIALECTS])
    fix = f"; did you mean {close}://?" if close else ""
    return (
        f"unknown scheme {scheme}://{fix} (a tracking server http(s)://host:port, a database "
        "sqlite:///path/mlflow.db or postgresql://..., or a folder)"
    )


def model_uri_problem(value: str) -> str | None:
    """Why ``value`` is not an MLflow model URI (None when it looks like one)."""
    models = re.match(r"^models:/[^/@\s]+(@[^/@\s]+|/[^/@\s]+)$", value)
    if value.startswith("models:") and not models:
        e_g = "e.g. models:/ivd-rom-surrogate@champion"
        return f"expected models:/NAME@ALIAS or models:/NAME/VERSION, {e_g}"
    if value.startswith("runs:") and not re.match(r"^runs:/[0-9A-Za-z]+/.+$", value):
        return "expected runs:/RUN_ID/ARTIFACT_PATH"
    if re.match(r"^(model|modles|modells):/", value):
        return f"did you mean models:/{value.split(':/', 1)[1]}?"
    if "@" in value and "/" not in value and "://" not in value:
        return f"did you mean models:/{value}?"
    return None  # a path or another artifact URI


# ---------------------------------------------------------------------- the environment
def _mirror_problem(value: str) -> str | None:
    path = Path(value.strip()).expanduser()
    if not path.is_dir():
        return (
            f"{path.resolve()} {'is a file, not a folder' if path.exists() else 'does not exist'}"
        )
    if not any((path / split).is_dir() for split in ("Large", "Small", "Test")):
        return f"{path.resolve()} holds none of Large/, Small/, Test/"
    return None


@dataclasses.dataclass(frozen=True)
class EnvVar:
    """An environment variable femcal reads: its doc, the commands reading it, and why a
    value is unusable (None when it is)."""

    name: str
    doc: str
    commands: tuple[str, ...]
    problem: Callable[[str], str | None] = dataclasses.field(repr=False)


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
            sqlalchemy_url_problem,
        ),
        EnvVar(
            "FEMCAL_DASK_ADDRESS",
            "the Dask scheduler of the FE campaign, tcp://host:port (when fe.scheduler_address "
            "is null); e.g. tcp://login-node:8786, or unset it for a local cluster",
            ("simulate", "validate"),
            dask_address_problem,
        ),
        EnvVar(
            "MLFLOW_TRACKING_URI",
            "the MLflow tracking server or database (overrides mlflow.store_dir); e.g. "
            "http://mlflow-server:5000, or unset it to use the project's store",
            (*_TRACKING, "diagnose", "validate"),
            mlflow_tracking_uri_problem,
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
    read = {n: v for n, v in ENVIRONMENT.items() if command is None or command in v.commands}
    found = {n: environ[n] for n in read if environ.get(n, "").strip()}
    whys = {n: read[n].problem(value) for n, value in found.items()}
    problems = [f"{n}={found[n]!r}: {w}. {n} is {read[n].doc}." for n, w in whys.items() if w]
    if len(problems) == 1:
        raise ConfigError(f"Environment variable {problems[0]}")
    if problems:
        listing = "\n".join(f"  {p}" for p in problems)
        raise ConfigError(f"Invalid environment variables:\n{listing}")
    return found


# ----------------------------------------------------------------------------- values
#: ``true`` or ``false``.
Bool = StrictBool


def Int(ge: int | None = None, le: int | None = None) -> Any:  # noqa: N802 (a type)
    """An integer (not a bool) in ``[ge, le]``."""
    return Annotated[int, Strict(), Field(ge=ge, le=le)]


def Float(ge: float | None = None, le: float | None = None, **open_: float) -> Any:  # noqa: N802
    """A finite number (a YAML int or float, not a bool) in ``[ge, le]`` (``gt``, ``lt``)."""
    return Annotated[float, Strict(), Field(ge=ge, le=le, **open_, allow_inf_nan=False)]


_Unique = type("_Unique", (), {"unique": True})  # ListOf's mark: describe says "no repeats"


def _unique(value: tuple) -> tuple:
    for v in (v for i, v in enumerate(value) if v in value[:i]):
        raise fail(f"{fmt.yaml_repr(v)} is listed twice in {fmt.yaml_repr(value)}; list each once")
    return value


def ListOf(item: Any, *, min_len: int = 0, unique: bool = False) -> Any:  # noqa: N802
    """A YAML list whose items are ``item``s, as a tuple."""
    more = (AfterValidator(_unique), _Unique()) if unique else ()
    return Annotated[(tuple[item, ...], Field(min_length=min_len), *more)]


def Text(what: str, problem: Callable[[str], str | None] | None = None) -> Any:  # noqa: N802
    """A non-empty string; ``what`` names it in messages, ``problem`` says why it is unusable."""

    def check(value: Any) -> str:
        if not isinstance(value, str) or not value.strip():
            raise fail(f"expected {what}, got {fmt.got(value)}")
        why = problem(value) if problem else None
        if why is not None:
            raise fail(f"expected {what}, got {fmt.yaml_repr(value)}: {why}")
        return value

    return Annotated[str, PlainValidator(check), fmt.Doc(what)]


def _n_jobs(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not (value >= 1 or value == -1):
        raise fail(f"expected an integer >= 1, or -1 (all cores), got {fmt.got(value)}")
    return value


def _dataset_name(value: Any) -> str:
    if isinstance(value, str) and re.match(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", value):
        return value
    why = "must start with a letter or digit and hold only letters, digits, '_', '.' and '-'"
    why += " (it names the stage calibrate@<name> and reports/calibrate-<name>.json)"
    raise fail(f"dataset name {fmt.yaml_repr(value)} {why}")


SQL_URL = Text("a SQLAlchemy database URL", sqlalchemy_url_problem)
DASK_ADDRESS = Text("a Dask scheduler address tcp://host:port", dask_address_problem)
MODEL_URI = Text("an MLflow model URI (models:/NAME@ALIAS)", model_uri_problem)
PATH = Text("a path (a non-empty string)")
NAME = Text("a non-empty name")
MOMENTS = ListOf(Float(gt=0), min_len=1, unique=True)  # Nm
DATASET_NAME = Annotated[str, PlainValidator(_dataset_name), fmt.Doc("a dataset name")]
N_JOBS = Annotated[int, PlainValidator(_n_jobs), fmt.Doc("an integer >= 1, or -1 (all cores)")]


def light_class(module: str, name: str) -> type:
    """``femcal.<module>.<name>``, from its file alone while its package (which imports
    torch) is not loaded, so that validating stays light; that file imports nothing heavy."""
    full = f"femcal.{module}"
    if full.rsplit(".", 1)[0] in sys.modules:
        return getattr(importlib.import_module(full), name)
    private = f"femcal.settings._light.{module}"
    if private not in sys.modules:
        path = Path(__file__).parents[1].joinpath(*module.split(".")).with_suffix(".py")
        spec = importlib.util.spec_from_file_location(private, path)
        sys.modules[private] = loaded = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(loaded)
    return getattr(sys.modules[private], name)


# ----------------------------------------------------------------------- sections, keywords
def setting(doc: str, default: Any = ..., **constraints: Any) -> Any:
    """A setting: its one-line doc and its default (none: required)."""
    return Field(default, description=doc, **constraints)


class Section(BaseModel):
    """A section of a params file (or a mapping inside one): every key known, typed, frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    #: ``file:section`` of a section the file gives partially (None: complete).
    _missing_in: str | None = PrivateAttr(None)
    _reword = model_validator(mode="wrap")(classmethod(fmt.reword))

    def __getattr__(self, name: str) -> Any:
        # A required key a partial section lacks: the error that names it, where it is read.
        where = (self.__pydantic_private__ or {}).get("_missing_in")
        if where and name in type(self).__pydantic_fields__:
            from femcal.settings.params import missing_setting

            path, section = where.rsplit(":", 1)
            raise missing_setting(path, f"{section}.{name}")
        return super().__getattr__(name)


class Keywords(Section):
    """The keyword arguments of a function that a mapping of the params file sets, each
    optional (the function's default). ``_owner`` names the function in messages;
    ``_reasons``: keyword not settable there -> why, and the fix."""

    _owner: ClassVar[str] = "function"
    _reasons: ClassVar[dict[str, str]] = {}


def keyword(doc: str) -> Any:
    """A keyword argument: its doc; unset, the function's own default applies."""
    return Field(None, description=doc)


def plain(model: type, *, typed: bool = False) -> Any:
    """A mapping validated against ``model`` (null: empty), kept as given or, ``typed``, as
    key -> validated value of the keys given (in their order)."""

    adapter = TypeAdapter(model)

    def keep(value: Any, handler: Any) -> Any:
        value = {} if value is None else value
        checked = adapter.validate_python(value)
        if not typed:
            return dict(value) if isinstance(value, dict) else value
        names, given = fmt.keys_of(model), checked.model_fields_set
        order = list(value) if isinstance(value, dict | list | tuple) else list(names)
        return {k: getattr(checked, names[k]) for k in order if names[k] in given}

    return Annotated[dict[str, Any], WrapValidator(keep), fmt.PlainOf(model)]


# ------------------------------------------------------------------ options dataclasses
def option(default: Any, doc: str) -> Any:
    """An option of an options dataclass (``DiagnoseOptions``, ...): its default and doc; its
    annotation bounds it. Sections, the command line and :func:`check_options` read all three."""
    return dataclasses.field(default=default, metadata={"doc": doc})


class OptionError(ConfigError):
    """A value an options dataclass refuses: ``owner: text.``; ``key`` names the option."""

    def __init__(self, owner: str, key: str, text: str) -> None:
        super().__init__(f"{owner}: {text}.")
        self.key, self.text = key, text


@functools.cache
def option_fields(cls: type) -> dict[str, tuple[Any, Any, str]]:
    """Option -> (annotation, default, doc) of the fields of an options dataclass declared
    with :func:`option`, in declaration order (its other fields are the library's alone);
    an annotation is read in the module of the class declaring it (a base's too)."""
    names = ChainMap(*(vars(sys.modules[c.__module__]) for c in cls.__mro__))
    return {
        f.name: (eval(f.type, {}, names) if isinstance(f.type, str) else f.type, f.default, doc)
        for f in dataclasses.fields(cls)
        if (doc := f.metadata.get("doc")) is not None
    }


@functools.cache
def _adapter(annotation: Any) -> TypeAdapter:
    return TypeAdapter(annotation)


def check_options(options: Any, owner: str) -> None:
    """Check each option of an options dataclass against its annotation (pydantic validates;
    NumPy scalars as the numbers they hold, a ``Path`` as its text) and store it conformed (int,
    float, tuple); OptionError: ``owner: alpha must be in (0, 1); got 1.5. alpha: <its doc>.``"""
    for name, (annotation, _, doc) in option_fields(type(options)).items():
        value = getattr(options, name)
        given = value.item() if hasattr(value, "dtype") and hasattr(value, "item") else value
        path = isinstance(given, os.PathLike)  # a Path is checked as its text and kept
        try:
            fixed = _adapter(annotation).validate_python(os.fspath(given) if path else given)
        except ValidationError as exc:
            error = exc.errors(include_url=False)[0]
            words = fmt.describe(annotation).replace(" or null", " or None")
            words = re.sub(r"^a number (?=[<>i])", "", words)
            text = f"{name} must be {words}; got {value!r}. {name}: {doc}"
            if error["type"] in fmt.CUSTOM:  # a check of the type's own (e.g. no repeats)
                text = f"{name}: {error['msg']}"
            elif words.startswith("one of "):
                text = f"unknown {name} {value!r}; choose {words}"
            raise OptionError(owner, name, text) from None
        if fixed is not value and not path:
            object.__setattr__(options, name, fixed)


class OptionSection(Section):
    """A section (or keyword table) holding the options of an options dataclass
    (``_options``): each checked as declared there, those given together by the dataclass'
    own cross-checks (:func:`with_options` adds the fields)."""

    _options: ClassVar[type]

    def options(self) -> dict[str, Any]:
        """The dataclass' keywords this section sets (a keyword table: those given)."""
        names = option_fields(self._options)
        given = self.model_fields_set if isinstance(self, Keywords) else names
        return {k: getattr(self, k) for k in names if k in given}

    @model_validator(mode="after")
    def _together(self) -> Any:
        try:
            self._options(**OptionSection.options(self))
        except OptionError as exc:
            raise fail(exc.text, exc.key) from None
        return self


def with_options(base: type | None = None, /, **fields: Any) -> Any:
    """Class decorator: the section or keyword table ``base`` with one more field per item of
    ``fields`` (key -> (annotation, Field)) or, without them, per option of ``base._options``
    (its annotation, doc and default; in a keyword table None, the function's own default)."""
    if base is None:
        return lambda cls: with_options(cls, **fields)
    unset = issubclass(base, Keywords)
    fields = fields or {
        key: (tp, Field(None if unset else default, description=what))
        for key, (tp, default, what) in option_fields(base._options).items()
    }
    where = {"__doc__": base.__doc__, "__module__": base.__module__}
    return create_model(base.__name__, __base__=base, **where, **fields)
