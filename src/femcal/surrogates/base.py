"""The surrogate contract and its registry of names.

A surrogate follows scikit-learn's estimator contract: ``__init__`` only stores its
arguments, ``fit(X, y)`` learns and returns ``self``, fitted attributes end in ``_``.
``X`` is a table with the columns ``load_case``, ``moment_nm`` and the parameter names of
the surrogate's :class:`~femcal.space.ParameterSpace`, in physical units; ``y`` is the RoM in
degrees. ``predict(X)`` returns RoM in degrees, shape (n,).

A new surrogate is one file: a class decorated with :func:`register_surrogate`, its module
listed in the registry's ``builtins`` (:data:`surrogate_registry`, a
:class:`~femcal.registry.Registry`). A package can also provide surrogates through the
entry-point group ``femcal.surrogates`` (a module that registers its classes on import, or a
class, registered under the entry point's name).
Only registered classes are loaded from saved models (:func:`trusted_surrogate_class`).

The baselines the ``baselines`` stage fits and the ``evaluate`` stage scores are a registry of
their own (:data:`baseline_registry`, :class:`Baseline`, :func:`register_baseline`, entry-point
group ``femcal.baselines``): a surrogate that also saves itself into a folder and loads back.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError, UntrustedArtifactError
from femcal.registry import Registry
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace


@runtime_checkable
class Surrogate(Protocol):
    """What every surrogate offers."""

    def fit(self, X: pd.DataFrame, y: np.ndarray) -> Surrogate: ...

    def predict(self, X: pd.DataFrame) -> np.ndarray: ...


#: Entry-point group of installed surrogate plugins.
ENTRY_POINT_GROUP = "femcal.surrogates"


def _set_registry_name(name: str, cls: Any) -> None:
    """A surrogate class knows the name it is registered under (``registry_name``)."""
    if not isinstance(cls, type):
        raise ConfigError(
            f"A surrogate is registered as a class (its instances fit and predict); got "
            f"{cls!r} for '{name}'. Register the class."
        )
    cls.registry_name = name


#: The surrogate registry: the built-in surrogates (baselines, the network) and installed
#: plugins (entry points of :data:`ENTRY_POINT_GROUP`).
surrogate_registry: Registry[type] = Registry(
    "surrogate",
    group=ENTRY_POINT_GROUP,
    builtins=("femcal.surrogates.baselines", "femcal.surrogates.nn"),
    fix=(
        'Or register your own: a class decorated with @register_surrogate("name"), in a '
        f"package with an entry point in the group {ENTRY_POINT_GROUP}."
    ),
    accepts=lambda obj: isinstance(obj, type),
    expects="a surrogate class",
    on_register=_set_registry_name,
)


def register_surrogate(name: str, *, replace: bool = False) -> Callable[[type], type]:
    """Class decorator: make a surrogate available under ``name`` (sets ``registry_name``).

    ConfigError if another class already holds ``name`` (unless ``replace=True``).
    """
    return surrogate_registry.register(name, replace=replace)


def available_surrogates() -> list[str]:
    """Registered surrogate names, sorted."""
    return surrogate_registry.names()


def get_surrogate(name: str) -> type:
    """The surrogate class registered as ``name`` (ConfigError listing the names otherwise)."""
    return surrogate_registry.get(name)


def make_surrogate(name: str, **kwargs: Any) -> Surrogate:
    """Build the surrogate registered as ``name`` with keyword arguments ``kwargs``."""
    return surrogate_registry.create(name, **kwargs)


@runtime_checkable
class Baseline(Protocol):
    """What a baseline offers: a surrogate the ``baselines`` stage fits and saves, and the
    ``evaluate`` stage loads back and scores.

    ``cls(space, *, seed, n_jobs)`` builds it (``space`` a
    :class:`~femcal.space.ParameterSpace`, ``seed`` an int, the only source of randomness,
    ``n_jobs`` the threads it may use); ``fit(X, y)`` and ``predict(X)`` as
    :class:`Surrogate` (``X`` n rows, ``y`` and the prediction RoM in degrees, shape (n,));
    ``save(folder)`` writes the fitted model into a folder, and the classmethod
    ``load(folder)`` reads it back.
    """

    def fit(self, X: pd.DataFrame, y: np.ndarray) -> Baseline: ...

    def predict(self, X: pd.DataFrame) -> np.ndarray: ...

    def save(self, path: str | Path) -> None: ...

    @classmethod
    def load(cls, path: str | Path) -> Baseline: ...


#: Entry-point group of installed baseline plugins.
BASELINE_GROUP = "femcal.baselines"


def _check_baseline(name: str, cls: Any) -> None:
    """A baseline is registered as a class with ``fit``, ``predict``, ``save`` and ``load``."""
    missing = [m for m in ("fit", "predict", "save", "load") if not hasattr(cls, m)]
    if not isinstance(cls, type) or missing:
        raise ConfigError(
            f"A baseline is registered as a class with fit, predict, save and load "
            f"(femcal.surrogates.base.Baseline); got {cls!r} for '{name}'"
            + (f", without {', '.join(missing)}" if isinstance(cls, type) else "")
            + ". Register such a class."
        )


#: The baseline registry: the study's model zoo the ``baselines`` stage fits
#: (``baselines.models``) and installed plugins (entry points of :data:`BASELINE_GROUP`).
baseline_registry: Registry[type] = Registry(
    "baseline",
    group=BASELINE_GROUP,
    builtins=("femcal.surrogates.baselines",),
    fix=(
        'Or register your own: a class decorated with @register_baseline("name"), in a '
        f"package with an entry point in the group {BASELINE_GROUP}."
    ),
    accepts=lambda obj: isinstance(obj, type),
    expects="a baseline class",
    on_register=_check_baseline,
)


def register_baseline(name: str, *, replace: bool = False) -> Callable[[type], type]:
    """Class decorator: make a baseline available under ``name`` (``baselines.models``).

    ConfigError if another class already holds ``name`` (unless ``replace=True``), or the
    class lacks one of ``fit``, ``predict``, ``save``, ``load`` (:class:`Baseline`).
    """
    return baseline_registry.register(name, replace=replace)


def available_baselines() -> list[str]:
    """Registered baseline names, sorted."""
    return baseline_registry.names()


def get_baseline(name: str) -> type:
    """The baseline class registered as ``name`` (ConfigError listing the names otherwise)."""
    return baseline_registry.get(name)


def make_baseline(name: str, **kwargs: Any) -> Baseline:
    """Build the baseline registered as ``name`` with keyword arguments ``kwargs``."""
    return baseline_registry.create(name, **kwargs)


def trusted_surrogate_classes() -> dict[str, type]:
    """The classes a saved model may name as its loader, by ``"module:QualName"``.

    Those of femcal's surrogate registry: the built-in surrogates, those installed through the
    ``femcal.surrogates`` entry points and those registered in this process.
    """
    return _registered_classes(load=True)


def _registered_classes(*, load: bool) -> dict[str, type]:
    """Registered surrogate classes by ``"module:QualName"`` (``load=False``: those so far)."""
    return {
        f"{cls.__module__}:{cls.__qualname__}": cls
        for _, cls in surrogate_registry.items(load=load)
        if isinstance(cls, type)
    }


def trusted_surrogate_class(spec: Any, *, source: str) -> type:
    """The registered surrogate class ``spec`` (``"module:QualName"``) names, or an error.

    Nothing is imported on the file's say-so: ``spec`` is looked up among the registered
    classes, so a saved model cannot make femcal import or call anything else. A class of a
    built-in module is looked up after importing that module alone (the neural surrogate's
    loader imports no model zoo); any other after loading the whole registry.

    Parameters
    ----------
    spec : str
        The loader named by a saved model (its ``femcal_loader.json``).
    source : str
        Where ``spec`` was read (the file), for the message.

    Returns
    -------
    type
        The class; its ``load(folder)`` rebuilds the surrogate from data files.

    Raises
    ------
    UntrustedArtifactError
        ``spec`` is not a registered surrogate class, or that class cannot ``load``.
    """
    named = isinstance(spec, str)
    found: dict[str, type] = {}
    if named and surrogate_registry.import_builtin(spec.partition(":")[0]):
        # femcal's own module, imported alone: the network's loader needs no scikit-learn
        # model zoo, no LightGBM, no plugin
        found = _registered_classes(load=False)
    classes = found if named and spec in found else _registered_classes(load=True)
    cls = classes.get(spec) if named else None
    if cls is None:
        raise UntrustedArtifactError(
            f"{source} names the class {spec!r}, which is not a registered femcal surrogate; "
            "femcal refuses to import it (a model could otherwise run any code it names). "
            f"Trusted classes: {', '.join(sorted(classes))}. If the class is yours, register "
            "it with @register_surrogate in a package installed with an entry point in the "
            f"group '{ENTRY_POINT_GROUP}', then load again; otherwise do not load this model."
        )
    if not callable(getattr(cls, "load", None)):
        raise UntrustedArtifactError(
            f"{source} names {spec!r}, a registered surrogate without a load(folder) "
            "classmethod, so it cannot be loaded from a saved model. Give the class save(folder) "
            "and load(folder)."
        )
    return cls


def check_features(X: pd.DataFrame, space: ParameterSpace, *, what: str = "X") -> None:
    """Raise :class:`InputDataError` unless ``X`` has the columns a surrogate needs."""
    if not isinstance(X, pd.DataFrame):
        raise InputDataError(
            f"{what} must be a pandas DataFrame with columns load_case, moment_nm and "
            f"{', '.join(space.names)}; got {type(X).__name__}."
        )
    needed = ["load_case", "moment_nm", *space.names]
    missing = [c for c in needed if c not in X.columns]
    if missing:
        raise InputDataError(
            f"{what} lacks the column(s) {missing}. A surrogate needs load_case, moment_nm and "
            f"the parameters {', '.join(space.names)} in physical units."
        )
    bad = sorted(set(X["load_case"].astype(str)) - set(LOAD_CASES))
    if bad:
        raise InputDataError(
            f"{what}: unknown load_case value(s) {bad}; valid names are {', '.join(LOAD_CASES)}."
        )
    numeric = X[["moment_nm", *space.names]]
    if numeric.isna().any().any():
        cols = numeric.columns[numeric.isna().any()].tolist()
        raise InputDataError(f"{what}: NaN in column(s) {cols}; fill or drop those rows first.")


def encode_features(X: pd.DataFrame, space: ParameterSpace) -> np.ndarray:
    """Design matrix shared by the tabular baselines.

    Parameters
    ----------
    X : DataFrame, n rows
        Columns ``load_case``, ``moment_nm`` and the parameter names (physical units).
    space : ParameterSpace
        Maps the parameters to the unit box.

    Returns
    -------
    ndarray, shape (n, 4 + 1 + d)
        One-hot load case (order of :data:`~femcal.schema.LOAD_CASES`), moment in Nm,
        parameters in the unit box.
    """
    check_features(X, space)
    lc = X["load_case"].astype(str).to_numpy()
    onehot = (lc[:, None] == np.asarray(LOAD_CASES)[None, :]).astype(float)
    moment = X["moment_nm"].to_numpy(dtype=float)[:, None]
    params = space.to_unit(X[list(space.names)].to_numpy(dtype=float))
    return np.hstack([onehot, moment, params])


#: Smallest |prediction| (deg) a relative error is taken against.
RELATIVE_FLOOR_DEG = 0.01


def error_profile(
    moments: np.ndarray, error: np.ndarray, prediction: np.ndarray | None = None
) -> dict[str, list[float]] | None:
    """The root-mean-square error at each distinct moment, absolute and relative.

    Parameters
    ----------
    moments : ndarray, shape (n,)
        The rows' moments, Nm.
    error : ndarray, shape (n,)
        Prediction minus truth, deg (non-finite rows are left out).
    prediction : ndarray, shape (n,), optional
        The predictions, deg: the relative error is ``error / |prediction|`` (``|prediction|``
        floored at :data:`RELATIVE_FLOOR_DEG`).

    Returns
    -------
    dict or None
        ``{"moments": [...], "rms_deg": [...], "relative_rms": [...]}`` (the last with
        ``prediction`` only), moments ascending; None when no row is finite.
    """
    moments, error = np.asarray(moments, dtype=float), np.asarray(error, dtype=float)
    ok = np.isfinite(error) & np.isfinite(moments)
    if not ok.any():
        return None
    levels, index = np.unique(np.round(moments[ok], 6), return_inverse=True)
    count = np.bincount(index)
    out = {
        "moments": levels.tolist(),
        "rms_deg": np.sqrt(np.bincount(index, error[ok] ** 2) / count).tolist(),
    }
    if prediction is not None:
        scale = np.maximum(np.abs(np.asarray(prediction, dtype=float)[ok]), RELATIVE_FLOOR_DEG)
        rel = np.sqrt(np.bincount(index, (error[ok] / scale) ** 2) / count)
        out["relative_rms"] = rel.tolist()
    return out
