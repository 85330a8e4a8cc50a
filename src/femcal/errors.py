"""Exception hierarchy: one root, mixed with the matching built-in type; and how a message
lists things (:func:`listed`)."""

import threading


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


class UntrustedArtifactError(FemcalError, ValueError):
    """A saved model names code or types femcal does not trust (names the file and the fix)."""


class OutputFolderError(FemcalError, OSError):
    """An output folder cannot take a run's outputs (a file, files femcal did not write, not
    writable); names the folder, what is in the way and the fix."""


class SolverError(FemcalError, RuntimeError):
    """An FE solver is missing or cannot start (failed simulations are data, not errors)."""


class FemcalWarning(UserWarning):
    """A warning femcal also logs where it arises: the command line prints the log line only;
    a library caller can catch or filter it as a ``UserWarning``."""


_lazy_lock = threading.Lock()


def _surrogate_not_fitted_error() -> type:
    try:
        from sklearn.exceptions import NotFittedError as base
    except ImportError:  # pragma: no cover - scikit-learn is a dependency
        base = AttributeError

    class SurrogateNotFittedError(FemcalError, base):
        """``predict`` was called before ``fit`` (also scikit-learn's ``NotFittedError``)."""

    SurrogateNotFittedError.__module__ = __name__
    SurrogateNotFittedError.__qualname__ = "SurrogateNotFittedError"
    return SurrogateNotFittedError


def __getattr__(name: str) -> type:
    # SurrogateNotFittedError derives from scikit-learn's NotFittedError; scikit-learn takes
    # seconds to import, so it is created on first use, not when any femcal error is needed.
    if name == "SurrogateNotFittedError":
        with _lazy_lock:
            if name not in globals():
                globals()[name] = _surrogate_not_fitted_error()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def listed(items, *, total: int | None = None, most: int = 6, sep: str = ", ") -> str:
    """How a message lists things: the first ``most`` of ``items`` joined by ``sep``, and a
    count of the rest.

    Parameters
    ----------
    items : sequence of str
        The items, already in words.
    total : int, optional
        How many there are in all (default ``len(items)``), when ``items`` holds only some.
    most : int
        How many are shown.
    sep : str
        What joins them.

    Returns
    -------
    str
        For example ``"a, b (and 3 more)"``.
    """
    total = len(items) if total is None else total
    more = f" (and {total - most} more)" if total > most else ""
    return sep.join(list(items)[:most]) + more
