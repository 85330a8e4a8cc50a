"""Exception hierarchy: one root, mixed with the matching built-in type."""


class FemcalError(Exception):
    """Root of every error femcal raises on purpose."""


class InputDataError(FemcalError, ValueError):
    """A user-supplied file or table is malformed (names the file, the field and the fix)."""


class ChecksumError(FemcalError, ValueError):
    """A downloaded or mirrored file does not match its pinned SHA-256."""


class DataSourceError(FemcalError, OSError):
    """A data file could not be obtained (missing in the mirror, download failed)."""


class ConfigError(FemcalError, ValueError):
    """A setting (params.yaml, argument, environment variable) is invalid."""


class ModelRegistryError(FemcalError, LookupError):
    """A model could not be found in, or loaded from, the MLflow registry."""


try:
    from sklearn.exceptions import NotFittedError as _NotFittedError
except ImportError:  # pragma: no cover - scikit-learn is a dependency
    _NotFittedError = AttributeError


class SurrogateNotFittedError(FemcalError, _NotFittedError):
    """``predict`` was called before ``fit`` (also scikit-learn's ``NotFittedError``)."""


class SolverError(FemcalError, RuntimeError):
    """An FE solver is missing or cannot start (failed simulations are data, not errors)."""
